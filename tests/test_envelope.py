"""The hardware envelope: plausibility of every limit, limits inside the envelope, the envelope
guard of the tick (:mod:`motcomp.core.envelope`) and the start-up check of its files.

The property: for any config and reload sequence (limits drawn inside and outside the envelope;
those outside refused) and any input stream (values in and out of range, huge, NaN, seq jumps,
garbage, gaps, missed deadlines), no output of :func:`motcomp.core.tick.step` leaves the envelope
in position, velocity or acceleration."""

from __future__ import annotations

import math
import os
import subprocess
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from motcomp.config import (
    RESTART_KEYS,
    check_envelope,
    load_config,
    new_tick,
    parse_config,
    read_toml,
    resolve_axes,
)
from motcomp.core.axes import AXES
from motcomp.core.envelope import TOLERANCE_M, EnvelopeGuard, EnvelopeParams
from motcomp.core.saturation import AxisLimits
from motcomp.core.tick import TickOutput, TickParams, TickState, step
from motcomp.errors import ConfigError
from motcomp.io.wire import encode_input
from motcomp.resources import config_file
from tests.conftest import motcomp_cmd, subprocess_env

MS = 1_000_000  # ns
H = 1e-3  # s, the example's period
EXAMPLE = config_file("motcomp.toml")
Y, X, ROLL = AXES.index("rails_y"), AXES.index("rails_x"), AXES.index("hex_roll")
# the shipped envelope, written out here (not read from the code under test)
SHIPPED: dict[str, tuple[float, float, float, float]] = {
    "rails_x": (-2.6, 2.6, 2.5, 8.0), "rails_y": (-2.6, 2.6, 2.5, 8.0),
    "hex_x": (-0.3, 0.3, 0.8, 10.0), "hex_y": (-0.3, 0.3, 0.8, 10.0),
    "hex_z": (-0.2, 0.2, 0.6, 10.0), "hex_roll": (-0.35, 0.35, 1.0, 8.0),
    "hex_pitch": (-0.35, 0.35, 1.0, 8.0), "hex_yaw": (-0.4, 0.4, 1.0, 8.0)}
LIN = ("pos_min_m", "pos_max_m", "vel_max_m_s", "acc_max_m_s2")
ROT = ("pos_min_rad", "pos_max_rad", "vel_max_rad_s", "acc_max_rad_s2")


@cache
def example_data() -> dict[str, Any]:
    return read_toml(EXAMPLE)


def with_limits(**axes: tuple[float, float, float, float]) -> dict[str, Any]:
    """The example's document with the limits of some axes replaced."""
    data = read_toml(EXAMPLE)
    for axis, row in axes.items():
        keys = ROT if axis.startswith("hex_r") or axis.startswith("hex_p") or axis == "hex_yaw" \
            else LIN
        data["axes"][axis].update(dict(zip(keys, row, strict=True)))
    return data


def assert_within_envelope(outs: list[TickOutput], dts: list[float],
                           env: dict[str, tuple[float, float, float, float]]) -> None:
    """Position, velocity and acceleration of the emitted commands within ``env``, starting at
    rest at neutral.  ``dts[k]`` is the time from output k-1 to output k: the velocity over a
    gap of several periods is the mean of the per-period ones, and the difference of two
    adjacent means over the distance of their centres is bounded by the acceleration limit as
    each period's is."""
    u = np.array([[0.0] * len(AXES)] + [o.u for o in outs])
    dt = np.array(dts)
    assert np.all(np.isfinite(u))
    v = np.diff(u, axis=0) / dt[:, None]
    v = np.vstack([np.zeros(len(AXES)), v])
    dt_mid = (np.concatenate([[dt[0]], dt]) + np.concatenate([dt, [dt[-1]]]))[:-1] / 2
    a = np.diff(v, axis=0) / dt_mid[:, None]
    slack = 10 * TOLERANCE_M  # per period, in position: rounding, far below any motion
    for i, axis in enumerate(AXES):
        lo, hi, vmax, amax = env.get(axis, (0.0, 0.0, 0.0, 0.0))
        assert u[:, i].max() <= hi + slack and u[:, i].min() >= lo - slack, axis
        assert np.abs(v[:, i]).max() <= vmax + slack / H, (axis, np.abs(v[:, i]).max())
        assert np.abs(a[:, i]).max() <= amax + slack / H**2, (axis, np.abs(a[:, i]).max())


# --- plausibility and the envelope in the config -------------------------------------------------
@pytest.mark.parametrize(("key", "value", "bound"), [
    ("pos_min_m", -1e308, "[-10, 10] m"), ("pos_max_m", 1e308, "[-10, 10] m"),
    ("pos_max_m", 1000.0, "[-10, 10] m"), ("vel_max_m_s", 1e308, "(0, 10] m/s"),
    ("acc_max_m_s2", 1e308, "(0, 100] m/s^2"),
])
def test_implausible_limit_is_refused_naming_key_value_and_bound(key: str, value: float,
                                                                 bound: str) -> None:
    data = read_toml(EXAMPLE)
    data["axes"]["rails_y"][key] = value
    with pytest.raises(ConfigError) as exc:
        parse_config(data, "site.toml")
    text = str(exc.value)
    assert f"axes.rails_y.{key}" in text and repr(value) in text and bound in text, text


def test_issue_reload_file_of_1e308_limits_is_refused() -> None:
    """The issue's site file: every rails_y limit at +-1e308."""
    data = read_toml(EXAMPLE)
    data["axes"]["rails_y"].update(pos_min_m=-1e308, pos_max_m=1e308, vel_max_m_s=1e308,
                                   acc_max_m_s2=1e308)
    with pytest.raises(ConfigError, match=r"axes\.rails_y\.pos_min_m.*-10, 10\] m.*-1e\+308"):
        parse_config(data, "site.toml")


@pytest.mark.parametrize(("axis", "j", "value"), [
    ("rails_y", 1, 2.7), ("rails_y", 0, -3.0), ("rails_x", 2, 2.6), ("rails_x", 3, 9.0),
    ("hex_z", 1, 0.25), ("hex_roll", 0, -0.5), ("hex_yaw", 2, 1.5), ("hex_pitch", 3, 8.5),
])
def test_limit_outside_the_envelope_is_refused(axis: str, j: int, value: float) -> None:
    half = [x * 0.5 for x in SHIPPED[axis]]
    half[j] = value
    row = (half[0], half[1], half[2], half[3])
    keys = ROT if axis in ("hex_roll", "hex_pitch", "hex_yaw") else LIN
    with pytest.raises(ConfigError) as exc:
        parse_config(with_limits(**{axis: row}), "site.toml")
    assert (f"axes.{axis}.{keys[j]} = {value!r} lies outside envelope.{axis}.{keys[j]} = "
            f"{SHIPPED[axis][j]!r}") in str(exc.value)


def test_limit_from_defaults_outside_the_envelope_names_defaults() -> None:
    data = read_toml(EXAMPLE)
    del data["axes"]["rails_x"]["vel_max_m_s"]
    data["defaults"]["vel_max_m_s"] = 3.0
    with pytest.raises(ConfigError, match=r"defaults\.vel_max_m_s = 3\.0 lies outside "
                                          r"envelope\.rails_x\.vel_max_m_s = 2\.5"):
        parse_config(data)


def test_limits_equal_to_the_envelope_are_accepted() -> None:
    cfg = parse_config(with_limits(**SHIPPED))
    lim = resolve_axes(cfg).limits
    assert lim.v_max[Y] == 2.5 and lim.a_max[ROLL] == 8.0


@pytest.mark.parametrize(("envelope", "message"), [
    ({"rails_y": {"pos_min_m": -2.6, "pos_max_m": 2.6, "vel_max_m_s": 2.5,
                  "acc_max_m_s2": 1e308}}, "envelope.rails_y.acc_max_m_s2"),
    ({"rails_y": {"pos_min_m": 2.6, "pos_max_m": -2.6, "vel_max_m_s": 2.5,
                  "acc_max_m_s2": 8.0}}, "envelope.rails_y: limits of rails_y: pos_min_m"),
    ({"rails_y": {"pos_min_rad": -1, "pos_max_rad": 1, "vel_max_rad_s": 1,
                  "acc_max_rad_s2": 1}}, "use the wrong unit"),
    ({"rails_z": {"pos_min_m": -1, "pos_max_m": 1, "vel_max_m_s": 1, "acc_max_m_s2": 1}},
     "envelope.rails_z: unknown axis"),
    ({"rails_y": {"pos_min_m": -2.6, "pos_max_m": 2.6, "vel_max_m_s": 2.5}},
     "missing acc_max_m_s2"),
])
def test_bad_envelope_is_refused(envelope: dict[str, Any], message: str) -> None:
    data = read_toml(EXAMPLE)
    data["envelope"].update(envelope)
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        parse_config(data)


def test_envelope_is_a_restart_key() -> None:
    assert "envelope" in RESTART_KEYS


def test_shipped_configs_carry_the_envelope_of_every_driven_axis() -> None:
    for name in ("motcomp.toml", "demo.toml"):
        cfg = load_config(config_file(name))
        axes = resolve_axes(cfg)
        for i, axis in enumerate(AXES):
            assert axes.driven[i] and axes.envelope[i] == SHIPPED[axis], (name, axis)


# --- the guard -------------------------------------------------------------------------------
def one_axis(p: tuple[float, float, float, float], rate_hz: float = 1000.0) -> EnvelopeParams:
    return EnvelopeParams((p[0],), (p[1],), (p[2],), (p[3],), rate_hz)


def guard_run(params: EnvelopeParams, commands: list[float]) -> tuple[list[float], EnvelopeGuard]:
    g = EnvelopeGuard(1)
    out = []
    for x in commands:
        u = [x]
        g.apply(params, u)
        out.append(u[0])
    return out, g


def check_one(out: list[float], p: tuple[float, float, float, float], h: float) -> None:
    u = np.concatenate([[0.0, 0.0], out])
    v = np.diff(u) / h
    a = np.diff(v) / h
    assert np.all(np.isfinite(u))
    slack = 10 * TOLERANCE_M
    assert u.max() <= p[1] + slack and u.min() >= p[0] - slack
    assert np.abs(v).max() <= p[2] + slack / h
    assert np.abs(a).max() <= p[3] + slack / h**2
    # the braking condition: it can always stop inside the range
    stop = u[1:] + np.sign(v) * v**2 / (2 * p[3])
    assert stop.max() <= p[1] + 1e-9 and stop.min() >= p[0] - 1e-9


def test_guard_passes_a_feasible_command_bit_exactly() -> None:
    """A min-jerk move to 2 m and back in 2 s each: peak 1.875 m/s and 5.8 m/s^2 < 2.5, 8."""
    t = np.arange(0, 2.0, H)
    s = t / 2.0
    up = 2.0 * (10 * s**3 - 15 * s**4 + 6 * s**5)
    cmd = [*up, *up[::-1], *np.zeros(100)]
    out, g = guard_run(one_axis(SHIPPED["rails_y"]), list(map(float, cmd)))
    assert out == [float(x) for x in cmd]
    assert g.clamps == 0 and g.acted == [0]


@settings(max_examples=150, deadline=None)
@given(cmd=st.lists(st.one_of(st.floats(-20, 20), st.sampled_from(
           [math.nan, math.inf, -math.inf, 1e308, -1e308, 2.6, -2.6])), min_size=1, max_size=60),
       hold=st.integers(1, 40), rate=st.sampled_from([100.0, 1000.0, 2000.0]),
       row=st.tuples(st.floats(0.01, 10), st.floats(0.01, 10), st.floats(0.01, 10),
                     st.floats(0.1, 100)))
def test_guard_keeps_any_command_within_the_envelope(cmd: list[float], hold: int, rate: float,
                                                     row: tuple[float, ...]) -> None:
    p = (-row[0], row[1], row[2], row[3])
    out, _ = guard_run(one_axis(p, rate), [x for x in cmd for _ in range(hold)])
    check_one(out, p, 1.0 / rate)


def test_guard_rejoins_the_command_after_acting() -> None:
    """A command that jumps 1 m (a bug upstream) and then moves on smoothly: the guard brings
    the output there within the envelope, next to no overshoot, and then follows it exactly."""
    p = SHIPPED["rails_y"]
    t = np.arange(0, 4.0, H)
    smooth = 0.3 * np.sin(2 * np.pi * 0.25 * t)
    cmd = smooth + np.where(t >= 1.0, 1.0, 0.0)
    out, g = guard_run(one_axis(p), list(map(float, cmd)))
    check_one(out, p, H)
    out_a = np.array(out)
    k = int(1.0 / H)
    assert out_a[k] < cmd[k] and g.acted[0] > 0
    # approaches from below; the relative velocity left at contact (a few a_max h, a discrete
    # approach to a curving command) passes it by micrometres (13 um here), no more
    assert np.max(out_a[k:] - cmd[k:]) < 5e-5
    rejoined = np.flatnonzero(out_a != cmd)[-1] * H
    assert rejoined < 2.0, rejoined  # 1 m at <= 2.5 m/s and 8 m/s^2: well within a second
    assert np.array_equal(out_a[int(2.0 / H):], cmd[int(2.0 / H):])


def test_guard_holds_an_undriven_axis_at_neutral() -> None:
    out, g = guard_run(one_axis((0.0, 0.0, 0.0, 0.0)), [0.0, 0.0, 1e-3, math.nan, 0.0])
    assert out == [0.0] * 5 and g.acted == [2]


def test_envelope_params_refuse_a_range_without_neutral() -> None:
    with pytest.raises(ValueError, match="invalid axis"):
        one_axis((0.1, 1.0, 1.0, 1.0))


# --- the tick: a no-op on normal runs, the envelope for any config and input ------------------
def sines(k: int, amp: float = 0.6) -> dict[str, float]:
    """A feasible motion of every axis, within half of the example's limits."""
    t = k * H
    ramp = min(1.0, t / 2.0) ** 3
    return {a: amp * ramp * SHIPPED[a][1] * 0.5 * math.sin(2 * math.pi * (0.2 + 0.1 * i) * t)
            for i, a in enumerate(AXES)}


@pytest.mark.parametrize("limits", ["example", "equal to the envelope"])
def test_guard_never_acts_on_a_normal_run(limits: str) -> None:
    """The example config (and one whose limits equal the envelope): a motion on all axes,
    a stop (stale, hold, ramp to neutral), a restart and a jittery sender: the limiter keeps
    the command inside, the guard never changes it."""
    cfg = load_config(EXAMPLE) if limits == "example" else parse_config(with_limits(**SHIPPED))
    params, state = new_tick(cfg)
    rng = np.random.default_rng(1)
    outs = []
    for k in range(9000):
        stopped = 3000 <= k < 5000
        if stopped:
            frame = None
        else:
            jitter = rng.normal(0, 0.002) if k > 6000 else 0.0
            frame = encode_input(k, k * H + jitter, sines(k, 1.6 if k > 6000 else 0.6))
        outs.append(step(state, params, k * MS, frame))
    assert state.envelope_clamps == 0 and state.envelope_acted == [0] * len(AXES)
    assert not any(f.startswith("envelope:") for o in outs for f in o.flags)
    assert any(o.mode == "stale" for o in outs) and sum(state.sat) > 0  # the limiter did act
    assert_within_envelope(outs, [H] * len(outs), SHIPPED)


LIMIT_ROWS = st.tuples(st.sampled_from([0.05, 0.5, 1.3, 2.6, 2.61, 5.0, 1e3, 1e308]),
                       st.sampled_from([0.1, 1.0, 2.5, 2.6, 10.0, 1e308]),
                       st.sampled_from([0.2, 1.0, 6.0, 8.0, 8.5, 100.0, 1e308]))
INPUT = st.one_of(
    st.tuples(st.just("ok"), st.floats(-3.9, 3.9)),
    st.tuples(st.just("value"), st.sampled_from([math.nan, math.inf, 1e308, -1e308, 20.0, 3.89])),
    st.tuples(st.just("seq"), st.sampled_from([0, -1, -5, 2, 999, 1001, 2**62, 2**63 - 1])),
    st.tuples(st.just("none"), st.integers(1, 80)),
    st.tuples(st.just("garbage"), st.binary(max_size=20)),
    st.tuples(st.just("skip"), st.integers(1, 4)),
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(reloads=st.lists(st.tuples(st.integers(0, 1500), LIMIT_ROWS, LIMIT_ROWS, st.booleans()),
                        max_size=4),
       events=st.lists(st.tuples(st.integers(1, 60), INPUT), min_size=1, max_size=40))
def test_no_output_leaves_the_envelope(reloads: list[Any], events: list[Any]) -> None:
    """Reloads of rails_y and hex_roll limits (in or outside the envelope: outside refused,
    inside swapped in as the service does) under any input stream; and the same limits given
    to the compensator unchecked, as a bug in the reload would: the guard holds the envelope
    even then."""
    params, state = new_tick(load_config(EXAMPLE))
    todo = sorted(reloads)
    k = seq = 0
    outs: list[TickOutput] = []
    dts: list[float] = []
    for n, (kind, arg) in events:
        for j in range(n):
            while todo and todo[0][0] <= k:
                params = try_reload(state, params, todo.pop(0))
            frame: bytes | None = None
            if kind == "garbage":
                frame = bytes(arg)
            elif kind != "none":
                seq += arg if kind == "seq" and j == 0 else 1
                seq = min(max(seq, 0), 2**64 - 1)
                value = arg if kind in ("ok", "value") else 1.5 * math.sin(k * H * 3)
                frame = encode_input(seq, k * H, {"rails_y": value, "rails_x": -value / 2,
                                                  "hex_roll": value / 20})
            skipped = arg if kind == "skip" else 0
            k += skipped
            outs.append(step(state, params, k * MS, frame, skipped))
            dts.append((skipped + 1) * H)
            k += 1
    assert_within_envelope(outs, dts, SHIPPED)


def try_reload(state: TickState, params: TickParams, reload: Any) -> TickParams:
    """Parse a config with the drawn limits; refused exactly when a limit lies outside the
    envelope (or the plausible range); else swapped in between two ticks as
    :meth:`motcomp.runtime.service.Service.apply_config` does."""
    _, (p_y, v_y, a_y), (p_r, v_r, a_r), bug = reload
    rows = {"rails_y": (-p_y, p_y, v_y, a_y), "hex_roll": (-p_r / 4, p_r / 4, v_r / 2, a_r)}
    if bug:  # the limiter takes them unchecked; the tick's params (and envelope) stay
        axes = resolve_axes(load_config(EXAMPLE))
        lim = np.array([axes.limits.p_min, axes.limits.p_max, axes.limits.v_max,
                        axes.limits.a_max])
        lim[:, Y], lim[:, ROLL] = rows["rails_y"], rows["hex_roll"]
        state.comp.reconfigure(axes.models, axes.gains,
                               AxisLimits(lim[0], lim[1], lim[2], lim[3], AXES))
        return params
    inside = all(lo >= SHIPPED[a][0] and hi <= SHIPPED[a][1] and v <= SHIPPED[a][2]
                 and acc <= SHIPPED[a][3] for a, (lo, hi, v, acc) in rows.items())
    try:
        cfg = parse_config(with_limits(**rows), "reload.toml")
    except ConfigError as exc:
        assert not inside, exc
        assert "envelope" in str(exc) or "plausible" in str(exc), exc
        return params
    assert inside, rows
    axes = resolve_axes(cfg)
    new_params, _ = new_tick(cfg, axes)
    state.comp.reconfigure(axes.models, axes.gains, axes.limits)
    return new_params


# --- the start-up check of the envelope's files --------------------------------------------------
ENVELOPE_TOML = "".join(
    f"{axis} = {{ {', '.join(f'{k} = {v}' for k, v in zip(ROT if axis.startswith(('hex_r', 'hex_p', 'hex_yaw')) else LIN, row, strict=True))} }}\n"  # noqa: E501
    for axis, row in SHIPPED.items())


def site(tmp_path: Path, envelope_file: bool = True) -> Path:
    """A site config in ``tmp_path/etc`` including the example; the envelope in its own file
    (``envelope.toml``, included) or inline."""
    etc = tmp_path / "etc"
    etc.mkdir(mode=0o755, exist_ok=True)
    text = f'include = ["{EXAMPLE}"'
    if envelope_file:
        (etc / "envelope.toml").write_text("[envelope]\n" + ENVELOPE_TOML)
        (etc / "envelope.toml").chmod(0o644)
        text += ', "envelope.toml"'
    text += "]\n"
    path = etc / "site.toml"
    path.write_text(text)
    path.chmod(0o644)
    return path


def test_envelope_files_of_root_or_the_service_user_pass(tmp_path: Path) -> None:
    path = site(tmp_path)
    lines, warnings = check_envelope(path)
    assert warnings == [] and str(path.parent / "envelope.toml") in lines[0]
    assert str(EXAMPLE) not in lines[0]  # every envelope key comes from the included file


@pytest.mark.parametrize("mode", [0o664, 0o646, 0o666])
def test_group_or_other_writable_envelope_file_is_refused(tmp_path: Path, mode: int) -> None:
    path = site(tmp_path)
    env = path.parent / "envelope.toml"
    env.chmod(mode)
    with pytest.raises(ConfigError) as exc:
        check_envelope(path)
    assert str(env) in str(exc.value) and f"mode {mode:04o}" in str(exc.value)
    _, warnings = check_envelope(path, allow_writable=True)
    assert len(warnings) == 1 and f"mode {mode:04o}" in warnings[0]


def test_writable_directory_of_the_envelope_is_refused_unless_sticky(tmp_path: Path) -> None:
    path = site(tmp_path)
    path.parent.chmod(0o777)
    with pytest.raises(ConfigError, match="directory is writable by group or others"):
        check_envelope(path)
    path.parent.chmod(0o1777)
    assert check_envelope(path)[1] == []
    path.parent.chmod(0o755)


@pytest.mark.skipif(os.geteuid() != 0, reason="chown needs root")
def test_envelope_file_of_another_user_is_refused(tmp_path: Path) -> None:
    path = site(tmp_path)
    env = path.parent / "envelope.toml"
    os.chown(env, 12345, 12345)
    with pytest.raises(ConfigError, match="owned by uid 12345, neither root nor the service"):
        check_envelope(path)


def test_inline_envelope_checks_the_file_that_holds_it(tmp_path: Path) -> None:
    path = site(tmp_path, envelope_file=False)
    path.write_text(path.read_text() + "[envelope]\n" + ENVELOPE_TOML)
    path.chmod(0o620)
    with pytest.raises(ConfigError, match=f"{path}: the envelope file is writable"):
        check_envelope(path)


def test_driven_axis_without_envelope_cannot_start(tmp_path: Path) -> None:
    data = read_toml(EXAMPLE)
    del data["envelope"]["hex_yaw"]
    cfg = parse_config(data)  # offline tools take the plausible range ...
    assert resolve_axes(cfg).envelope[AXES.index("hex_yaw")] is None
    path = site(tmp_path)
    with pytest.raises(ConfigError, match=r"envelope\.hex_yaw: missing: every driven axis"):
        check_envelope(path, cfg)  # ... the service does not start so


def test_run_and_config_check_refuse_a_writable_envelope(tmp_path: Path) -> None:
    """``motcomp run`` exits 2 before opening anything; ``motcomp config check`` says the
    same; with ``--allow-writable-envelope`` the check passes (the service then starts)."""
    path = site(tmp_path)
    env = path.parent / "envelope.toml"
    env.chmod(0o664)
    for args in (["run", "--config", str(path)], ["config", "check", str(path)]):
        p = subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                           env=subprocess_env(), timeout=60)
        assert p.returncode == 2, (args, p.stdout, p.stderr)
        assert str(env) in p.stderr and "mode 0664" in p.stderr, p.stderr
    env.chmod(0o644)
    p = subprocess.run(motcomp_cmd("config", "check", str(path)), capture_output=True,
                       text=True, env=subprocess_env(), timeout=60)
    assert p.returncode == 0 and "envelope of rails_x" in p.stdout, p.stderr
