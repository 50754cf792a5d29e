"""``hbma-ctrl bench soak``: the rig daemon run for a long time with setpoints sent through its API.

The daemon runs as its own process (``hbma-ctrl daemon CONFIG --rig sim --speed X --duration-s T
--api 127.0.0.1:PORT``), exactly as a user starts it; this process is the API's client. Every
``every_s`` of rig time (read from ``GET /status``) it posts a random target through
``POST /setpoint``: a pose for every layer of a robot (centre 5-8 mm, bend 0-15 deg, any
direction) or a height for every chamber of a single-chamber rig (2-8 mm), drawn from ``seed``.

At the end it judges the daemon's ``daemon_stats.json`` against the soak's criteria (README "Run on
a rig / Measured"):

- ``no_fault``: no fault of any kind, and the run ended by its duration;
- ``no_tick_over_period``: no runtime tick (estimator, controller, supervisor) longer than the rig's
  period (``steps_over_period``: accelerated, by its thread's CPU time, the loop's module doc says
  why; ``deadline_misses`` counts whole steps, simulated plant included, against the wall period,
  which an accelerated simulation may never meet; ``steps_over_period_wall`` counts wall-clock
  ticks over the period, which depend on what else the machine runs);
- ``pressure_limit_held``: the highest reading at or under the controller's pressure limit;
- ``rss_growth_under_10mb``: resident memory grew by less than 10 MB;
- ``safe_exit``: the safe command was written at the end.

Writes ``soak.json`` (the verdicts, the daemon's stats, the setpoints sent and their replies) and
``setpoints.csv`` beside the daemon's own results (``daemon/``), through
:func:`hbma_ctrl.app.outputs.run_dir`.
"""

from __future__ import annotations

import csv
import json
import os
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

from hbma_ctrl.app.metrics import json_safe
from hbma_ctrl.app.outputs import run_dir

__all__ = ["run_soak", "soak_verdicts", "random_target", "RSS_GROWTH_MAX_MB"]

#: the soak's memory criterion, MB
RSS_GROWTH_MAX_MB = 10.0


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def random_target(rng: random.Random, n_layers: int, n_chambers: int) -> dict:
    """One random setpoint body (edge units) for the robot's layers or the rig's chambers."""
    if n_layers:
        return {"layers": [{"layer": i, "centre_mm": round(rng.uniform(5.0, 8.0), 2),
                            "bend_deg": round(rng.uniform(0.0, 15.0), 1),
                            "direction_deg": round(rng.uniform(-180.0, 180.0), 0)} for i in range(n_layers)]}
    return {"heights_mm": {str(i): round(rng.uniform(2.0, 8.0), 2) for i in range(n_chambers)}}


def soak_verdicts(stats: dict) -> dict:
    """The soak's criteria (module doc) from a daemon_stats.json dict: {name: bool}."""
    rss0, rss1 = stats.get("rss_mb_start"), stats.get("rss_mb_end")
    pmax, plim = stats.get("max_pressure_kpa"), stats.get("pressure_limit_kpa")
    return {
        "no_fault": not stats.get("faults") and stats.get("end_reason") == "duration",
        "no_tick_over_period": stats.get("steps_over_period") == 0,
        "pressure_limit_held": pmax is not None and plim is not None and pmax <= plim,
        "rss_growth_under_10mb": rss0 is not None and rss1 is not None and rss1 - rss0 < RSS_GROWTH_MAX_MB,
        "safe_exit": bool(stats.get("safe_exit")),
    }


def run_soak(config: Path, out: Path, duration_s: float, speed: float, every_s: float, seed: int,
             overwrite: bool = False, argv: list | None = None, echo=print) -> dict:
    """Run the soak (module doc) into ``out``; returns soak.json's content. Times in s of rig time."""
    rng = random.Random(seed)
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    with run_dir(out, command="bench soak", argv=argv, scenario_path=config, overwrite=overwrite) as tmp:
        cmd = [sys.executable, "-m", "hbma_ctrl", "daemon", str(config), "--rig", "sim", "--speed", repr(speed),
               "--duration-s", repr(duration_s), "--api", f"127.0.0.1:{port}", "--out", str(tmp / "daemon")]
        err_path = tmp / "daemon_stderr.txt"
        sent: list[dict] = []
        with open(err_path, "w") as err:
            proc = subprocess.Popen(cmd, stdout=err, stderr=subprocess.STDOUT, env=dict(os.environ))
            # a stop (Ctrl-C, or SIGTERM/SIGINT to a soak started in the background, where the shell
            # ignores SIGINT) stops the daemon too, through its own safe exit
            old = {sig: signal.signal(sig, _raise_interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
            try:
                _drive(proc, url, rng, every_s, duration_s, sent, echo)
                rc = proc.wait()
            except BaseException:
                # the daemon writes the safe command on SIGTERM; the soak's results stay readable
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=30)
                raise
            finally:
                for sig, h in old.items():
                    signal.signal(sig, h)
        stats_path = tmp / "daemon" / "daemon_stats.json"
        if not stats_path.exists():
            tail = err_path.read_text().strip().splitlines()[-1:] or ["(no output)"]
            raise ValueError(f"the daemon ended (exit {rc}) without daemon_stats.json: {tail[0]}")
        stats = json.loads(stats_path.read_text())
        verdicts = soak_verdicts(stats)
        with open(tmp / "setpoints.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["rig_t_s", "status", "body", "reply"])
            for s in sent:
                w.writerow([f"{s['rig_t_s']:.2f}", s["status"], json.dumps(s["body"]), json.dumps(s["reply"])])
        result = {"config": str(config), "duration_s": duration_s, "speed": speed, "setpoint_every_s": every_s,
                  "seed": seed, "daemon_exit_code": rc, "setpoints_sent": len(sent),
                  "setpoints_accepted": sum(1 for s in sent if s["status"] == 200),
                  "verdicts": verdicts, "passed": all(verdicts.values()), "daemon_stats": stats}
        (tmp / "soak.json").write_text(json.dumps(json_safe(result), indent=1) + "\n")
    return result


def _drive(proc: subprocess.Popen, url: str, rng: random.Random, every_s: float, duration_s: float,
           sent: list, echo) -> None:
    """Post a random setpoint each ``every_s`` of rig time until the daemon ends."""
    n_layers = n_chambers = None
    next_t = every_s
    last_note = time.monotonic()
    with httpx.Client(base_url=url, timeout=5.0) as client:
        while proc.poll() is None:
            time.sleep(0.5)
            try:
                st = client.get("/status").json()
            except (httpx.HTTPError, ValueError):
                continue  # not up yet, or ending
            if st.get("mode") != "running" or st.get("t_s") is None:
                continue
            if n_layers is None:
                n_layers, n_chambers = len(st.get("layers") or []), len(st.get("chambers") or [])
            t = float(st["t_s"])
            if t >= next_t and t < duration_s - 1.0:
                body = random_target(rng, n_layers, n_chambers)
                try:
                    r = client.post("/setpoint", json=body)
                    sent.append({"rig_t_s": t, "status": r.status_code, "body": body, "reply": r.json()})
                except (httpx.HTTPError, ValueError) as exc:
                    sent.append({"rig_t_s": t, "status": None, "body": body, "reply": str(exc)})
                next_t = (int(t // every_s) + 1) * every_s
            if time.monotonic() - last_note > 60.0:
                last_note = time.monotonic()
                echo(f"soak: rig time {t:.0f} / {duration_s:g} s, {len(sent)} setpoints, mode {st.get('mode')}, "
                     f"faults {st.get('faults', {}).get('counts') or 'none'}")
