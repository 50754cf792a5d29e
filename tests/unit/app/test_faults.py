"""Fault injection: every kind shows in the readings or in the command the rig receives, only on
its chambers and only in its time window; [[daemon.fault]] tables parse to SI or give one clear error."""

from __future__ import annotations

import numpy as np
import pytest

from hbma_ctrl.app.daemon.faults import INJECTED_KINDS, FaultSpec, FaultyRig, parse_faults
from hbma_ctrl.system.rigio import Readings, RigLinkError, safe_u

TS = 0.01


class ScriptRig:
    """A 3-chamber RigIO whose chamber i reads 1000 * (i + 1) + k Pa at period k; records what it gets."""

    n, sample_period = 3, TS

    def __init__(self):
        self.k = 0
        self.written: list = []
        self.safe_calls = 0

    def read(self):
        return Readings(t=self.k * TS, p=1000.0 * np.arange(1, 4) + self.k, seq=self.k, fresh=np.ones(3, dtype=bool))

    def write(self, u):
        self.written.append(np.array(u))
        self.k += 1

    def safe(self):
        self.safe_calls += 1

    def close(self):
        pass


CMD = np.array([[0.7, 0.7, 0.7], [0.6, 0.6, 0.6], [0.1, 0.1, 0.1]])


def drive(faults, steps=8, u=CMD):
    """Readings and received commands per period, on ScriptRig behind FaultyRig."""
    inner = ScriptRig()
    rig = FaultyRig(inner, faults)
    reads = []
    for _ in range(steps):
        reads.append(rig.read())
        rig.write(u)
    return reads, inner.written


def clean(k):
    return 1000.0 * np.arange(1, 4) + k


def test_without_faults_everything_passes_through():
    reads, written = drive([])
    for k, r in enumerate(reads):
        assert np.array_equal(r.p, clean(k)) and r.fresh.all() and r.seq == k
    assert all(np.array_equal(w, CMD) for w in written)


def test_dropout_is_nan_on_its_chamber_in_its_window_only():
    reads, _ = drive([FaultSpec("dropout", chamber=1, start=0.02, duration=0.03)])
    for k, r in enumerate(reads):
        hit = 2 <= k < 5
        assert np.isnan(r.p[1]) == hit
        assert np.array_equal(r.p[[0, 2]], clean(k)[[0, 2]])


def test_the_periods_each_fault_acted_are_counted():
    rig = FaultyRig(ScriptRig(), [FaultSpec("dropout", 0, 0.02, 0.03), FaultSpec("pump_failure", 1, 0.05)])
    for _ in range(8):
        rig.read()
        rig.write(CMD)
    assert rig.injected["dropout"] == 3 and rig.injected["pump_failure"] == 3 and rig.injected["leak"] == 0


def test_frozen_repeats_the_last_value_before_it_and_is_not_fresh():
    reads, _ = drive([FaultSpec("frozen", chamber=None, start=0.03)])
    for k, r in enumerate(reads):
        if k < 3:
            assert np.array_equal(r.p, clean(k)) and r.fresh.all()
        else:
            assert np.array_equal(r.p, clean(2)) and not r.fresh.any()


def test_offset_adds_its_value():
    reads, _ = drive([FaultSpec("offset", chamber=2, start=0.0, value=3000.0)])
    for k, r in enumerate(reads):
        assert r.p[2] == clean(k)[2] + 3000.0 and r.p[0] == clean(k)[0]


def test_out_of_range_reports_its_value():
    reads, _ = drive([FaultSpec("out_of_range", chamber=0, start=0.05, value=-60e3)])
    assert [r.p[0] for r in reads[5:]] == [-60e3] * 3 and reads[4].p[0] == clean(4)[0]


@pytest.mark.parametrize("kind,row,value,expect", [
    ("stuck_inlet", 1, 1.0, 1.0),
    ("stuck_inlet", 1, 0.0, 0.0),
    ("stuck_outlet", 2, 0.0, 0.0),
    ("leak", 2, 0.3, 0.4),  # 0.1 commanded + 0.3 extra
    ("leak", 2, 1.0, 1.0),  # at most fully open
    ("pump_failure", 0, 0.0, 0.0),
])
def test_actuator_faults_change_what_the_rig_receives(kind, row, value, expect):
    reads, written = drive([FaultSpec(kind, chamber=1, start=0.02, duration=0.04, value=value)])
    for k, w in enumerate(written):
        if 2 <= k < 6:
            assert w[row, 1] == pytest.approx(expect)
            w = w.copy()
            w[row, 1] = CMD[row, 1]
        assert np.array_equal(w, CMD)  # every other entry as commanded


def test_the_loops_command_array_is_not_modified():
    u = CMD.copy()
    drive([FaultSpec("stuck_inlet", start=0.0, value=1.0)], u=u)
    assert np.array_equal(u, CMD)


def test_link_loss_raises_in_its_window_and_the_link_comes_back():
    rig = FaultyRig(ScriptRig(), [FaultSpec("link_loss", start=0.02, duration=0.02)])
    for k in range(6):
        if 2 <= k < 4:
            with pytest.raises(RigLinkError, match="link lost"):
                rig.read()
        else:
            rig.read()
        rig.write(CMD)


def test_rig_time_without_stamps_counts_writes():
    class NoStamp(ScriptRig):
        def read(self):
            r = super().read()
            return Readings(t=None, p=r.p, seq=-1, fresh=np.ones(0, dtype=bool))

    rig = FaultyRig(NoStamp(), [FaultSpec("dropout", chamber=0, start=0.03)])
    got = []
    for _ in range(5):
        got.append(bool(np.isnan(rig.read().p[0])))
        rig.write(CMD)
    assert got == [False, False, False, True, True]


def test_safe_goes_straight_to_the_rig():
    inner = ScriptRig()
    FaultyRig(inner, [FaultSpec("stuck_inlet", start=0.0, value=1.0)]).safe()
    assert inner.safe_calls == 1 and inner.written == []


def test_in_the_safe_state_a_stuck_inlet_stays_stuck():
    reads, written = drive([FaultSpec("stuck_inlet", chamber=0, start=0.0, value=1.0)], steps=2, u=safe_u(3))
    assert written[0][1, 0] == 1.0 and written[0][1, 1] == 0.0


# --- [[daemon.fault]] ---------------------------------------------------------------------------------

def test_tables_parse_to_si():
    specs = parse_faults([
        {"kind": "offset", "chamber": 2, "start_s": 1.5, "duration_s": 0.5, "offset_kpa": -3.0},
        {"kind": "out_of_range", "value_kpa": -60.0},
        {"kind": "leak", "chamber": "all", "duty": 0.25},
        {"kind": "link_loss", "start_s": 4.0},
    ], n=3)
    assert specs[0] == FaultSpec("offset", 2, 1.5, 0.5, -3000.0)
    assert specs[1] == FaultSpec("out_of_range", None, 0.0, None, -60000.0)
    assert specs[2] == FaultSpec("leak", None, 0.0, None, 0.25)
    assert specs[3] == FaultSpec("link_loss", None, 4.0, None, 0.0)
    assert parse_faults(None) == []


def test_every_kind_has_a_table():
    value = {"offset": {"offset_kpa": 1.0}, "out_of_range": {"value_kpa": 99.0}, "stuck_inlet": {"duty": 1.0},
             "stuck_outlet": {"duty": 0.0}, "leak": {"duty": 0.5}}
    specs = parse_faults([{"kind": k, **value.get(k, {})} for k in INJECTED_KINDS])
    assert [s.kind for s in specs] == list(INJECTED_KINDS)


@pytest.mark.parametrize("row,message", [
    ({"kind": "ofset", "offset_kpa": 1.0}, "[daemon.fault[0]] kind = 'ofset' is not allowed; did you mean 'offset'?"),
    ({}, "[daemon.fault[0]] kind is required"),
    ({"kind": "offset"}, "[daemon.fault[0]] kind 'offset' needs offset_kpa"),
    ({"kind": "offset", "offset_kpa": 500.0}, "[daemon.fault[0]] offset_kpa = 500.0 is out of range [-100, 100] kPa"),
    ({"kind": "leak", "duty": 1.5}, "[daemon.fault[0]] duty = 1.5 is out of range [0, 1]"),
    ({"kind": "leak", "duty": 0.3, "offset_kpa": 1.0}, "offset_kpa: not a key of kind 'leak' (it takes duty)"),
    ({"kind": "dropout", "duty": 0.3}, "duty: not a key of kind 'dropout' (it takes no value key)"),
    ({"kind": "dropout", "chamber": "first"}, "chamber = 'first' must be a chamber index >= 0 or \"all\""),
    ({"kind": "dropout", "chamber": -1}, "chamber = -1 must be a chamber index >= 0"),
    ({"kind": "dropout", "chamber": 3}, "chamber = 3 is out of range: the rig has 3 chamber(s), allowed 0..2"),
    ({"kind": "dropout", "start_s": -1.0}, "start_s = -1.0 is out of range [0, 1e+06] s"),
    ({"kind": "dropout", "duration_s": 0.0}, "duration_s = 0.0 is out of range (0, 1e+06] s"),
    ({"kind": "dropout", "start": 1.0}, "start: unknown key"),
])
def test_bad_tables_give_one_clear_error(row, message):
    with pytest.raises(ValueError) as e:
        parse_faults([row], n=3)
    text = str(e.value)
    assert message in text and "\n" not in text


def test_the_error_names_the_table_it_is_in():
    with pytest.raises(ValueError, match=r"^\[daemon\.fault\[1\]\] offset_kpa"):
        parse_faults([{"kind": "dropout"}, {"kind": "offset", "offset_kpa": "3"}])


def test_not_an_array_of_tables():
    with pytest.raises(ValueError, match=r"\[\[daemon.fault\]\]"):
        parse_faults({"kind": "dropout"})
    with pytest.raises(ValueError, match=r"\[daemon.fault\[0\]\] must be a table"):
        parse_faults(["dropout"])


def test_a_rig_refuses_a_fault_on_a_chamber_it_does_not_have():
    with pytest.raises(ValueError, match="allowed 0..2"):
        FaultyRig(ScriptRig(), [FaultSpec("dropout", chamber=5)])
