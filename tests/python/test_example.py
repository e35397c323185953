"""examples/python/step_response.py (issue #18.8): its step metrics exactly, and one short run."""

import math
import os
import subprocess
import sys

import numpy as np
import pytest

EXAMPLE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "examples", "python")
sys.path.insert(0, EXAMPLE)

from step_response import step_metrics  # noqa: E402


def test_metrics_of_a_first_order_response():
    tau = 0.1
    t = np.arange(0, 2, 1e-5)
    rise, overshoot, settling = step_metrics(t, 1 - np.exp(-t / tau), 0.0, 1.0)
    assert rise == pytest.approx(tau * math.log(9), abs=2e-5)  # from 10 % to 90 %
    assert overshoot == 0.0
    assert settling == pytest.approx(tau * math.log(50), abs=2e-5)  # into the 2 % band for good


def test_metrics_of_an_underdamped_response():
    zeta, wn = 0.3, 10.0
    t = np.arange(0, 5, 1e-5)
    wd = wn * math.sqrt(1 - zeta ** 2)
    y = 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta ** 2) * np.sin(wd * t))
    rise, overshoot, settling = step_metrics(t, 2 + 0.5 * y, 2.0, 2.5)  # offset and scale do not matter
    assert overshoot == pytest.approx(100 * math.exp(-zeta * math.pi / math.sqrt(1 - zeta ** 2)), abs=1e-3)
    assert 0 < rise < math.pi / wd and 0 < settling < 4.5 / (zeta * wn)


def test_never_settling_is_nan():
    t = np.arange(0, 1, 0.01)
    assert math.isnan(step_metrics(t, 0.5 * np.ones_like(t), 0.0, 1.0)[2])


@pytest.mark.skipif(not os.environ.get("CHIMERA_ROBOTICS"), reason="the robotics modules are not built (-Dkdl)")
def test_a_short_run_prints_the_metrics_and_saves_the_plot(tmp_path):
    out = tmp_path / "step.png"
    run = subprocess.run([sys.executable, os.path.join(EXAMPLE, "step_response.py"), "--settle", "0.3",
                          "--seconds", "0.8", "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stdout + run.stderr
    lines = run.stdout.splitlines()
    assert lines[0].startswith("joint 2 step +0.200 rad (from 0.7854 to 0.9854)")
    assert any(line.startswith("rise time (10-90 %): ") and line.endswith(" ms") for line in lines)
    assert any(line.startswith("overshoot: ") for line in lines)
    assert any(line.startswith("jpid         ON") for line in lines)
    assert out.stat().st_size > 10000 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # The step feed is gone with the run: nothing is left in /dev/shm (the
    # module, started, made anew any feed an earlier run left).
    assert not os.path.exists("/dev/shm/chimera.tbuf.step"), "the run left its TBUF feed behind"
