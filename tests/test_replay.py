"""Offline replay against the service itself.

Sessions are produced on virtual time by the service's own ``tick`` (motcomp.replay.synth):
jittery transit, a drifting sender clock, loop stalls with catch-up, bypass switches, silent
gaps (stale, hold, ramp, rejoin), steps the limiter must absorb, partial frames, frames without
``t`` and bad frames.  The recorded outputs are then the ground truth:

* the reference engine (the service's ``tick`` driven by the rebuilt plan) reproduces them bit
  for bit;
* the offline engine agrees to ~1e-11 (floating-point ordering in ``lfilter``), and is itself
  bit-reproducible.
"""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motcomp.config import load_config, resolve_axes
from motcomp.core.saturation import axis_constants, limit_axis
from motcomp.record import Session, read_session
from motcomp.replay.engine import _limit, _params, _State, run_fast, run_ticks, saturated
from motcomp.replay.offline import plan_for
from motcomp.replay.plan import TickPlan
from motcomp.replay.reference import _offsets
from motcomp.replay.synth import SynthOptions, synthesize
from motcomp.resources import config_file
from motcomp.runtime.shaper import OFFSET_LEAK
from tests.conftest import motcomp_cmd, subprocess_env

CFG = load_config(config_file("motcomp.toml"))
AXES_CFG = resolve_axes(CFG)
RICH = SynthOptions(duration_s=8.0, seed=1, stalls=[(2.5, 3), (4.0, 30)], gaps=[(3.0, 0.3)],
                    bypass=[(1.5, True, ("rails_x",)), (5.0, False, ("rails_x",))],
                    steps=[(6.0, "rails_y", 0.3)], partial_every=7, bad_every=50,
                    no_t_every=13)


@pytest.fixture(scope="module")
def rich(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replay") / "rich.mcap"
    synthesize(path, CFG, RICH)
    return path


def recorded_rows(plan: TickPlan, session: Session) -> tuple[np.ndarray, np.ndarray]:
    assert session.outputs is not None
    rows = np.flatnonzero(plan.output >= 0)
    return rows, session.outputs.pos[plan.output[rows]]


def test_reference_engine_reproduces_the_service_bit_for_bit(rich: Path) -> None:
    s = read_session(rich)
    plan = plan_for(s, CFG, AXES_CFG)
    assert plan.method == "outputs+clock" and not plan.warm
    assert len(plan.bypass_events) == 2
    assert s.inputs is not None and (s.inputs.reason != 0).sum() >= 3  # the bad frames
    assert (~plan.emit).sum() == 3 + 20  # catch-up steps (at most MAX_CATCH_UP per stall)
    res = run_ticks(plan, s.inputs, CFG)
    rows, rec = recorded_rows(plan, s)
    assert np.array_equal(res.u[rows], rec)


def test_fast_engine_agrees_with_the_service(rich: Path) -> None:
    s = read_session(rich)
    plan = plan_for(s, CFG, AXES_CFG)
    fast = run_fast(plan, s.inputs, CFG, AXES_CFG)
    exact = run_ticks(plan, s.inputs, CFG)
    rows, rec = recorded_rows(plan, s)
    diff = np.abs(fast.u[rows] - rec)
    assert diff.max() < 1e-9, diff.max(axis=0)
    # compensated rails: lfilter ordering, ~1e-11; bypassed axes: ~1e-13 (the limiter's
    # third-order target tracker through lfilter where the limiter acts)
    assert diff[:, 2:].max() < 1e-12
    # the reference is the service's, bit for bit, where every frame carries the axis
    assert np.array_equal(fast.ref[rows, :2], exact.ref[rows, :2])
    # the limiter acted (steps, jitter) and the saturation verdicts agree with the recording
    sat = saturated(fast, CFG.status.saturation_tolerance)[rows]
    flags = s.outputs.flags[plan.output[rows]]
    rec_sat = ((flags[:, None] >> np.arange(8)) & 1).astype(bool)
    assert sat[:, 1].sum() > 100
    assert np.array_equal(sat, rec_sat)
    # modes: stale after the gap, rejoin after it
    assert {"stale", "rejoin"} <= {("", "rejoin", "stale", "parking")[m] for m in fast.mode}


def test_fast_engine_is_deterministic(rich: Path) -> None:
    s = read_session(rich)
    plan = plan_for(s, CFG, AXES_CFG)
    a = run_fast(plan, s.inputs, CFG, AXES_CFG)
    b = run_fast(plan, s.inputs, CFG, AXES_CFG)
    assert np.array_equal(a.u, b.u) and np.array_equal(a.flags, b.flags)


def test_warm_start_lost_outputs_and_parking(tmp_path: Path) -> None:
    path = tmp_path / "warm.mcap"
    synthesize(path, CFG, SynthOptions(duration_s=8.0, seed=4, record_from_s=6.0,
                                       lose_outputs=[(6.5, 40)], park_at_s=7.0))
    s = read_session(path)
    plan = plan_for(s, CFG, AXES_CFG)
    assert plan.warm and plan.park is not None and (plan.output < 0).sum() >= 40
    fast = run_fast(plan, s.inputs, CFG, AXES_CFG)
    exact = run_ticks(plan, s.inputs, CFG)
    rows, rec = recorded_rows(plan, s)
    assert np.abs(fast.u[rows] - exact.u[rows]).max() < 1e-9
    # parked at neutral at the end
    assert np.abs(fast.u[-1]).max() < 1e-6
    # started at rest mid-run: the difference from the recording dies out
    late = plan.now_ns[rows] - plan.now_ns[0] > 1.0e9
    assert np.abs(fast.u[rows][late] - rec[late]).max() < 1e-3


def test_inputs_only_recording(tmp_path: Path) -> None:
    path = tmp_path / "inputs.mcap"
    synthesize(path, CFG, SynthOptions(duration_s=4.0, seed=5, feedback=False))
    s = read_session(path)
    s.outputs = None
    plan = plan_for(s, CFG, AXES_CFG)
    assert plan.method == "inputs"
    fast = run_fast(plan, s.inputs, CFG, AXES_CFG)
    exact = run_ticks(plan, s.inputs, CFG)
    assert np.abs(fast.u - exact.u).max() < 1e-9


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31), st.sampled_from([-1.75e9, 1.2e9, 3.0, 0.0]))
def test_offset_scan_equals_the_shaper_loop(seed: int, base: float) -> None:
    rng = np.random.default_rng(seed)
    n = 300
    now = 1000.0 + np.cumsum(rng.uniform(0.0, 2e-3, n))
    transit = base + rng.uniform(0.0, 5e-4, n) if base else np.zeros(n)
    off0 = base + 1e-4 if base else 0.0
    expect = np.empty(n)
    off, at = off0, 999.9
    for i in range(n):  # ReferenceShaper.on_input
        off = transit[i] if transit[i] < off else min(off + OFFSET_LEAK * (now[i] - at),
                                                      transit[i])
        at = now[i]
        expect[i] = off
    assert np.array_equal(_offsets(off0, 999.9, now, transit), expect)


@pytest.mark.parametrize("case", ["sine_bursts_step", "end_stops"])
def test_limiter_stretches_equal_limit_axis(case: str) -> None:
    lim = axis_constants(AXES_CFG.limits, 1e-3)[1]  # rails_y: +-2.6 m, 2 m/s, 6 m/s^2
    rng = np.random.default_rng(2)
    t = np.arange(20000) * 1e-3
    if case == "sine_bursts_step":
        target = 0.4 * np.sin(2 * math.pi * 0.4 * t) + np.where(
            rng.random(t.size) < 0.01, rng.normal(0, 0.02, t.size), 0)
        target[5000:] += 0.3
    else:  # driven into the end stops and beyond: the braking bound acts
        target = 3.0 * np.sin(2 * math.pi * 0.1 * t + 1.0) + np.where(
            rng.random(t.size) < 0.005, rng.normal(0, 0.05, t.size), 0)
    prm = _params(CFG, AXES_CFG)[1]
    u, flags = _limit(target, _State(0.0, prm), lim)
    ref = np.empty_like(u)
    ref_flags = np.empty(u.size, dtype=np.int64)
    u0 = v0 = sp = sv = sa = 0.0
    for i, x in enumerate(target.tolist()):
        u0, v0, sp, sv, sa, ref_flags[i] = limit_axis(x, u0, v0, sp, sv, sa, lim)
        ref[i] = u0
    assert (flags != 0).sum() > 100
    if case == "end_stops":
        assert 2.55 < u.max() <= 2.6 and -2.6 <= u.min() < -2.55  # at the stops
    # the tracker's lfilter vs its recursion: ~1e-11 m where the limiter acts
    assert np.abs(u - ref).max() < 1e-10
    # Verdicts agree everywhere except, possibly, a sample resting on an end stop: there the
    # target is clipped to the stop and "feasible" means the last command sits *exactly* on it,
    # which a 1e-11 m difference decides either way (scipy's lfilter rounds differently across
    # releases).  Such a sample is at the stop in both, with the same output.
    differ = np.nonzero((flags != 0) != (ref_flags != 0))[0]
    at_stop = np.minimum(np.abs(ref[differ] - 2.6), np.abs(ref[differ] + 2.6)) < 1e-9
    assert at_stop.all(), (differ[~at_stop], flags[differ], ref_flags[differ])
    assert differ.size <= 3


def test_cli_json_compare_and_figures(rich: Path, tmp_path: Path) -> None:
    other = tmp_path / "amigo.toml"
    other.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[defaults]\nrule = "amigo"\n')
    p = subprocess.run(motcomp_cmd("replay", str(rich), "--compare", str(other), "--json",
                                   "--out", str(tmp_path / "fig"), "--quiet"),
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["method"] == "outputs+clock" and len(out["runs"]) == 2
    base, amigo = out["runs"]
    rails_y = {a["axis"]: a for a in base["axes"]}["rails_y"]
    assert rails_y["max_diff"] < 1e-9 and rails_y["delay_off_ms"] > 150
    assert rails_y["delay_on_ms"] < rails_y["delay_off_ms"] - 50
    assert not amigo["recorded_config"]
    assert all(Path(f).is_file() for f in out["figures"]) and out["figures"]
    assert "Traceback" not in p.stderr


def test_cli_without_a_recorded_config_asks_for_one(tmp_path: Path) -> None:
    path = tmp_path / "bare.mcap"
    from motcomp.record.recorder import SessionWriter

    with SessionWriter(path, ["sim/motion/setpoint"]) as w:
        w.write("sim/motion/setpoint", 1, b"\x81\xa3seq\x00")
    p = subprocess.run(motcomp_cmd("replay", str(path), "--quiet"), capture_output=True,
                       text=True, env=subprocess_env(), timeout=60)
    assert p.returncode == 2 and "--config" in p.stderr and "Traceback" not in p.stderr
