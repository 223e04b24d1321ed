"""The blend into live input (:mod:`motcomp.core.blend`), against numpy's polynomials: its basis'
end conditions, its peak factors, the shortest duration within an acceleration, the local cubic;
and the shaper's blends built on it (start-up into a moving input, a rejoin during the ramp to
neutral): continuous to the jerk, within their acceleration, no excursion beyond the motion."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.polynomial import polynomial as npp

from motcomp.config import load_config, resolve_axes, tick_params
from motcomp.core.bandlimit import band_limit_params
from motcomp.core.blend import (
    B0,
    B1,
    B2,
    B3,
    BLEND_ACC_PEAK,
    BLEND_MERGE_PEAK,
    JERK_STRETCH,
    blend_coefficients,
    blend_duration,
    horner,
    jerk_duration,
    local_cubic,
)
from motcomp.core.minjerk import min_jerk, min_jerk_derivatives
from motcomp.core.shaper import (
    BAND_SETTLE_DELAYS,
    FIT_S,
    FIT_WAIT_S,
    ReferenceShaper,
    ShaperParams,
)
from motcomp.sim.ideal import ideal_run

S = np.linspace(0.0, 1.0, 20001)


def derivs(c: tuple[float, ...] | list[float] | np.ndarray, s: float | np.ndarray, m: int
           ) -> np.ndarray:
    c_arr = np.array(c)
    return np.asarray(npp.polyval(s, npp.polyder(c_arr, m) if m else c_arr))


@pytest.mark.parametrize("k, basis", list(enumerate((B0, B1, B2, B3))))
def test_the_basis_starts_as_its_unit_and_ends_at_zero_to_the_jerk(k: int,
                                                                   basis: tuple[float, ...]
                                                                   ) -> None:
    for m in range(4):
        assert derivs(basis, 0.0, m) == pytest.approx(1.0 if m == k else 0.0, abs=1e-12)
        scale = np.max(np.abs(derivs(basis, S, m)))  # the power basis' rounding at s = 1
        assert abs(derivs(basis, 1.0, m)) < 1e-11 * max(scale, 1.0), (k, m)


def test_the_peak_factors() -> None:
    """On a fine grid: |B0''| 6.29 and |B1''| 3.49 (the septic Hermite basis alone: 7.51 and
    5.03), |B1| 0.227: what blend_duration and the excursion figures of the docs use."""
    acc0, acc1 = np.max(np.abs(derivs(B0, S, 2))), np.max(np.abs(derivs(B1, S, 2)))
    assert acc0 == pytest.approx(BLEND_ACC_PEAK, rel=2e-3)
    assert acc0 == pytest.approx(6.29, abs=0.01)
    assert acc1 == pytest.approx(BLEND_MERGE_PEAK, rel=2e-3)
    assert acc1 == pytest.approx(3.49, abs=0.01)
    assert np.max(np.abs(derivs(B1, S, 0))) == pytest.approx(0.227, abs=0.001)
    septic0 = np.array([1.0, 0, 0, 0, -35, 84, -70, 20])
    septic1 = np.array([0.0, 1, 0, 0, -20, 45, -36, 10])
    assert np.max(np.abs(derivs(septic0, S, 2))) == pytest.approx(7.513, abs=1e-3)
    assert np.max(np.abs(derivs(septic1, S, 2))) == pytest.approx(5.028, abs=1e-3)


def peak_acc(g: float, r: float, t: float) -> float:
    return float(np.max(np.abs(g * derivs(B0, S, 2) + r * t * derivs(B1, S, 2)))) / t**2


def test_the_duration_is_the_shortest_within_the_acceleration() -> None:
    rng = np.random.default_rng(3)
    longer = 0
    for _ in range(200):
        g, r = rng.normal(0.0, 0.3), rng.normal(0.0, 0.5)
        acc, base = rng.uniform(0.2, 3.0), rng.choice([0.0, 0.2, 0.5, 1.0])
        t = blend_duration(g, r, acc, base)
        assert t >= base
        if t == base:
            assert base == 0.0 or peak_acc(g, r, t) <= acc * 1.002
            continue
        longer += 1
        assert peak_acc(g, r, t) <= acc * 1.002  # the grid's 65 points against 20001
        assert peak_acc(g, r, 0.99 * t) > acc  # and no shorter one would do
    assert longer > 100
    assert blend_duration(0.3, 0.5, 0.0, 0.7) == 0.7  # no bound
    assert blend_duration(0.0, 0.0, 1.0, 0.7) == 0.7
    # a velocity difference alone: BLEND_MERGE_PEAK |r| / acc
    assert blend_duration(0.0, 0.75, 1.5, 0.0) == pytest.approx(BLEND_MERGE_PEAK * 0.75 / 1.5)


def test_the_carried_over_acceleration_and_jerk_are_clipped() -> None:
    """An estimate's error (a jerk of 1e5 m/s^3: a 1 mm step through the band limit) cannot
    swing a blend: with an acceleration budget each carried-over term takes at most twice it."""
    acc, t = 1.5, 2.0
    wild = blend_coefficients(0.0, 0.0, 50.0, 1e5, t, acc)
    tame = blend_coefficients(0.0, 0.0, 2.0 * acc, 2.0 * acc / (0.0404 * t), t)
    assert np.max(np.abs(derivs(wild, S, 0))) == pytest.approx(
        np.max(np.abs(derivs(tame, S, 0))), rel=1e-2)
    assert np.max(np.abs(derivs(wild, S, 2))) / t**2 <= 4.0 * acc * 1.01
    # within the budget nothing is clipped
    assert blend_coefficients(0.1, 0.2, 1.0, 0.5, t, acc) == blend_coefficients(
        0.1, 0.2, 1.0, 0.5, t)


def test_the_coefficients_start_as_the_difference_and_end_at_zero() -> None:
    g, r, a, j, t = 0.2, -0.6, 1.3, -4.0, 1.7
    c = blend_coefficients(g, r, a, j, t)
    at0 = [derivs(c, 0.0, m) / t**m for m in range(4)]  # d/dt = (1/T) d/ds
    assert at0 == pytest.approx([g, r, a, j], abs=1e-12)
    for m in range(4):
        assert abs(derivs(c, 1.0, m)) < 1e-9
    for s in (0.0, 0.3, 0.77, 1.0):
        assert horner(c, s) == pytest.approx(float(npp.polyval(s, np.array(c))), abs=1e-12)


def test_the_local_cubic_is_exact_on_a_cubic() -> None:
    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(-0.03, 0.0, 25))  # irregular ticks
    x = np.stack([0.1 + 0.5 * t + 0.7 * t**2 + 1.3 * t**3, -2.0 + 3.0 * t**3], axis=1)
    fit = local_cubic(t.tolist(), x.tolist())
    assert fit is not None
    derivs, residual = fit
    e = float(t[-1])  # the derivatives at the latest instant, in closed form
    for (v, a, j), (v0, a0, j0) in zip(derivs, [(0.5 + 1.4 * e + 3.9 * e**2, 1.4 + 7.8 * e, 7.8),
                                                (9.0 * e**2, 18.0 * e, 18.0)], strict=True):
        assert (v, a, j) == pytest.approx((v0, a0, j0), rel=1e-6, abs=1e-9)
    # a cubic is its own least-squares cubic; a bend is not
    assert residual < 1e-12
    bent = np.where(t < -0.015, 0.823 * t, -0.012345 + 0.775 * (t + 0.015))  # 48 mm/s less
    bent_fit = local_cubic(t.tolist(), bent[:, None].tolist())
    assert bent_fit is not None and bent_fit[1] > 1e-5
    assert local_cubic([0.0, 0.001, 0.002], [[1.0]] * 3) is None
    assert local_cubic([0.0, 0.0, 0.001, 0.001], [[1.0]] * 4) is None


def test_the_minimum_jerk_derivatives() -> None:
    c = np.array([0.0, 0, 0, 10, -15, 6])
    for x in (0.0, 0.2, 0.5, 0.9, 1.0):
        assert min_jerk(x) == pytest.approx(float(npp.polyval(x, c)))
        assert min_jerk_derivatives(x) == pytest.approx(
            [float(npp.polyval(x, npp.polyder(c, m))) for m in (1, 2, 3)], abs=1e-12)


# --- the shaper's blends ------------------------------------------------------------------------
SLALOM_A, SLALOM_F = 0.4, 0.3  # the outside senders' rails slalom (m, Hz)
Y = 1


def shaper_params(**kw: object) -> ShaperParams:
    n = 8
    band = band_limit_params(48.0, 1000.0)
    base: dict[str, object] = dict(driven=(True,) * n, ramp_speed=(0.3,) * n,
                                   reach_lo=(-10.0,) * n, reach_hi=(10.0,) * n,
                                   band=(band,) * n, blend_acc=(1.5,) * n)
    base.update(kw)
    return ShaperParams(**base)  # type: ignore[arg-type]


def slalom(t: float, phase: float) -> float:
    return SLALOM_A * float(np.sin(2.0 * np.pi * SLALOM_F * t + phase))


def drive(p: ShaperParams, phase: float, gap: tuple[float, float] | None, seconds: float
          ) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """1 kHz samples of the slalom (their ``t``, 0.3 ms transit), none within ``gap``; the
    reference and the slalom at each tick, and the modes."""
    sh = ReferenceShaper(8)
    refs, live, modes = [], [], []
    for k in range(int(seconds * 1000)):
        t = 1e-3 * k
        now = t + 3e-4
        if gap is None or not gap[0] <= t < gap[1]:
            sh.on_input(p, {Y: slalom(t, phase)}, now, t)
        ref, mode = sh.reference(p, now)
        refs.append(ref[Y])
        live.append(slalom(t, phase))
        modes.append(mode)
    return np.array(refs), np.array(live), modes


@pytest.mark.parametrize("phase", [0.0, 0.6, 1.6, 2.5, 4.0])
@pytest.mark.parametrize("case", ["start", "rejoin while ramping"])
def test_a_blend_into_a_moving_slalom_is_smooth_and_stays_within_the_motion(
        case: str, phase: float) -> None:
    """Into the rails' slalom (0.4 m, 0.3 Hz: up to 0.75 m/s, 1.4 m/s^2) at any phase, from
    neutral at rest (start) or from the ramp to neutral after 1 s without input: the reference's
    acceleration within the blend's 1.5 m/s^2 plus the slalom's own, its jerk changing by at most
    a few m/s^3 a tick (no step of velocity, acceleration or jerk: a velocity step is some
    100 m/s^2 in one tick), and the reference within 0.25 m of the slalom's range (the blend
    of 0.75 m/s over 1.5 m/s^2 needs at least 0.19 m: 0.5 r^2 / a; the quintic blend it replaces
    swung a rejoin to -1.07 m)."""
    p = shaper_params(startup_s=1.0, rejoin_s=0.5)
    gap = None if case == "start" else (3.0, 4.0)
    ref, live, modes = drive(p, phase, gap, 9.0)
    first = 0 if gap is None else 3000
    blend = [k for k in range(first, len(modes)) if modes[k] == "rejoin"]
    assert blend and blend[-1] - blend[0] + 1 == len(blend)  # one blend
    assert (blend[-1] - blend[0]) * 1e-3 < 2.6  # startup_s, or as the velocity needs
    assert set(modes[blend[-1] + 1:]) == {""}  # live after it
    sl = slice(blend[0] - 5 if blend[0] >= 5 else 0, blend[-1] + 50)
    acc = np.diff(ref[sl], 2) / 1e-6
    jerk = np.diff(acc) / 1e-3
    assert np.max(np.abs(acc)) < 1.5 + 1.5, np.max(np.abs(acc))
    assert np.max(np.abs(np.diff(acc))) < 0.05, np.max(np.abs(np.diff(acc)))
    # a jerk step: the mean jerk over 10 ticks against the 10 before (the live jerk's
    # estimate leaves a blip of a tick or two at the start, not a step)
    mean10 = np.convolve(jerk, np.ones(10) / 10.0, mode="valid")
    step = np.max(np.abs(mean10[10:] - mean10[:-10]))
    assert step < 3.0, step
    assert np.max(np.abs(ref)) < SLALOM_A + 0.25, np.max(np.abs(ref))
    # and once live, the slalom a band delay and the playback's lag behind
    assert np.max(np.abs(ref[blend[-1] + 100:] - live[blend[-1] + 100 - 9:-9])) < 2e-3


def start_into_a_ramp(x: Any, ticks: int = 4000) -> tuple[int | None, np.ndarray, np.ndarray,
                                                                 list[str]]:
    """A start into ``x(k)`` (1 kHz samples with ``t``, 0.3 ms transit), the rails' budgets:
    the tick the blend started, the reference and the input at each tick, and the modes."""
    p = shaper_params(startup_s=1.0, rejoin_s=0.5, blend_jerk=(8.1,) * 8)
    sh = ReferenceShaper(8)
    start, refs, xs, modes = None, [], [], []
    for k in range(ticks):
        t = 1e-3 * k
        sh.on_input(p, {Y: x(k)}, t + 3e-4, t)
        ref, mode = sh.reference(p, t + 3e-4)
        if start is None and k and not sh._blend_pending:
            start = k
        refs.append(ref[Y])
        xs.append(x(k))
        modes.append(mode)
    return start, np.array(refs), np.array(xs), modes


@pytest.mark.parametrize("bend_ms", [5, 11, 17, 23, 26, 29, 35])
def test_a_live_input_that_bends_as_the_blend_would_start_is_not_misread(bend_ms: int) -> None:
    """A start into a ramp whose slope drops from 0.823 to 0.775 m/s ``bend_ms`` before the
    blend would start, as the live input's reconstruction did on one core: the cubic through
    a window holding the bend reads an acceleration and a jerk the input does not have (3 m/s^2
    and 373 m/s^3 there, and the blend carried them into a reference of -2.3 m on the rails for
    a slalom within +-0.4 m; -1.7 m here).  The blend waits for a window the cubic explains
    (FIT_TOL), at most FIT_WAIT_S: the reference never goes below the held neutral by more
    than 0.05 mm (the velocity merge's 0.02 mm, as without the bend) nor beyond the input, and
    is live after the blend."""
    plain, _, _, _ = start_into_a_ramp(lambda k: 0.823e-3 * k)
    assert plain is not None
    bend = plain - bend_ms

    def x(k: int) -> float:
        return 0.823e-3 * k if k < bend else 0.823e-3 * bend + 0.775e-3 * (k - bend)

    start, ref, xs, modes = start_into_a_ramp(x)
    assert start is not None and plain <= start <= plain + 2 * FIT_S * 1e3, (plain, start)
    assert np.min(ref) > -5e-5, np.min(ref)
    assert np.all(ref <= xs), np.max(ref - xs)
    live = start + modes[start:].index("")
    assert set(modes[live:]) == {""}


def test_a_live_input_no_cubic_explains_starts_with_its_velocity_only() -> None:
    """A ramp (0.8 m/s) with a 45 Hz ripple of 20 um, which the band limit passes in part: no
    window of FIT_S is a cubic to within shaper.FIT_TOL, so the blend starts FIT_WAIT_S after the
    first full window and carries the live input's velocity, not its acceleration or jerk
    (the ripple's, read off a cubic, would be carried over seconds): the reference takes the
    input's own acceleration at the start (the ripple's, about 1 m/s^2: it dips 0.6 mm below
    the held neutral) and stays within the input's range, and the blend ends."""
    def x(k: int) -> float:
        return 0.8e-3 * k + 2e-5 * float(np.sin(2.0 * np.pi * 45.0 * k * 1e-3))

    plain, _, _, _ = start_into_a_ramp(lambda k: 0.8e-3 * k)
    start, ref, xs, modes = start_into_a_ramp(x)
    assert plain is not None and start is not None
    assert abs(start - (plain + FIT_WAIT_S * 1e3)) <= 2, (plain, start)
    assert np.min(ref) > -1e-3, np.min(ref)
    assert np.max(ref) <= np.max(xs), (np.max(ref), np.max(xs))
    assert modes[-1] == ""


@pytest.mark.parametrize("phase", [0.0, 0.6, 1.1, 1.7, 2.5, 3.0])
def test_the_compensated_command_starts_into_a_moving_slalom_without_a_jolt(phase: float
                                                                            ) -> None:
    """The demo's compensated rails (config/demo.toml) started into the slalom at full speed,
    at any phase: the command never at its 6 m/s^2 acceleration limit and its acceleration
    changing by at most 0.5 m/s^2 a tick (the minimum-jerk blends before: 70-170 ticks at the
    limit, steps of 12 m/s^2 -- a velocity step at the start, a jerk step at the end, which the
    compensator multiplies by about Tp1)."""
    cfg = load_config(Path(__file__).resolve().parents[1] / "config" / "demo.toml")
    t = np.arange(6000) / 1000.0
    run = ideal_run(cfg, {"rails_y": SLALOM_A * np.sin(2.0 * np.pi * SLALOM_F * t + phase)},
                    1000.0, settle_s=0.0)
    acc = np.diff(run.u["rails_y"], 2) * 1e6
    assert np.sum(np.abs(acc) > 5.9) == 0, np.sum(np.abs(acc) > 5.9)
    assert np.max(np.abs(np.diff(acc))) < 0.5, np.max(np.abs(np.diff(acc)))


def blend_start_after_loss(two: bool) -> int:
    """Ticks from the first frame after a 1 s loss of the moving slalom to the blend's start
    (the reference leaving the held one or the ramp), that frame taken alone or with the next
    one in the same tick (``two``)."""
    p = shaper_params(startup_s=1.0, rejoin_s=0.5)
    sh = ReferenceShaper(8)
    held: list[tuple[dict[int, float], float]] = []
    for k in range(4500):
        t = 1e-3 * k
        now = t + 3e-4
        if not 2000 <= k < 3000:
            if two and k == 3000:
                held.append(({Y: slalom(t, 0.0)}, t))
            else:
                for pos, ts in [*held, ({Y: slalom(t, 0.0)}, t)]:
                    sh.on_input(p, pos, now, ts)
                held = []
        sh.reference(p, now)
        if k > 3000 and not sh._blend_pending:  # the blend has started
            return k - 3000
    raise AssertionError("no blend")


def test_two_frames_in_the_first_tick_after_a_loss_wait_as_one() -> None:
    """The blend after a loss waits for the band limit whether the first tick takes one frame
    or two (with two, the playback was ready at once and the loss itself counted as time the
    band limit had run: the blend started on its seeding transient, the compensated command at
    its acceleration limit for 570-980 ticks)."""
    one, two = blend_start_after_loss(False), blend_start_after_loss(True)
    band = band_limit_params(48.0, 1000.0)
    assert band is not None
    assert abs(one - two) <= 2, (one, two)
    assert two * 1e-3 >= BAND_SETTLE_DELAYS * band.delay_s + FIT_S, two


@pytest.mark.parametrize(("g", "r", "a"), [(-0.0209, -0.3673, -1.245), (-0.0417, -0.6822, -0.613),
                                           (0.3, 0.0, 0.0), (0.0, 0.0, 2.0), (0.05, -0.4, 1.0)])
def test_jerk_duration_is_the_shortest_step_within_the_jerk(g: float, r: float, a: float) -> None:
    """The blend over :func:`jerk_duration`'s ``T`` (gap, velocity and acceleration terms; the
    jerk term does not shrink with ``T``) keeps its jerk, the polynomial's third derivative on a
    fine grid, within the bound (to the 65-point grid's resolution, 1 %), and one step shorter
    does not; ``base`` when it already does; no bound: ``base``.  The first two cases are a
    rejoin near the slalom's trough and one away from it (the rails, J = 8.1 m/s^3)."""
    jerk, base = 8.06, 0.5
    T = jerk_duration(g, r, a, 0.0, jerk, base)
    s = np.linspace(0.0, 1.0, 20001)

    def peak(t: float) -> float:
        e = np.polynomial.Polynomial(blend_coefficients(g, r, a, 0.0, t))
        return float(np.abs(e.deriv(3)(s)).max()) / t**3

    assert peak(T) <= 1.01 * jerk
    assert base == T or peak(T / JERK_STRETCH) > 0.99 * jerk
    assert jerk_duration(g, r, a, 0.0, 0.0, base) == base


def test_the_config_gives_each_axis_a_jerk_budget_from_its_model() -> None:
    """``blend_jerk`` = the blend's acceleration budget over the model's lag ``Tp1``: the
    compensated command carries about ``Tp1`` times the reference's jerk (the example's rails:
    1.5 m/s^2 / 0.186 s = 8.1 m/s^3)."""
    cfg = load_config(Path(__file__).resolve().parents[1] / "config" / "motcomp.toml")
    axes = resolve_axes(cfg)
    sp = tick_params(cfg, axes).shaper
    for i, m in enumerate(axes.models):
        assert sp.blend_jerk[i] == pytest.approx(sp.blend_acc[i] / m.Tp1, rel=1e-12)
    assert sp.blend_jerk[1] == pytest.approx(1.5 / 0.1857683128, rel=1e-9)
