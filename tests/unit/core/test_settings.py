"""The settings declarations: one check per declared field, its error naming the field and range, and
the scenario key's name and unit derived from the declaration."""

from dataclasses import dataclass

import pytest

from hbma_ctrl.core.settings import Settings, setting, specs


@dataclass
class _Demo(Settings):
    WHERE = "demo"

    p_max: float = setting(35e3, lo=0.0, hi=1e6, lo_open=True, unit="Pa", user="kPa", doc="pressure limit")
    p_margin: float = setting(1e3, lo=0.0, hi=1e6, unit="Pa", user="kPa", doc="margin below p_max")
    steps: int = setting(3, integer=True, lo=1, hi=10, doc="steps")
    law: str = setting("cap", choices=("cap", "exact"), doc="membrane law")
    on: bool = setting(True, doc="a flag")
    w: tuple = setting((1.0, 2.0), lo=0.0, hi=5.0, doc="weights")
    delay: float = setting(0.005, lo=0.0, hi=0.1, unit="s", user="ms", key="lag_ms", doc="delay")

    def check_rules(self) -> None:
        self.within("p_margin", hi=self.p_max)


@pytest.mark.parametrize("kw,needle", [
    ({"p_max": 0.0}, "demo.p_max = 0.0 is out of range (0.0, 1000000.0] Pa"),
    ({"steps": 2.0}, "demo.steps = 2.0 must be an integer in [1, 10]"),
    ({"steps": True}, "demo.steps = True must be an integer in [1, 10]"),
    ({"law": "exat"}, "demo.law = 'exat' (did you mean 'exact'?): allowed cap, exact"),
    ({"on": 1}, "demo.on = 1 must be true or false"),
    ({"w": (1.0,)}, "demo.w = (1.0,) must have 2 entries"),
    ({"w": (1.0, 6.0)}, "demo.w[1] = 6.0 is out of range [0.0, 5.0]"),
    ({"p_margin": 2e3, "p_max": 1e3}, "demo.p_margin = 2000.0 is out of range [0.0, 1000.0] Pa"),
])
def test_a_bad_value_is_refused_naming_the_field_and_its_range(kw, needle):
    with pytest.raises(ValueError) as exc:
        _Demo(**kw).validate()
    assert str(exc.value) == needle


def test_the_defaults_pass_and_the_scenario_key_follows_the_user_unit():
    assert _Demo().validate() == _Demo()
    sp = specs(_Demo)
    assert sp["p_max"].key_for("p_max") == "p_max_kpa" and sp["delay"].key_for("delay") == "lag_ms"
    assert sp["p_max"].user_bounds() == (0.0, 1000.0) and sp["delay"].to_user(0.005) == 5.0
    assert sp["delay"].to_si(5.0) == pytest.approx(0.005) and sp["w"].to_si([1, 2]) == (1.0, 2.0)
