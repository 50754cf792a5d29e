"""Optional dependencies the benchmarks compare against, and whether this environment has them."""

from __future__ import annotations

import warnings

__all__ = ["dompc_available"]


def dompc_available() -> tuple[bool, str]:
    """(True, version) when do-mpc imports, else (False, why)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import do_mpc  # noqa: F401
        return True, getattr(do_mpc, "__version__", "?")
    except Exception as exc:  # noqa: BLE001 - any import problem means "not available"
        return False, f"do-mpc is not installed ({exc}); install the extra: pip install 'hbma-ctrl[bench]'"
