"""The daemon's live page in headless Chromium (Debian's chromium, driven over the DevTools pipe):
the page loads from the daemon, shows the values GET /status gives, and a setpoint typed into it and
its stop button reach the loop, whose last status the page shows. Every wait polls with a generous
bound; nothing is judged by time."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from checkout import ROOT
from hbma_ctrl.app.bench.browser import Browser, chromium_path

pytestmark = [pytest.mark.slow, pytest.mark.subprocess,
              pytest.mark.skipif(chromium_path() is None, reason="no chromium (apt-get install chromium)")]

#: the file's targets without the start-up calibration, the watchdog off (a loaded test machine must
#: not decide this test) and the status published once a second, so the page and GET /status show
#: the same status long enough to be compared
EDITS = {"[controller]\n": "[controller]\ncalibrate = false\n",
         "log_flush_s = 0.5": "log_flush_s = 0.5\nmiss_limit = 100000\nstatus_every = 100"}
#: the page's cells (data-k) and the digits it shows them with, by where they are in GET /status
CHAMBER_CELLS = {"h_mm": 3, "target_mm": 3, "p_kpa": 2, "p_est_kpa": 2, "speed_pct": 1, "inlet_duty": 2,
                 "outlet_duty": 2}
LOOP_CELLS = {"steps": 0, "deadline_misses": 0, "overruns": 0, "step_ms_median": 2, "step_ms_p99": 2}

READ_PAGE = """(() => {
  const cell = (k, i) => document.querySelector(i === undefined ? `[data-k="${k}"]` : `[data-k="${k}"][data-i="${i}"]`);
  const out = {mode: cell("mode").textContent, t_s: cell("t_s").textContent, chambers: [], loop: {}};
  for (const k of %s) out.loop[k] = cell(k).textContent;
  for (let i = 0; cell("h_mm", i); i++) {
    const c = {};
    for (const k of %s) c[k] = cell(k, i).textContent;
    out.chambers.push(c);
  }
  return out;
})()""" % (json.dumps(list(LOOP_CELLS)), json.dumps(list(CHAMBER_CELLS)))


def _start(config: Path, out: Path) -> tuple[subprocess.Popen, str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "hbma_ctrl", "daemon", str(config), "--rig", "sim", "--api",
                             "127.0.0.1:0", "--out", str(out)], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while True:
        line = proc.stderr.readline()
        if not line or time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"daemon did not start: {proc.communicate()}")
        m = re.match(r"api: (\S+)", line.strip())
        if m:
            return proc, m.group(1)


def _same(text: str, value, digits: int) -> bool:
    """The page's text shows ``value`` at ``digits`` decimals ('-' for null)."""
    if value is None:
        return text == "-"
    return text != "-" and abs(float(text) - value) <= 0.5 * 10.0 ** -digits + 1e-9


def test_the_live_page_shows_the_status_and_its_setpoint_and_stop_reach_the_loop(tmp_path):
    text = (ROOT / "scenarios" / "daemon_chamber.toml").read_text()
    for a, b in EDITS.items():
        assert a in text
        text = text.replace(a, b, 1)
    config = tmp_path / "cfg.toml"
    config.write_text(text)
    proc, api = _start(config, tmp_path / "run")
    try:
        with Browser() as browser, httpx.Client(base_url=api, timeout=10) as http:
            page = browser.open(api + "/")
            browser.wait_for(page, "document.querySelector('[data-k=\"mode\"]').textContent === 'running' && "
                                   "document.querySelector('[data-k=\"h_mm\"][data-i=\"0\"]') !== null", timeout=120)
            # the page and GET /status read at one status (the loop publishes once a second): equal values
            matched = None
            for _ in range(200):
                shown = browser.evaluate(page, READ_PAGE)
                status = http.get("/status").json()
                if shown["loop"]["steps"] == str(status["loop"]["steps"]) and shown["chambers"]:
                    matched = (shown, status)
                    break
                time.sleep(0.1)
            assert matched is not None, "the page never showed the status GET /status gave"
            shown, status = matched
            assert shown["mode"] == status["mode"] and _same(shown["t_s"], status["t_s"], 2)
            for k, d in LOOP_CELLS.items():
                assert _same(shown["loop"][k], status["loop"][k], d), (k, shown["loop"][k], status["loop"][k])
            assert len(shown["chambers"]) == len(status["chambers"])
            for c_shown, c in zip(shown["chambers"], status["chambers"]):
                for k, d in CHAMBER_CELLS.items():
                    assert _same(c_shown[k], c[k], d), (k, c_shown[k], c[k])

            # a height typed into the page's setpoint field, sent with Enter, becomes the loop's target
            before = http.get("/status").json()["chambers"][0]["target_mm"]
            browser.evaluate(page, "document.querySelector('[data-sp=\"0\"]').focus()")
            browser.insert_text(page, "4.5")
            browser.press(page, "Enter")
            applied = json.loads(browser.wait_for(page, "document.getElementById('sp-reply').dataset.applied",
                                                  timeout=60))["heights_mm"]["0"]
            assert applied == pytest.approx(4.5) and before != pytest.approx(4.5)
            for _ in range(600):
                target = http.get("/status").json()["chambers"][0]["target_mm"]
                if target is not None and target == pytest.approx(applied):
                    break
                time.sleep(0.1)
            assert target == pytest.approx(applied), (target, applied)
            browser.wait_for(page, "document.querySelector('[data-k=\"target_mm\"][data-i=\"0\"]').textContent "
                                   "=== '4.500'", timeout=60)

            # the page's stop button ends the daemon in the safe state, and the page shows the loop stopped
            browser.evaluate(page, "document.getElementById('stop').click()")
            proc.wait(120)
            browser.wait_for(page, "document.querySelector('[data-k=\"mode\"]').textContent === 'stopped'",
                             timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()
    assert proc.returncode == 0
    stats = json.loads((tmp_path / "run" / "daemon_stats.json").read_text())
    assert stats["end_reason"] == "api" and stats["safe_exit"] is True
