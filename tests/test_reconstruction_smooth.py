"""The ``smooth`` input reconstruction (motcomp.core.shaper): exact on quadratics, and what it
does to the command with jittery, slow and timestamp-less senders (through the tick, offline)."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from motcomp.config import ServiceConfig, load_config, new_tick, resolve_axes
from motcomp.core.axes import AXIS_INDEX
from motcomp.core.quality import command_quality
from motcomp.core.shaper import ReferenceShaper, ShaperParams
from motcomp.core.tick import set_bypass, step
from motcomp.io.wire import encode_input
from motcomp.resources import config_file
from motcomp.sim.ideal import ideal_run
from motcomp.sim.source import builtin

Y = AXIS_INDEX["rails_y"]


def _cfg(reconstruction: str) -> ServiceConfig:
    cfg = load_config(config_file("motcomp.toml"))
    return cfg.model_copy(update={"input": cfg.input.model_copy(
        update={"reconstruction": reconstruction})})


def _params(n: int = 8) -> ShaperParams:
    return ShaperParams(driven=(True,) * n, ramp_speed=(1.0,) * n, reach_lo=(-10.0,) * n,
                        reach_hi=(10.0,) * n, startup_s=0.0, reconstruction="smooth")


def test_a_quadratic_is_played_back_exactly_one_lag_behind() -> None:
    """Samples of x(t) = 0.3 + 0.5 t + 0.5 t^2 at 100 Hz, arriving 2 ms after their instant, a
    tick every 1 ms: Catmull-Rom tangents and the end parabola's slope are exact on a parabola,
    so before the moving average the playback is x(tau) at the playback instant, and the
    reference is the mean of x over the last 10 instants (one input period), to rounding.  The
    lag is one period of playback plus 4.5 ticks of averaging."""
    p = _params()
    sh = ReferenceShaper(8)
    x = lambda t: 0.3 + 0.5 * t + 0.5 * t * t  # noqa: E731
    errs, taus = [], []
    for k in range(3000):  # ticks at 1 kHz, frames every 10th
        now = 1e-3 * k + 0.002
        if k % 10 == 0:
            t = 1e-3 * k
            sh.on_input(p, {Y: x(t)}, now, t)
        ref, _ = sh.reference(p, now)
        delay = sh.playback_delay_s
        taus.append(None if delay is None else now - delay)
        if k > 1500:  # the playback delay's filter has settled
            expected = sum(x(tau) for tau in taus[-10:]) / 10
            errs.append(ref[Y] - expected)
    assert sh.lag_s == pytest.approx(0.010 + 0.0045, abs=1e-9)
    assert max(map(abs, errs)) < 1e-9


def _jittery(cfg: ServiceConfig, signal: str, src_hz: float, jitter_us: float, stalls: bool,
             with_t: bool, bypass: bool, seed: int = 1, drift: float = 0.0
             ) -> tuple[float, float]:
    """(share of ticks the limiter acted on, HF acceleration RMS of the command) of rails_y or
    rails_x (the signal's axis) for a sender late by U(0, jitter) after its instants, whose
    clock runs ``drift`` (relative) slow against the loop's."""
    traj = builtin(signal, src_hz)
    rng = np.random.default_rng(seed)
    axes = resolve_axes(cfg)
    params, state = new_tick(cfg, axes)
    if bypass:
        set_bypass(state, list(axes.driven))
    (axis, x), = traj.pos.items()
    i = AXIS_INDEX[axis]
    ts = np.arange(x.size) / src_hz
    arrive = ts * (1.0 + drift) + 3e-4 + rng.uniform(0.0, jitter_us * 1e-6, x.size)
    if stalls:  # 2-15 ms, every 3 s on average; the frames due meanwhile come in a burst
        t = 1.0
        while t < ts[-1]:
            d = rng.uniform(0.002, 0.015)
            late = (ts >= t) & (ts < t + d)
            arrive[late] = np.maximum(arrive[late], t + d + 3e-4)
            t += rng.exponential(3.0)
    arrive = np.maximum.accumulate(arrive)

    def frame(seq: int, t: float, v: float) -> bytes:
        return (encode_input(seq, t, {axis: v}) if with_t
                else msgpack.packb({"seq": seq, "pos": {axis: v}}))

    period = params.period_ns
    settle = 2000
    for k in range(settle):
        step(state, params, k * period, frame(k, (k - settle) * 1e-3, float(x[0])))
    seq, j, u, acted = settle, 0, [], 0
    for k in range(int(ts[-1] * 1000)):
        frames = []  # every frame that arrived since the previous tick, as the service reads
        while j < x.size and arrive[j] <= k * 1e-3:
            frames.append(frame(seq, float(ts[j]), float(x[j])))
            seq, j = seq + 1, j + 1
        before = state.acted[i]
        u.append(step(state, params, (settle + k) * period, frames).u[i])
        acted += state.acted[i] != before
    return acted / len(u), command_quality(np.array(u), 1000.0).hf_acc_rms


def _floor(cfg: ServiceConfig, signal: str, bypass: bool) -> float:
    traj = builtin(signal, 1000.0)
    run = ideal_run(cfg, traj.pos, 1000.0, bypass=bypass)
    return command_quality(next(iter(run.u.values())), 1000.0).hf_acc_rms


@pytest.mark.parametrize("with_t", [True, False], ids=["t", "no-t"])
def test_a_1khz_sender_with_300us_jitter_reaches_the_floor(with_t: bool) -> None:
    """Compensated slalom: the linear reconstruction lets the jitter through (the limiter acts
    and the HF acceleration is many times the floor); the smooth one absorbs it."""
    smooth = _cfg("smooth")
    share, hf = _jittery(smooth, "slalom", 1000.0, 300.0, False, with_t, False)
    floor = _floor(smooth, "slalom", False)
    assert share == 0.0
    assert hf <= 1.2 * floor


@pytest.mark.parametrize("src_hz", [250.0, 100.0, 60.0])
def test_slow_senders_are_upsampled_without_steps(src_hz: float) -> None:
    """Bypassed slalom from a 60-250 Hz sender with t and 300 us jitter: the command is the
    reconstruction itself.  Linear extrapolation jumps at every frame (the limiter acts on
    tens of per cent of the ticks); the smooth playback never trips it, with an HF acceleration
    of a few hundredths of m/s^2 (the slalom's own acceleration is ~3 m/s^2)."""
    share_lin, hf_lin = _jittery(_cfg("linear"), "slalom", src_hz, 300.0, False, True, True)
    share, hf = _jittery(_cfg("smooth"), "slalom", src_hz, 300.0, False, True, True)
    assert share == 0.0 and hf < 0.15
    assert share_lin > 0.01 and hf_lin > 10 * hf


@pytest.mark.parametrize("with_t", [True, False], ids=["t", "no-t"])
def test_stalls_of_a_1khz_sender_do_not_trip_the_limiter(with_t: bool) -> None:
    """1 kHz, 300 us jitter, stalls of 2-15 ms every 3 s on average whose frames come in a
    burst: every frame of the burst is read (the seq step keeps the timeline of frames without
    t), the playback bridges the stall along the parabola of the last samples, and the
    compensated command never reaches the limiter (it did on 1.6 % of the ticks when a tick
    read the newest frame only, and on 2.4 % with the linear reconstruction).  What remains of
    the stalls is an HF acceleration of a few hundredths of m/s^2 (0.05 measured, the floor
    0.008)."""
    smooth = _cfg("smooth")
    share, hf = _jittery(smooth, "slalom", 1000.0, 300.0, True, with_t, False)
    share_b, hf_b = _jittery(smooth, "slalom", 1000.0, 300.0, True, with_t, True)
    assert share == 0.0 and share_b == 0.0
    assert hf < 0.1 and hf_b < 0.01


@pytest.mark.parametrize("drift", [3e-4, -1e-4], ids=["slow-300ppm", "fast-100ppm"])
def test_a_drifting_sender_clock_is_followed_without_steps(drift: float) -> None:
    """The sender's clock runs 300 ppm slow (or 100 ppm fast) against the loop's: the frames'
    arrival phase sweeps through the ticks (up to a period of extra wait), the smallest transit
    drifts; the playback instant follows through its filter and the limiter never acts."""
    share, hf = _jittery(_cfg("smooth"), "slalom", 1000.0, 300.0, True, True, False,
                         drift=drift)
    assert share == 0.0 and hf < 0.1
