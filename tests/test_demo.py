"""The README's main command: ``motcomp demo``, end to end (about 35 s), run once for the module.

Besides the delay gained, the demo records the command the service sends the platform and
sets it beside the ideal run (the config's tick fed the same motion perfectly timed: the floor).
The sanity tests check that those figures exist and hang together; the motion-quality targets of
the compensated command are :data:`MAX_LIMITED_SHARE_ON` and :data:`MAX_HF_RATIO_TO_IDEAL`,
asserted in :func:`test_compensated_command_is_near_the_floor` (the figures are taken over the
stretches of recorded ticks, live and ideal alike).  The real-time figures are judged only if the
host's bare loop clock, run beside the demo, held the loop rate; otherwise those tests report
*not judged* with the host's figures (docs/TESTING.md), never a wider bound.
"""

from __future__ import annotations

import math
import platform

import numpy as np
import pytest

from motcomp.config import load_config
from motcomp.demo import PHASES, RAILS, DemoResult, _resampled_delay, _Trace, report, run_demo
from motcomp.resources import config_file
from motcomp.runtime.probe import HostClock, HostProbe, loop_kept_from_cpu
from tests.conftest import judge_realtime

pytestmark = pytest.mark.slow

MAX_LIMITED_SHARE_ON = 0.005
"""Compensated rails: largest share of ticks with the command at the acceleration limit (the
motion-quality target; measured 0 in runs at load 0.5-4, 1710 missed deadlines in the last)."""
MAX_HF_RATIO_TO_IDEAL = 2.0
"""Compensated rails: largest HF acceleration RMS of the live command, as a multiple of the ideal
run's over the same stretches (the target; measured 1.0-1.2 at load 0.5-4)."""
IDEAL_ABOVE_LIVE_FACTOR = 1.5
"""Sanity, not quality: the ideal run is the floor, so its HF acceleration RMS may exceed the
live command's at most by this factor (the two are sampled with a sub-tick phase offset)."""
MIN_RECORDED_SHARE = 0.9
"""Sanity: the command figures mean something only if most ticks' frames were recorded."""
HEXAPOD = ("hex_z", "hex_roll", "hex_pitch")
MAX_PREDICTED_HEXAPOD_MS = 10.0
"""The hexapod's sines through the example config's prediction, measured on the feedback: the
issue's bound on the worst delay over the band (the design's phase delay at 0.25-0.5 Hz is
about 4 ms, plus the input reconstruction's 1.1 ms)."""


@pytest.fixture(scope="module")
def measured(tmp_path_factory: pytest.TempPathFactory) -> tuple[DemoResult, HostClock | None]:
    """The demo, and the host's bare loop clock (the demo config's rate and naps) beside it."""
    loop = load_config(config_file("demo.toml")).loop
    with HostProbe(loop.rate_hz, sleep_max_us=loop.sleep_max_us) as probe:
        res = run_demo(tmp_path_factory.mktemp("demo"), quiet=True)
    return res, probe.result


@pytest.fixture(scope="module")
def demo(measured: tuple[DemoResult, HostClock | None]) -> DemoResult:
    return measured[0]


@pytest.fixture(scope="module")
def host(measured: tuple[DemoResult, HostClock | None]) -> HostClock | None:
    return measured[1]


def test_demo_reports_the_delay_gained(demo: DemoResult, host: HostClock | None) -> None:
    text = report(demo)
    assert all(code == 0 for code in demo.exit_codes.values()), text
    assert "Platform hard-limit violations: 0" in text
    # a host that starved the service's loop is said under the table, with the reason
    starved = loop_kept_from_cpu(demo.status)
    assert ("NOT A QUIET HOST'S FIGURES" in text) == bool(starved), text
    assert not starved or starved in " ".join(text.split()), text
    judge_realtime(host, "the delays of the demo", demo.status)
    ms = {a: (d["off"] * 1e3, d["on"] * 1e3) for a, d in demo.delays.items()}
    off, on = ms["rails_y"]  # the slalom, as in the paper's Fig. 4
    # the platform's 196 ms behind the setpoints, and the band limit's 7.0 ms before it
    assert off == pytest.approx(196 + 7.0, abs=8), text
    off_x, on_x = ms["rails_x"]
    if demo.stale.get("on", 0) == 0:
        assert off - on > 150 and off_x - on_x > 100, text
    else:  # the input stalled beyond stale_after_s (a starved host): the report says so
        assert "the delay of that phase includes it" in text
        assert off - on > 100 and off_x - on_x > 50, text
    for axis in HEXAPOD:  # PID bypassed; compensated by prediction in phase "on"
        assert ms[axis][0] > 30, text  # the platform's own ~38 ms
        if demo.stale.get("on", 0) == 0:
            assert ms[axis][1] <= MAX_PREDICTED_HEXAPOD_MS, text
    assert set(demo.saturation) >= set(RAILS)  # counts per phase, from the service
    # the table's flags are the motion's, from the recorded frames, and those of the input's
    # stop are said apart: together within the service's counters over the whole phase
    for axis, per in demo.saturation_motion.items():
        for ph, n in per.items():
            stop = demo.saturation_stop[axis][ph]
            assert 0 <= n + stop <= demo.saturation.get(axis, {}).get(ph, 0), (axis, ph, text)
            if stop:
                assert f"{axis} {demo.saturation_stop[axis]['off']} / " \
                       f"{demo.saturation_stop[axis]['on']}" in " ".join(text.split()), text
    assert "Platform hard-limit violations: 0" in text


def test_demo_records_the_command_and_sets_it_beside_the_floor(demo: DemoResult,
                                                               host: HostClock | None) -> None:
    text = report(demo)
    assert set(demo.command) == set(demo.delays), text  # every axis of the table
    for ph in PHASES:
        f = demo.frames[ph]
        assert f.recorded + f.lost + f.unsent == f.ticks, f
    judge_realtime(host, "the command frames of the demo", demo.status)
    for ph in PHASES:
        f = demo.frames[ph]
        assert f.recorded >= MIN_RECORDED_SHARE * f.ticks, f
        m0, m1 = demo.motion[ph]
        assert f.ticks == pytest.approx((m1 - m0) * demo.status["rate_hz"], abs=1)
    for axis, per_phase in demo.command.items():
        a_max = demo.acc_limit[axis]
        assert a_max > 0
        for ph in PHASES:
            c = per_phase[ph]
            for q in (c.live, c.ideal):
                assert all(math.isfinite(v) and v >= 0 for v in q.as_dict().values()), c
            for share in (c.at_limit, c.ideal_at_limit, c.ideal_acted):
                assert 0.0 <= share <= 1.0, (axis, ph, c)
            assert c.ideal.acc_peak <= a_max * (1 + 1e-9), (axis, ph, c)  # the limiter's bound
            # (the figures start once the live prefilters are at full weight, after the ideal
            # run's, which rejoins after a stale gap as the live phase does)
            assert c.ideal.hf_acc_rms <= IDEAL_ABOVE_LIVE_FACTOR * c.live.hf_acc_rms, (
                axis, ph, c)
            assert c.live.jerk_rms > 0 and c.live.acc_peak > 0, (axis, ph, c)  # it moved
    for axis in RAILS:  # the floor of the setpoint itself (bypass) never touches the limit
        assert demo.command[axis]["off"].ideal_at_limit == 0.0
        assert demo.command[axis]["off"].ideal.acc_peak < demo.acc_limit[axis]
    assert "from the command*" in text and "ratio" in text
    assert "Command frames over the motion, off / on:" in text


def test_demo_logs_the_platform_s_set_up_and_its_counters(demo: DemoResult) -> None:
    assert demo.figure is not None
    text = (demo.figure.parent / "logs" / "hil.log").read_text()
    assert "simulated platform at 1000 Hz" in text and "truth p1d:" in text, text
    if platform.machine() in ("x86_64", "aarch64"):  # its loop computes as the service's does
        assert "; subnormals flushed to zero" in text, text
    assert "hard-limit violations: none" in text, text


def test_demo_figure_shows_the_command(demo: DemoResult) -> None:
    from PIL import Image

    assert demo.figure is not None
    assert demo.figure.stat().st_size > 10_000
    want = {f"{a} {what}" for a in RAILS for what in
            ("position (m)", "command (m)", "acceleration (m/s^2)")}
    assert want <= set(demo.panels), demo.panels
    assert "hex_roll position (rad)" in demo.panels and "hex_pitch position (rad)" in demo.panels
    with Image.open(demo.figure) as png:  # the file written is the one with these panels
        assert png.info["Description"] == "; ".join(demo.panels)


def test_compensated_command_is_near_the_floor(demo: DemoResult, host: HostClock | None
                                               ) -> None:
    judge_realtime(host, "the demo's compensated command", demo.status)
    text = report(demo)
    for axis in RAILS:
        c = demo.command[axis]["on"]
        assert c.at_limit <= MAX_LIMITED_SHARE_ON, (axis, text)
        assert c.hf_ratio <= MAX_HF_RATIO_TO_IDEAL, (axis, text)


def test_a_delay_the_feedback_does_not_show_is_not_measured_and_says_why() -> None:
    """Feedback that does not follow the motion within the searched lags (a host that starved
    the platform): the delay is NaN with the reason, the demo goes on (it stopped with exit 2)."""
    t = np.arange(0.0, 10.0, 1e-3)
    ref, out = _Trace(), _Trace()
    for tk in t.tolist():  # the feedback drifts away: no lag within [-0.5, 1] s explains it
        ref.add(tk, {"rails_y": math.sin(2 * math.pi * 0.31 * tk)})
        out.add(tk, {"rails_y": tk})
    delay, why = _resampled_delay(ref, out, "rails_y", 0.0, 10.0)
    assert math.isnan(delay) and "edge of the searched lags" in why, (delay, why)
    delay, why = _resampled_delay(ref, ref, "rails_y", 0.0, 10.0)
    assert abs(delay) < 1e-3 and why == ""
