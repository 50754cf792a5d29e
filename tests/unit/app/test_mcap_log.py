"""The MCAP log's writer and reader: every message round-trips, schemas and metadata are in the file,
a full queue drops and counts, a file cut short reads up to its last whole chunk."""

from __future__ import annotations

import json
import math
import threading

import numpy as np
import pytest
from mcap.reader import make_reader

from hbma_ctrl.app.logs.reader import columns, message_counts, read_mcap
from hbma_ctrl.app.logs.signals import GROUPS, SignalLog, signal_channels
from hbma_ctrl.app.logs.writer import McapLog, json_schema, number_map
from hbma_ctrl.robot.design import RobotDesign
from hbma_ctrl.robot.kinematics import layer_plane

SCHEMA = json_schema("Readings", "test", {"p_kpa": number_map("pressure, kPa")}, ["p_kpa"])


def _messages(n: int) -> list[dict]:
    rng = np.random.default_rng(3)
    return [{"p_kpa": {"C1": float(rng.normal()), "C2": None if i % 7 == 0 else float(i)}} for i in range(n)]


def test_every_message_round_trips_with_its_stamps(tmp_path):
    path = tmp_path / "log.mcap"
    msgs = _messages(1000)
    log = McapLog(path, {"/readings": SCHEMA}, chunk_bytes=4096)
    for i, m in enumerate(msgs):
        assert log.put(i * 0.01, "/readings", m)
    st = log.close()
    c = read_mcap(path)
    assert st["messages"] == 1000 and st["dropped"] == 0 and not c.truncated
    assert c.messages["/readings"] == [{"t_s": i * 0.01, **m} for i, m in enumerate(msgs)]
    assert c.log_ns["/readings"] == [log.start_ns + round(i * 0.01 * 1e9) for i in range(1000)]
    pub = c.publish_ns["/readings"]
    assert all(b >= a for a, b in zip(pub, pub[1:])) and pub[0] >= log.start_ns


def test_channels_carry_their_json_schemas_and_the_file_its_metadata_and_attachments(tmp_path):
    path = tmp_path / "log.mcap"
    log = McapLog(path, {"/readings": SCHEMA}, metadata={"run": {"version": "9.9"}},
                  attachments={"config.toml": ("application/toml", b"[scenario]\nname = 'x'\n")})
    log.put(0.0, "/readings", _messages(1)[0])
    log.close(metadata={"stats": {"steps": "1"}})
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    (chan,) = summary.channels.values()
    schema = summary.schemas[chan.schema_id]
    assert (chan.topic, chan.message_encoding, schema.encoding, schema.name) == ("/readings", "json", "jsonschema",
                                                                                 "Readings")
    assert json.loads(schema.data) == SCHEMA
    c = read_mcap(path)
    assert c.metadata["run"] == {"version": "9.9"} and c.metadata["stats"] == {"steps": "1"}
    assert c.metadata["log"]["messages"] == "1" and c.metadata["log"]["dropped"] == "0"
    assert c.attachments["config.toml"] == ("application/toml", b"[scenario]\nname = 'x'\n")


def test_a_full_queue_drops_the_item_without_blocking_and_counts_it(tmp_path):
    entered, release = threading.Event(), threading.Event()

    def slow(t, payload):  # holds the writer thread until released
        entered.set()
        release.wait(10)
        return [("/readings", payload)]

    log = McapLog(tmp_path / "log.mcap", {"/readings": SCHEMA}, expanders={"slow": slow}, queue_size=3)
    m = _messages(1)[0]
    assert log.put(0.0, "slow", m)
    assert entered.wait(10)  # the writer thread holds the first item: the queue is empty
    accepted = [log.put(0.01 * (i + 1), "/readings", m) for i in range(5)]
    release.set()
    st = log.close()
    assert accepted == [True, True, True, False, False]
    assert (st["dropped"], st["messages"]) == (2, 4)
    assert read_mcap(tmp_path / "log.mcap").metadata["log"]["dropped"] == "2"


def test_a_file_cut_anywhere_reads_back_a_gapless_prefix_and_says_it_is_cut(tmp_path):
    path = tmp_path / "log.mcap"
    msgs = _messages(800)
    log = McapLog(path, {"/readings": SCHEMA}, chunk_bytes=2048, metadata={"run": {"k": "v"}})
    for i, m in enumerate(msgs):
        log.put(i * 0.01, "/readings", m)
    log.close()
    data = path.read_bytes()
    whole = read_mcap(path).messages["/readings"]
    counts = []
    for frac in (0.2, 0.5, 0.8, 0.97):
        cut = tmp_path / f"cut{frac}.mcap"
        cut.write_bytes(data[:int(len(data) * frac)])
        c = read_mcap(cut)
        got = c.messages["/readings"]
        assert c.truncated and c.metadata["run"] == {"k": "v"}
        assert got == whole[:len(got)]
        counts.append(len(got))
    assert counts == sorted(counts) and counts[0] > 0  # later cuts keep more, chunk by chunk


def test_signal_log_writes_each_group_per_period_with_nulls_for_nan(tmp_path):
    names = ["A1", "A2", "A3"]
    log = SignalLog(tmp_path / "log.mcap", names, GROUPS)
    p = np.array([1e3, 2e3, np.nan])
    u = np.array([[0.5, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 1.0]])
    log.period(0.5, p=p, p_est=p + 10.0, h=[1e-3, 2e-3, 3e-3], h_std=[1e-4] * 3, target=[2e-3] * 3, u=u,
               truth=(0.51, [1.1e-3, 2e-3, 3e-3], p), mode="running", step_s=2e-3, faults="")
    log.event(0.5, "setpoint", "A1 2 mm", {"target_A1_mm": 2.0})
    log.close()
    c = read_mcap(tmp_path / "log.mcap")
    assert set(c.messages) == set(signal_channels(GROUPS, robot=False))
    assert c.messages["/readings"] == [{"t_s": 0.5, "p_kpa": {"A1": 1.0, "A2": 2.0, "A3": None}}]
    assert c.messages["/commands"][0]["inlet"] == {"A1": 1.0, "A2": 0.0, "A3": 0.0}
    assert c.messages["/truth"][0]["t_s"] == 0.51 and c.messages["/truth"][0]["h_mm"]["A1"] == pytest.approx(1.1)
    assert c.messages["/loop"][0] == {"t_s": 0.5, "mode": "running", "step_ms": 2.0, "faults": ""}
    assert c.messages["/events"][0]["fields"] == {"target_A1_mm": "2.0"}
    assert columns(c.messages["/estimates"])["h_mm.A2"][0] == pytest.approx(2.0)


def test_signal_log_of_a_robot_gives_each_layers_pose_from_the_heights(tmp_path):
    design = RobotDesign(n_layers=2).validate()
    h = np.array([3e-3, 4e-3, 5e-3, 6e-3, 6e-3, 6e-3])
    log = SignalLog(tmp_path / "log.mcap", design.names, ("estimates", "truth"), design=design)
    log.period(0.0, h=h, truth=(0.0, h, np.zeros(6)))
    log.period(0.01, h=np.full(6, np.nan))  # no estimate yet: no layers
    log.close()
    c = read_mcap(tmp_path / "log.mcap")
    assert "/readings" not in c.messages and "/robot/pose_target" not in c.messages
    first, second = c.messages["/robot/pose"]
    c0, b0, d0 = layer_plane(design, h[:3])
    assert first["layers"][0] == pytest.approx({"layer": "A", "centre_mm": c0 * 1e3, "bend_deg": math.degrees(b0),
                                                "direction_deg": math.degrees(d0)})
    assert first["layers"][1]["bend_deg"] == pytest.approx(0.0, abs=1e-9) and second["layers"] == []
    assert c.messages["/robot/pose_truth"][0]["layers"] == first["layers"]


def test_message_counts_come_from_a_whole_files_summary_and_a_stride_thins_all_but_the_events(tmp_path):
    path = tmp_path / "log.mcap"
    ev = json_schema("Events", "test", {"kind": {"type": "string"}})
    log = McapLog(path, {"/readings": SCHEMA, "/events": ev}, chunk_bytes=2048)
    for i, m in enumerate(_messages(100)):
        log.put(i * 0.01, "/readings", m)
        if i % 10 == 0:
            log.put(i * 0.01, "/events", {"kind": "tick"})
    log.close()
    assert message_counts(path) == {"/readings": 100, "/events": 10}
    thin = read_mcap(path, stride=7)
    assert [m["t_s"] for m in thin.messages["/readings"]] == [i * 0.01 for i in range(0, 100, 7)]
    assert thin.count("/events") == 10
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-100])
    assert message_counts(cut) is None
