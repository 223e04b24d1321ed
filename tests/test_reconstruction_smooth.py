"""The ``smooth`` input reconstruction (motcomp.core.shaper): exact on quadratics, and what it
does to the command with jittery, slow and timestamp-less senders (through the tick, offline)."""

from __future__ import annotations

import functools
import math

import msgpack
import numpy as np
import pytest

from motcomp.config import ServiceConfig, load_config, new_tick, resolve_axes
from motcomp.core.axes import AXIS_INDEX
from motcomp.core.interp import ROUNDING_SLOPE, STENCIL_S, Curve, Knot, beyond_rounding
from motcomp.core.interp import extrapolate as _extrapolate
from motcomp.core.interp import knot as _knot
from motcomp.core.interp import quintic as _quintic
from motcomp.core.quality import command_quality, estimate_delay
from motcomp.core.shaper import FIT_S, ReferenceShaper, ShaperParams
from motcomp.core.tick import set_bypass, step
from motcomp.io.wire import encode_input
from motcomp.resources import config_file
from motcomp.sim.ideal import ideal_run
from motcomp.sim.source import builtin

Y = AXIS_INDEX["rails_y"]


def _cfg(reconstruction: str, lead_s: float = 0.0) -> ServiceConfig:
    cfg = load_config(config_file("motcomp.toml"))
    return cfg.model_copy(update={"input": cfg.input.model_copy(
        update={"reconstruction": reconstruction, "lead_s": lead_s})})


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
             with_t: bool, bypass: bool, seed: int = 1, drift: float = 0.0,
             skips: bool = False, losses: bool = False,
             stall_ms: tuple[float, float] = (2.0, 15.0),
             ref_delay: list[float] | None = None) -> tuple[float, float]:
    """(share of ticks the limiter acted on, HF acceleration RMS of the command) of rails_y or
    rails_x (the signal's axis) for a sender late by U(0, jitter) after its instants, whose
    clock runs ``drift`` (relative) slow against the loop's; with ``skips``, the sender leaves
    out one sample about every second (its seq counts the frames it sends); with ``losses``,
    about one frame a second is lost on the way (its seq is skipped); ``ref_delay``
    receives the reference's delay behind the sender's trajectory (s)."""
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
    if stalls:  # every 3 s on average; the frames due meanwhile come in a burst
        t = 1.0
        while t < ts[-1]:
            d = rng.uniform(stall_ms[0], stall_ms[1]) / 1e3
            late = (ts >= t) & (ts < t + d)
            arrive[late] = np.maximum(arrive[late], t + d + 3e-4)
            t += rng.exponential(3.0)
    arrive = np.maximum.accumulate(arrive)
    keep = np.ones(x.size, dtype=bool)
    if skips:
        keep[rng.choice(np.arange(1000, x.size - 1000), size=int(ts[-1]), replace=False)] = False
    lose = np.zeros(x.size, dtype=bool)
    if losses:
        lose[rng.choice(np.arange(1500, x.size - 1000), size=int(ts[-1]), replace=False)] = True

    def frame(seq: int, t: float, v: float) -> bytes:
        return (encode_input(seq, t, {axis: v}) if with_t
                else msgpack.packb({"seq": seq, "pos": {axis: v}}))

    period = params.period_ns
    settle = 2000
    for k in range(settle):
        step(state, params, k * period, frame(k, (k - settle) * 1e-3, float(x[0])))
    seq, j, u, refs, acted = settle, 0, [], [], 0
    for k in range(int(ts[-1] * 1000)):
        frames = []  # every frame that arrived since the previous tick, as the service reads
        while j < x.size and arrive[j] <= k * 1e-3:
            if keep[j]:
                if not lose[j]:
                    frames.append(frame(seq, float(ts[j]), float(x[j])))
                seq += 1
            j += 1
        before = state.acted[i]
        u.append(step(state, params, (settle + k) * period, frames).u[i])
        refs.append(state.shaper.ref[i])
        acted += state.acted[i] != before
    if ref_delay is not None:
        grid = np.arange(len(refs)) * 1e-3
        ref_delay.append(estimate_delay(np.interp(grid, ts, x), np.array(refs), 1000.0,
                                        min_lag_s=-0.05, max_lag_s=0.1))
    return acted / len(u), command_quality(np.array(u), 1000.0).hf_acc_rms


@functools.cache
def _floor(bypass: bool) -> float:
    """The floor: the HF acceleration RMS of the ideal run's slalom command (1 kHz samples,
    perfectly timed) through the smooth reconstruction's config, bypassed or compensated."""
    traj = builtin("slalom", 1000.0)
    run = ideal_run(_cfg("smooth"), traj.pos, 1000.0, bypass=bypass)
    return command_quality(next(iter(run.u.values())), 1000.0).hf_acc_rms


@pytest.mark.parametrize("with_t", [True, False], ids=["t", "no-t"])
def test_a_1khz_sender_with_300us_jitter_reaches_the_floor(with_t: bool) -> None:
    """Compensated slalom: the linear reconstruction lets the jitter through (the limiter acts
    and the HF acceleration is many times the floor); the smooth one absorbs it."""
    smooth = _cfg("smooth")
    share, hf = _jittery(smooth, "slalom", 1000.0, 300.0, False, with_t, False)
    floor = _floor(False)
    assert share == 0.0
    assert hf <= 1.2 * floor


@pytest.mark.parametrize("with_t", [True, False], ids=["t", "no-t"])
@pytest.mark.parametrize("src_hz", [250.0, 100.0, 60.0])
def test_slow_senders_are_upsampled_at_the_floor(src_hz: float, with_t: bool) -> None:
    """Slalom from a 60-250 Hz sender (after 2 s of 1 kHz frames: the rate is relearnt), 300 us
    jitter.  Bypassed, the command is the reconstruction itself: linear extrapolation jumps at
    every frame (the limiter acts on tens of per cent of the ticks); the smooth playback stays
    within 20 % of the ideal 1 kHz run's HF acceleration, bypassed and compensated (measured
    1.0-1.1x)."""
    smooth = _cfg("smooth")
    share, hf = _jittery(smooth, "slalom", src_hz, 300.0, False, with_t, True)
    assert share == 0.0 and hf <= 1.2 * _floor(True)
    share_on, hf_on = _jittery(smooth, "slalom", src_hz, 300.0, False, with_t, False)
    assert share_on == 0.0 and hf_on <= 1.2 * _floor(False)
    if with_t:
        share_lin, hf_lin = _jittery(_cfg("linear"), "slalom", src_hz, 300.0, False, True, True)
        assert share_lin > 0.01 and hf_lin > 100 * hf


@pytest.mark.parametrize("with_t", [True, False], ids=["t", "no-t"])
def test_stalls_of_a_1khz_sender_stay_at_the_floor(with_t: bool) -> None:
    """1 kHz, 300 us jitter, stalls of 2-15 ms every 3 s on average whose frames come in a
    burst: every frame of the burst is read (the seq step keeps the timeline of frames without
    t), the playback bridges the stall along the newest sample's constant-jerk cubic, and the
    compensated command stays within 20 % of the ideal run's HF acceleration (1.09x measured;
    5.8x when the bridge was the parabola through the last three samples, and the limiter
    acted on 1.6 % of the ticks when a tick read the newest frame only)."""
    smooth = _cfg("smooth")
    share, hf = _jittery(smooth, "slalom", 1000.0, 300.0, True, with_t, False)
    share_b, hf_b = _jittery(smooth, "slalom", 1000.0, 300.0, True, with_t, True)
    assert share == 0.0 and share_b == 0.0
    assert hf <= 1.2 * _floor(False)
    assert hf_b <= 1.2 * _floor(True)


@pytest.mark.parametrize("with_t", [True, False], ids=["t", "no-t"])
def test_samples_a_sender_skips_keep_their_place(with_t: bool) -> None:
    """A 1 kHz sender that leaves out one sample about every second (a simulation keeping its
    schedule after a stall; its seq counts the frames sent): with t, the stamp two periods on
    is on the grid; without t, the step twice the expected one spans two samples.  Placed one
    period early, each skip would be a velocity spike the compensator multiplies (the limiter
    acted on 20 % of a live recording's ticks)."""
    smooth = _cfg("smooth")
    share, hf = _jittery(smooth, "slalom", 1000.0, 300.0, False, with_t, False, skips=True)
    assert share == 0.0 and hf <= 1.2 * _floor(False)
    # and frames lost on the way besides (seq steps by 2): the skip is counted on top
    share, hf = _jittery(smooth, "slalom", 1000.0, 300.0, False, with_t, False, skips=True,
                         losses=True)
    assert share == 0.0 and hf <= 1.2 * _floor(False)


@pytest.mark.parametrize(("before_trough_ms", "skipped", "slalom"), [
    (32, 3, False), (60, 3, False), (120, 3, False), (-2, 3, True), (-4, 3, True),
    (0, 1, True), (1, 1, True), (0, 2, True), (1, 2, True), (1, 3, True), (-1, 1, True),
    (-3, 2, False), (0, 1, False), (-1, 2, False), (2, 1, False)])
def test_samples_skipped_where_the_motion_slows_keep_their_place(
        before_trough_ms: int, skipped: int, slalom: bool) -> None:
    """A 1 kHz sender without t (the hexapod's 5 cm, 0.5 Hz heave, on time) skips three samples
    ``before_trough_ms`` before a trough, where its steps shrink by 1-3 % a sample: four samples
    then move less than four times the next step (a live recording: 32 ms before the trough,
    the constant-step rule read 3.8 steps, out of tolerance, and placed the sample three periods
    early; the predicted hexapod's command sat at its acceleration limit for 50 ms).  Along the
    last step and its change, each sample keeps its instant: the knots are the true instants.
    Just past the trough (-2, -4 ms) of the rails' slalom the steps are not steady but their
    change is (a live recording, a skip 2 ms past the slalom's trough read as one step: the
    compensated command at its acceleration limit, 7.5 m/s^2 off the ideal).  At the trough
    itself (0, 1 ms: ``skipped`` samples from the trough or just after it) the step's change
    leaves two counts a new step can mean, one each side of the trough: where the nearer one is
    not the frames it says, the farther counts (a live recording, the trough's sample skipped:
    -4.0, -2.5, then -0.5 um, read as 0.33 steps; one step placed it a period early, 3.4 m/s^2
    off the ideal).  The heave's steps change by 0.5 um a sample, below the 1 um its skips
    were once counted from: a live recording, two samples skipped 3 ms past its trough and
    read as one step, 2.5 m/s^2 off the ideal for a few ms (bypassed hexapod: jerk 20x).  A
    skip that ends just before the trough and one step after it mirror each other: the same
    step, which is read as one step (not tested: it cannot tell)."""
    x = lambda t: 0.05 * np.sin(np.pi * t)  # noqa: E731  (trough at 1.5 s)
    if slalom:  # the rails' slalom, trough at 1.5 s: 1.5 um of change a step
        x = lambda t: 0.4 * np.sin(2 * np.pi * 0.31 * (t - 1.5) - np.pi / 2)  # noqa: E731
    skip0 = 1500 - before_trough_ms
    sent = [k for k in range(1600) if not skip0 < k <= skip0 + skipped]
    _assert_instants_kept([float(x(k * 1e-3)) for k in sent], sent)


def _assert_instants_kept(values: list[float], sent: list[int]) -> None:
    """A 1 kHz sender without t sends ``values`` of its samples ``sent`` (indices), on time, its
    seq stepping by 1 (a skip unseen): each knot lies at its sample's true instant."""
    p = _params()
    sh = ReferenceShaper(8)
    instants = []
    for v, k in zip(values, sent, strict=True):
        now = k * 1e-3 + 3e-4
        sh.on_input(p, {Y: v}, now)
        sh.reference(p, now)
        instants.append(sh.curves[Y].knots[-1].t)
    err = np.diff(instants) - np.diff(sent) * 1e-3
    assert np.max(np.abs(err[500:])) < 1e-6, (np.argmax(np.abs(err)), np.max(np.abs(err)))


@pytest.mark.parametrize("noisy", [False, True], ids=["float32", "noise-50nm"])
def test_a_sender_without_t_is_not_read_as_skipping_beside_its_crests(noisy: bool) -> None:
    """Values without t, none skipped.  float32 values (rails at 2 m, slalom 0.6 m at 0.3 Hz:
    a 0.24 um ulp against 2.1 um of change a step): beside each crest the rounding moves the
    nearer count off one frame, and the farther one can fall near an integer; it counts only
    where the step is off one frame's by four ulps or more (without that, 10 of 60 crests read
    a skip: the sample placed a period late).  Exact values with 50 nm of noise (the hexapod's
    5 cm heave, 0.5 um of change a step): the step's changes must agree three times, and the
    step be off one frame's by four times their spread (the former rule: 7 skips in 60 s)."""
    tau = np.arange(20000) * 1e-3
    if noisy:
        x = 0.05 * np.sin(np.pi * tau) + 5e-8 * np.random.default_rng(7).normal(size=tau.size)
    else:
        x = (2.0 + 0.6 * np.sin(2.0 * np.pi * 0.3 * tau)).astype(np.float32)
    _assert_instants_kept([float(v) for v in x], list(range(tau.size)))


@pytest.mark.parametrize("drift", [3e-4, -1e-4], ids=["slow-300ppm", "fast-100ppm"])
def test_a_drifting_sender_clock_is_followed_without_steps(drift: float) -> None:
    """The sender's clock runs 300 ppm slow (or 100 ppm fast) against the loop's: the frames'
    arrival phase sweeps through the ticks (up to a period of extra wait), the smallest transit
    drifts; the playback instant follows through its filter and the limiter never acts."""
    share, hf = _jittery(_cfg("smooth"), "slalom", 1000.0, 300.0, True, True, False,
                         drift=drift)
    assert share == 0.0 and hf <= 1.2 * _floor(False)


def _cubic(t: float) -> tuple[float, float, float, float]:
    """x(t) = 0.3 + 0.5 t - 1.2 t^2 + 2 t^3 and its first three derivatives."""
    return (0.3 + t * (0.5 + t * (-1.2 + 2.0 * t)), 0.5 + t * (-2.4 + 6.0 * t), -2.4 + 12.0 * t,
            12.0)


def test_knots_are_exact_on_a_cubic_on_an_uneven_grid() -> None:
    """Each sample's slope, acceleration and jerk are those of the cubic through it and the
    three before it: exact on a cubic whatever the spacing (closed-form derivatives)."""
    ts = [0.0, 0.0013, 0.0021, 0.0035, 0.0041, 0.0072]
    h: list[Knot] = []
    for t in ts:
        h.append(_knot(h[-3:], t, _cubic(t)[0]))
    for knot in h[3:]:
        assert knot.fields()[2:] == pytest.approx(_cubic(knot.t)[1:], rel=1e-6, abs=1e-6)
    assert h[1].m == pytest.approx((_cubic(ts[1])[0] - _cubic(0.0)[0]) / ts[1])  # a line
    assert (h[1].a, h[1].j) == (0.0, 0.0)


def test_a_float32_values_slope_is_taken_over_the_stencils_spacing() -> None:
    """A float32 value's derivatives come from samples at least STENCIL_S before it, its own
    neighbour included (one period's difference would carry its rounding 5 times over at
    1 kHz); a float64 value's from the sample just before it."""
    dt = 2.0 ** -10  # 0.98 ms, exact: five steps are 4.9 ms, six 5.9
    assert 5 * dt < STENCIL_S <= 6 * dt
    for f32 in (True, False):
        c = Curve()
        for k in range(1025):
            v = 0.31 + 0.2 * (k * dt) ** 2
            c.add(k * dt, float(np.float32(v)) if f32 else v, 1e-4)
        newest = c.knots[-1]
        last = -7 if f32 else -2  # six steps back, or the one just before
        picked = [c.knots[last - 12], c.knots[last - 6], c.knots[last]]
        assert newest.fields() == _knot(picked, newest.t, newest.v).fields(), f32


def test_a_slope_difference_within_the_samples_rounding_steps_and_beyond_it_fades() -> None:
    """beyond_rounding: ROUNDING_SLOPE times the sample's rounding -- its value's ulp (float32's
    where it is one) plus its slope times its stamp's resolution -- per sample spacing is
    taken off a slope difference's size (closed form)."""
    v32 = float(np.float32(0.3))  # in [0.25, 0.5): a float32 ulp of 2^-25
    e = ROUNDING_SLOPE * 2.0 ** -25 / 1e-3
    assert beyond_rounding(0.5 * e, v32, 0.0, 0.0, 1e-3) == 0.0
    assert beyond_rounding(-0.9 * e, v32, 0.0, 0.0, 1e-3) == 0.0
    assert beyond_rounding(3.0 * e, v32, 0.0, 0.0, 1e-3) == pytest.approx(2.0 * e, rel=1e-12)
    assert beyond_rounding(-3.0 * e, v32, 0.0, 0.0, 1e-3) == pytest.approx(-2.0 * e, rel=1e-12)
    v64 = 0.3 + 1e-9  # not a float32: its own ulp, 5.6e-17
    assert beyond_rounding(1e-6, v64, 0.0, 0.0, 1e-3) == pytest.approx(
        1e-6 - ROUNDING_SLOPE * math.ulp(v64) / 1e-3, rel=1e-15)
    # an epoch stamp (ulp 2.4e-7 s) on a sample moving at 0.5 m/s: 0.12 um more
    t_res = math.ulp(1.8e9)
    e64 = ROUNDING_SLOPE * (math.ulp(v64) + 0.5 * t_res) / 1e-3
    assert beyond_rounding(0.9 * e64, v64, -0.5, t_res, 1e-3) == 0.0
    assert beyond_rounding(2.0 * e64, v64, -0.5, t_res, 1e-3) == pytest.approx(e64, rel=1e-12)
    assert beyond_rounding(1e-6, v32, 0.0, 0.0, 0.0) == 1e-6  # no spacing known: all fades


def test_a_late_sample_never_steps_the_played_value() -> None:
    """A float32 line (slope 0.2) bridged over a late sample: the played value's difference to
    the extrapolation is faded, never stepped; a slope difference the values' rounding explains
    (the sample on the line) is not faded, one beyond it (the sample 1 um off) is."""
    phi = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)  # the fade held still: its start shows
    for off, slope_faded in ((0.0, False), (1e-6, True)):
        c = Curve()
        for k in range(20):
            c.add(k * 1e-3, float(np.float32(0.3 + 0.2 * k * 1e-3)), 1e-4)
        c.at(0.0195, 0.01, phi, 0.2)  # extrapolating past the newest (0.019)
        before = c.at(0.0205, 0.01, phi, 0.2)
        c.add(0.020, float(np.float32(0.3 + 0.2 * 0.020 + off)), 1e-4)  # lands late
        after = c.at(0.0205, 0.01, phi, 0.2)
        assert after == pytest.approx(before, abs=1e-15) and c.fix is not None
        assert (abs(c.fix[1]) > 1e-4) == slope_faded, (off, c.fix)


def test_the_quintic_meets_each_sample_to_the_acceleration() -> None:
    """Between two samples with exact derivatives the quintic Hermite reproduces any polynomial
    of degree five; with the estimated derivatives of a smooth signal, value, slope and
    acceleration are continuous across a sample (finite differences on both sides)."""
    g = [1.0, 1.0, -3.0, 0.5, 2.0, -1.0]  # coefficients, constant first

    def poly(t: float, d: int) -> float:
        c = np.polynomial.polynomial.polyder(g, d) if d else g
        return float(np.polynomial.polynomial.polyval(t, c))

    knots = [Knot(t, poly(t, 0), poly(t, 1), poly(t, 2), 0.0) for t in (0.2, 0.9)]
    for tau in (0.2, 0.35, 0.6, 0.9):
        value, slope = _quintic(knots, tau)
        assert value == pytest.approx(poly(tau, 0), abs=1e-12)
        assert slope == pytest.approx(poly(tau, 1), abs=1e-12)
    h: list[Knot] = []
    for k in range(12):
        t = 0.01 * k
        h.append(_knot(h[-3:], t, float(np.sin(7.0 * t))))
    e = 1e-5
    for knot in h[5:9]:
        t = knot.t
        left = [_quintic(h, t - j * e)[0] for j in (2, 1, 0)]
        right = [_quintic(h, t + j * e)[0] for j in (0, 1, 2)]
        assert left[2] == right[0] == pytest.approx(knot.v, abs=1e-15)
        slope_l, slope_r = (left[2] - left[1]) / e, (right[1] - right[0]) / e
        assert slope_l == pytest.approx(slope_r, abs=1e-3)
        acc_l = (left[2] - 2 * left[1] + left[0]) / e**2
        acc_r = (right[2] - 2 * right[1] + right[0]) / e**2
        assert acc_l == pytest.approx(acc_r, abs=0.05)  # |x''| ~ 49 here


def test_a_cubic_is_played_back_exactly_through_a_stall() -> None:
    """Samples of a cubic every 2^-10 s (exact epoch stamps), 0.3 ms in transit; one sample
    skipped by the sender, and a 12-period stall whose frames then come in a burst.  The
    knots and the quintic are exact on a cubic, and so is the constant-jerk bridge: the
    reference is x at the playback instant throughout, to rounding.  With epoch stamps at
    1 kHz (``t0 + k/rate`` rounded to 0.24 us) the values decide where, within the stamps'
    resolution, the samples lie: values computed at the stamp itself are placed at the stamp,
    rounding and all; values computed at ``k/rate`` on the grid the stamps round, and the
    playback is as exact as with exact stamps (docs/WIRE.md)."""
    p = _params()
    x = lambda t: 0.3 + t * (0.5 + t * (-0.6 + 0.2 * t))  # noqa: E731
    period = 2.0**-10
    for case in ("exact", "values at the stamps", "values on the grid"):
        q = period if case == "exact" else 1e-3
        stamps = np.array([1.7e9 + q * j for j in range(2500)]) - 1.7e9
        sh = ReferenceShaper(8)
        errs, bridged = [], 0
        for k in range(2500):
            now = q * k + 3e-4
            burst = range(1000, 1013) if k == 1012 else [] if 1000 <= k < 1012 else [k]
            for j in burst:
                if j != 500:  # the sender skipped this one
                    value = x(q * j) if case == "values on the grid" else x(stamps[j])
                    sh.on_input(p, {Y: value}, now, 1.7e9 + q * j)
            ref, _ = sh.reference(p, now)
            bridged += sh.curves[Y].extra is not None
            delay = sh.playback_delay_s
            if delay is not None and k > 300:  # the delay filter settled
                truth = now - delay
                if case == "values at the stamps":  # the instants are the stamps': rounded
                    truth = float(np.interp(truth, np.arange(2500) * q, stamps))
                errs.append(ref[Y] - x(truth))
        instants = np.array([knot.t for knot in sh.curves[Y].knots])
        assert bridged >= 10  # the stall was bridged
        if case == "values on the grid":
            assert not sh.timeline.at_stamps
            grid = np.round(instants / q) * q
            assert np.max(np.abs(instants - grid)) < 2e-9  # the grid, not the stamps' rounding
            assert np.max(np.abs(np.diff(instants) - q)) < 1e-11  # a line
            assert max(map(abs, errs)) < 1e-9  # 8.5e-6 with the stamps as the instants
        else:
            assert sh.timeline.at_stamps
            assert np.all(np.isin(instants, stamps))  # each the stamp itself
            if case == "exact":
                assert max(map(abs, errs)) < 1e-9
            else:
                assert np.max(np.abs(np.diff(instants) - q)) < 2.4e-7  # 1 ulp


def _feed_grid(sh: ReferenceShaper, values: str, seconds: float, rng: np.random.Generator,
               jitter_s: float = 0.0, k0: int = 0, moving: bool = True, no_t_every: int = 0
               ) -> tuple[np.ndarray, np.ndarray]:
    """A 1 kHz sender of a 0.4 m, 0.31 Hz sine stamping ``t0 + k/1000`` in epoch seconds
    (plus a jitter of its instants), its values float32 and computed ``at the stamps`` or
    ``on the grid``: how far the instants the shaper read lie from the grid, and from the
    stamps (s)."""
    p = _params()
    t0 = 1.795e9 + 0.123456
    frac = t0 - math.floor(t0)  # (the shaper's instants are relative to a whole second)
    grid, stamps = [], []
    for k in range(k0, k0 + int(seconds * 1000)):
        stamp = t0 + k / 1000 + rng.uniform(0.0, jitter_s)
        tau = stamp - t0 if values == "at the stamps" else k / 1000
        value = float(np.float32(0.4 * np.sin(2 * np.pi * 0.31 * tau))) if moving else 0.25
        stamped = not (no_t_every and k % no_t_every == 0)
        sh.on_input(p, {Y: value}, k / 1000 + 5e-4, stamp if stamped else None)
        instant = sh.curves[Y].knots[-1].t
        grid.append(instant - frac - k / 1000)
        stamps.append(instant - (stamp - math.floor(t0)))
    return np.abs(grid), np.abs(stamps)


def test_where_a_grid_senders_values_lie_is_read_from_the_values() -> None:
    """Epoch stamps ``t0 + k/rate`` are 0.24 us coarse.  Values computed at the stamps are read
    at the stamps (t is the truth); values computed on the grid are read on it, once the values
    say so (float32 noise and all, within a second); a resting sender's values say nothing,
    and the stamps are kept; a jittered sender's stamps are never moved; and a sender that
    changes from the one to the other is followed."""
    ulp = math.ulp(1.795e9)
    rng = np.random.default_rng(3)
    sh = ReferenceShaper(8)
    grid, stamps = _feed_grid(sh, "at the stamps", 10.0, rng)
    assert sh.timeline.at_stamps and stamps.max() == 0.0
    assert grid[-5000:].mean() > 0.2 * ulp  # (the stamps' rounding)
    sh = ReferenceShaper(8)
    grid, _ = _feed_grid(sh, "on the grid", 10.0, rng)
    assert not sh.timeline.at_stamps
    k = int(np.nonzero(grid >= 0.02 * ulp)[0][-1]) + 1  # read on the grid from frame k on
    assert 100 < k < 1000, k
    assert grid[-1000:].max() < 2e-4 * ulp  # the grid to 0.05 ns once the line settled
    _, stamps = _feed_grid(sh, "at the stamps", 10.0, rng, k0=10_000)  # the sender changes
    assert sh.timeline.at_stamps and stamps[-3000:].max() == 0.0
    sh = ReferenceShaper(8)
    _feed_grid(sh, "on the grid", 5.0, rng, moving=False)
    assert sh.timeline.at_stamps  # no evidence either way
    sh = ReferenceShaper(8)
    _feed_grid(sh, "on the grid", 5.0, rng)
    assert not sh.timeline.at_stamps
    _, stamps = _feed_grid(sh, "on the grid", 5.0, rng, jitter_s=2e-4, k0=5000)
    assert stamps.max() == 0.0  # a jittered stamp is off the grid: the instant is the stamp
    sh = ReferenceShaper(8)  # every 13th frame without t: it, and those after it, on the grid
    grid, _ = _feed_grid(sh, "on the grid", 5.0, rng, no_t_every=13)
    assert not sh.timeline.at_stamps and grid[-3000:].max() < 0.01 * ulp  # (garbage if not carried)


def test_extrapolation_goes_on_along_the_cubic_then_at_constant_acceleration() -> None:
    """Up to the bound the newest sample's Taylor cubic (exact on a cubic); beyond it the
    parabola with the value, slope and acceleration reached at the bound, so that a gap longer
    than the bound never stops the reference dead (a velocity step, which the compensator
    turned into 21 % of limited ticks with 25-45 ms stalls)."""
    t0, bound = 0.004, 0.02
    knot = Knot(t0, *_cubic(t0))
    value, slope = _extrapolate(knot, t0 + 0.01, bound)
    assert value == pytest.approx(_cubic(t0 + 0.01)[0], abs=1e-12)
    assert slope == pytest.approx(_cubic(t0 + 0.01)[1], abs=1e-12)
    x_b, v_b, a_b, _ = _cubic(t0 + bound)
    for r in (0.0, 0.005, 0.03):
        value, slope = _extrapolate(knot, t0 + bound + r, bound)
        assert value == pytest.approx(x_b + v_b * r + 0.5 * a_b * r * r, abs=1e-12)
        assert slope == pytest.approx(v_b + a_b * r, abs=1e-12)


def test_a_stall_longer_than_the_bound_does_not_trip_the_limiter() -> None:
    """1 kHz with t, stalls of 35 ms every 3 s (beyond the 20 ms bound, short of stale):
    compensated, the limiter never acts."""
    share, _ = _jittery(_cfg("smooth"), "slalom", 1000.0, 300.0, True, True, False,
                        stall_ms=(35.0, 35.0))
    assert share == 0.0


def test_the_rejoin_blend_starts_where_the_reference_is() -> None:
    """A moving input (0.5 m/s) stops for 120 ms (stale: the reference holds), then comes back
    with a burst of 10 frames: the first reference after it equals the held one (the blend's
    offset is taken against the played-back reference, not the newest sample, which lies a lag
    and a burst ahead; that difference was a 4.5 mm jump in a live recording)."""
    p = _params()
    sh = ReferenceShaper(8)
    x = lambda t: 0.5 * t  # noqa: E731
    held = None
    for k in range(1500):
        now = 1e-3 * k + 3e-4
        if k < 1000:
            sh.on_input(p, {Y: x(1e-3 * k)}, now, 1e-3 * k)
        elif k == 1120:
            for j in range(1110, 1121):
                sh.on_input(p, {Y: x(1e-3 * j)}, now, 1e-3 * j)
        elif k > 1120:
            sh.on_input(p, {Y: x(1e-3 * k)}, now, 1e-3 * k)
        ref, mode = sh.reference(p, now)
        if k == 1119:
            assert mode == "stale"
            held = ref[Y]
        if k == 1120:
            assert mode == "rejoin"
            assert ref[Y] == pytest.approx(held, abs=1e-12)
        if k == 1121:
            assert abs(ref[Y] - held) < 1e-3  # moving on from there, at most ~0.5 m/s


@pytest.mark.parametrize("stale_ms", [120, 800], ids=["held", "ramping"])
def test_the_rejoin_blend_is_smooth_at_both_ends(stale_ms: int) -> None:
    """A moving input (0.5 m/s) stops, the reference holds (or ramps to neutral), then the input
    comes back: the blend starts FIT_S after the playback (no band limit here) and leaves the
    held path and meets the live one with no step of velocity, acceleration or jerk (a constant
    offset faded out gave the reference the live input's 0.5 m/s at the blend's first tick:
    500 m/s^2 for one tick; a minimum-jerk fade, a jerk step at its end)."""
    p = _params()
    sh = ReferenceShaper(8)
    refs, modes = [], []
    back = 1000 + stale_ms
    for k in range(back + 1500):
        now = 1e-3 * k + 3e-4
        if k < 1000 or k >= back:
            sh.on_input(p, {Y: 0.5 * 1e-3 * k}, now, 1e-3 * k)
        ref, mode = sh.reference(p, now)
        refs.append(ref[Y])
        modes.append(mode)
    end = modes.index("", back)  # the playback's start, FIT_S of live input, the blend
    assert modes[back] == "rejoin" and 0 <= end - back - 1e3 * (p.rejoin_s + FIT_S) <= 5, (
        end - back)
    acc = np.diff(np.array(refs[back - 50:end + 50]), 2) / 1e-6
    jerk = np.diff(acc) / 1e-3
    # the blend of a gap of up to 0.6 m over 0.5 s: some m/s^2, its jerk some 100 m/s^3,
    # changing from tick to tick by at most some 10 m/s^3 (its snap; a velocity step: 500 m/s^2
    # at one tick; the minimum-jerk fade's jerk step at its end: 60 g / T^3, 200-300 m/s^3)
    assert np.max(np.abs(acc)) < 30.0, np.max(np.abs(acc))
    assert np.max(np.abs(jerk)) < 1000.0, np.max(np.abs(jerk))
    assert np.max(np.abs(np.diff(jerk))) < 40.0, np.max(np.abs(np.diff(jerk)))


def test_a_lead_plays_a_cubic_back_ahead_exactly() -> None:
    """With ``lead_s`` the playback runs that far ahead of the lag, beyond the newest sample:
    along the newest sample's constant-jerk cubic, exact on a cubic; the lag reported is the
    playback's minus the lead."""
    x = lambda t: 0.3 + t * (0.5 + t * (-0.6 + 0.2 * t))  # noqa: E731
    period = 2.0**-10
    p = ShaperParams(driven=(True,) * 8, ramp_speed=(1.0,) * 8, reach_lo=(-10.0,) * 8,
                     reach_hi=(10.0,) * 8, startup_s=0.0, tick_s=period, lead_s=0.003)
    sh = ReferenceShaper(8)
    errs = []
    for k in range(2000):
        now = period * k + 3e-4
        sh.on_input(p, {Y: x(period * k)}, now, 1.7e9 + period * k)
        ref, _ = sh.reference(p, now)
        if k > 1000:
            tau = now - sh.playback_delay_s + 0.003
            assert tau > period * k  # ahead of the newest sample
            errs.append(ref[Y] - x(tau))
    assert max(map(abs, errs)) < 1e-9
    assert sh.lag_s == pytest.approx(max(p.playback_lag_s, period) - 0.003, abs=2e-5)


@pytest.mark.parametrize(("src_hz", "lead_s"), [(100.0, 0.0145), (250.0, 0.0055)])
def test_a_lead_takes_the_lag_off_a_slow_sender(src_hz: float, lead_s: float) -> None:
    """A 100 Hz (250 Hz) sender with t and 300 us jitter, the lead set to the lag: the slalom's
    reference lags its trajectory by about 1 ms instead of 15.5 ms (6.5 ms), beyond the band
    limit's own delay, the limiter never
    acts, and the compensated command's HF acceleration stays within 2x the ideal 1 kHz run's
    (1.8x and 1.1x measured; docs/TUNING.md, "Prediction", has the lane change's price)."""
    plain, ahead = [], []
    _jittery(_cfg("smooth"), "slalom", src_hz, 300.0, False, True, False, ref_delay=plain)
    share, hf = _jittery(_cfg("smooth", lead_s), "slalom", src_hz, 300.0, False, True, False,
                         ref_delay=ahead)
    band = new_tick(_cfg("smooth"))[0].shaper.band[Y]  # a pure delay in the band, apart
    assert band is not None
    assert plain[0] - band.delay_s > 0.006 and abs(ahead[0] - band.delay_s) < 0.0015
    assert plain[0] - ahead[0] == pytest.approx(lead_s, abs=5e-4)
    assert share == 0.0 and hf <= 2.0 * _floor(False)


def test_the_start_blend_of_a_sender_without_t_waits_for_its_instants() -> None:
    """A sender without ``t`` on a starved host: a 0.3 m, 0.31 Hz sine on rails_y from its
    first frame (0.58 m/s), sent in bursts whenever the sender gets the CPU (every 2-8 ms).
    The start blend waits until the instants' line spans UNSTAMPED_SETTLE_S, so it merges the
    motion at its rate: the limiter never acts over the 6 s and the blend is over within 3 s of
    the first frame (blending after 50 ms, as before: the limiter acted on 3362 ticks, the blend
    lasted 3.4 s; in runs recorded on one core, 812-1590 ticks and 3.1-3.6 s)."""
    cfg = _cfg("smooth")
    params, state = new_tick(cfg, resolve_axes(cfg))
    rng = np.random.default_rng(3)
    n = 6000
    arrive = np.empty(n)
    k = 0
    wake = 0.0
    while k < n:  # the sender wakes every 5-25 ms and sends what is due
        wake += rng.uniform(2e-3, 8e-3)
        while k < n and k * 1e-3 <= wake:
            arrive[k] = wake + rng.uniform(0.0, 3e-4)
            k += 1
    j, first, limited, blend_end = 0, None, 0, None
    for tick in range(n):
        now = tick * 1e-3
        frames = []
        while j < n and arrive[j] <= now:
            x = 0.3 * math.sin(2.0 * math.pi * 0.31 * j * 1e-3)
            frames.append(msgpack.packb({"seq": j, "pos": {"rails_y": x}}))
            j += 1
        out = step(state, params, 10**9 + tick * 1_000_000, frames or None)
        if first is None and j:
            first = now
        limited += bool(out.limited[Y])
        if first is not None and "rejoin" not in out.flags and blend_end is None \
                and now - first > 0.1:
            blend_end = now - first
    assert limited == 0, (limited, blend_end)
    assert blend_end is not None and blend_end <= 3.0, blend_end
