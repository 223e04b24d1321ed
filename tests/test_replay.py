"""Offline replay against the service's own tick.

Sessions are produced on virtual time by :func:`motcomp.core.tick.step`, the function the
service calls every tick (motcomp.replay.synth): jittery transit, a drifting sender clock, loop
stalls with catch-up, bypass switches, silent gaps (stale, hold, ramp, rejoin), steps the
limiter must absorb, partial frames, frames without ``t``, bad frames and parking.  The
recorded outputs are then the ground truth: the replay runs the same function on the recorded
bytes at the recorded instants, so every recorded output -- command, ``src_seq``, saturation,
mode and bypass flags -- comes out the same, bit for bit.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from motcomp.config import load_config, resolve_axes
from motcomp.core.axes import AXES
from motcomp.record import Session, read_session
from motcomp.record.frames import FLAG_BITS
from motcomp.replay.engine import MODES, EngineResult, run_ticks
from motcomp.replay.offline import plan_for, replay_files
from motcomp.replay.plan import TickPlan
from motcomp.replay.synth import SynthOptions, synthesize
from motcomp.resources import config_file
from tests.conftest import motcomp_cmd, subprocess_env

CFG = load_config(config_file("motcomp.toml"))
AXES_CFG = resolve_axes(CFG)
RICH = dict(duration_s=8.0, seed=1, stalls=[(2.5, 3), (4.0, 30)], gaps=[(3.0, 0.3)],
            bypass=[(1.5, True, ("rails_x",)), (5.0, False, ("rails_x",))],
            steps=[(6.0, "rails_y", 0.3)], partial_every=7, bad_every=50, no_t_every=13)


@pytest.fixture(scope="module")
def rich(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replay") / "rich.mcap"
    synthesize(path, CFG, SynthOptions(**RICH))  # type: ignore[arg-type]
    return path


@pytest.fixture(scope="module")
def parked(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replay") / "parked.mcap"
    synthesize(path, CFG, SynthOptions(**RICH, park_at_s=7.0))  # type: ignore[arg-type]
    return path


def recorded_rows(plan: TickPlan, session: Session) -> tuple[np.ndarray, np.ndarray]:
    assert session.outputs is not None
    rows = np.flatnonzero(plan.output >= 0)
    return rows, plan.output[rows]


FLAG_MASK_OF_COLUMNS = sum(v for k, v in FLAG_BITS.items()
                           if not k.startswith(("fallback:", "nopredict:")))
"""The flags :func:`flag_bits` rebuilds from the result's columns (the prediction's are in
:attr:`EngineResult.flags` only)."""


def flag_bits(res: EngineResult, rows: np.ndarray) -> np.ndarray:
    """The output flags of the replayed ticks as :data:`FLAG_BITS` (driven axes' bypass)."""
    bits = np.zeros(rows.size, dtype=np.int64)
    for a, name in enumerate(AXES):
        bits |= np.where(res.limited[rows, a], FLAG_BITS[f"sat:{name}"], 0)
        if AXES_CFG.driven[a]:
            bits |= np.where(res.bypass[rows, a], FLAG_BITS[f"bypass:{name}"], 0)
    for m, mode in enumerate(MODES):
        if mode:
            bits |= np.where(res.mode[rows] == m, FLAG_BITS[mode], 0)
    return bits


@pytest.mark.parametrize("session", ["rich", "parked"])
def test_replay_is_the_service_bit_for_bit(session: str, request: pytest.FixtureRequest) -> None:
    s = read_session(request.getfixturevalue(session))
    plan = plan_for(s, CFG, AXES_CFG)
    assert plan.method == "outputs+clock" and not plan.warm
    assert len(plan.bypass_events) == 2
    assert (~plan.emit).sum() == 3 + 30  # catch-up steps, one per deadline of the two stalls
    assert s.inputs is not None and s.outputs is not None
    res = run_ticks(plan, s.inputs, CFG)
    rows, out = recorded_rows(plan, s)
    assert rows.size == plan.emit.sum() == len(s.outputs)
    assert np.array_equal(res.u[rows], s.outputs.pos[out])
    assert np.array_equal(res.src_seq[rows], s.outputs.src_seq[out])
    # saturation verdicts, modes and bypass flags: the tick's own, as recorded
    assert np.array_equal(flag_bits(res, rows), s.outputs.flags[out] & FLAG_MASK_OF_COLUMNS)
    assert res.flags is not None and np.array_equal(res.flags[rows], s.outputs.flags[out])
    assert res.limited[rows, 1].sum() > 100  # the step drove rails_y into its limits
    modes = {MODES[m] for m in res.mode[rows]}
    assert modes == ({"", "stale", "rejoin", "parking"} if session == "parked"
                     else {"", "stale", "rejoin"})
    # catch-up steps send nothing: no numbers of their own
    assert np.isnan(res.u[~plan.emit]).all() and not res.limited[~plan.emit].any()
    if session == "parked":
        assert plan.park is not None and MODES[res.mode[-1]] == "parking"
        assert np.abs(res.u[-1]).max() < 1e-4  # nearly at neutral when the session ends


def test_the_tick_judges_the_frames(rich: Path) -> None:
    """Plans do not filter frames: from the input arrivals, each tick reads the newest frame,
    bad or not, and the replay's tick rejects the bad ones as the service did."""
    s = read_session(rich)
    assert s.inputs is not None and not s.inputs.decoded.all()  # b"\xc1" frames
    recorded = next(st for _, st in reversed(s.status))["frames"]["rejected_by_reason"]
    s.outputs = None
    plan = plan_for(s, CFG, AXES_CFG)
    assert plan.method == "inputs" and plan.warm
    read = plan.frame[plan.frame >= 0]
    assert (~s.inputs.decoded[read]).sum() > 10  # undecodable frames are fed to the tick
    res = run_ticks(plan, s.inputs, CFG)
    assert set(res.rejected) == {k for k, v in recorded.items() if v} == {
        "decode", "axis", "nonfinite"}
    # the same frames, on ticks rebuilt from the recorder's receive times: nearly the same
    for k, n in res.rejected.items():
        assert abs(n - recorded[k]) <= 0.3 * recorded[k]
    lim = AXES_CFG.limits
    assert np.all((res.u >= lim.p_min) & (res.u <= lim.p_max))


def test_warm_start_lost_outputs_and_parking(tmp_path: Path) -> None:
    path = tmp_path / "warm.mcap"
    synthesize(path, CFG, SynthOptions(duration_s=8.0, seed=4, record_from_s=6.0,
                                       lose_outputs=[(6.5, 40)], park_at_s=7.0))
    s = read_session(path)
    plan = plan_for(s, CFG, AXES_CFG)
    assert plan.warm and plan.park is not None and (plan.output < 0).sum() >= 40
    assert s.inputs is not None and s.outputs is not None
    res = run_ticks(plan, s.inputs, CFG)
    rows, out = recorded_rows(plan, s)
    rec = s.outputs.pos[out]
    # started at rest mid-run, without the start-up blend: at the first frame, then the
    # difference from the recording dies out
    assert res.mode[0] == 0
    late = plan.now_ns[rows] - plan.now_ns[0] > 1.0e9
    predicted = [i for i, p in enumerate(AXES_CFG.prediction) if p is not None]
    pid = [i for i, d in enumerate(AXES_CFG.driven) if d and i not in predicted]
    if pid:
        assert np.abs(res.u[rows][late][:, pid] - rec[late][:, pid]).max() < 1e-3
    # the prefilters (the hexapod's 40 Laguerre functions at 1 Hz, the rails' 31 at 0.7 Hz: a
    # memory of seconds) and the band limit start at rest under a moving reference: their
    # difference decays more slowly -- the rails' by 100x in the first second, the hexapod's
    # (whose motion here is small) stays below where it started
    assert predicted
    first = plan.now_ns[rows] - plan.now_ns[0] < 0.25e9
    for i in predicted:
        early = np.abs(res.u[rows][first][:, i] - rec[first][:, i]).max()
        assert np.abs(res.u[rows][late][:, i] - rec[late][:, i]).max() <= early, AXES[i]
    for i in (AXES.index("rails_x"), AXES.index("rails_y")):
        early = np.abs(res.u[rows][first][:, i] - rec[first][:, i]).max()
        assert np.abs(res.u[rows][late][:, i] - rec[late][:, i]).max() < 0.02 * early
    assert np.abs(res.u[rows][late][:, predicted] - rec[late][:, predicted]).max() < 0.01
    assert np.abs(res.u[-1]).max() < 1e-6  # parked at neutral at the end


def test_jobs_give_the_same_numbers(rich: Path, parked: Path) -> None:
    one = list(replay_files([rich, parked], [None], jobs=1))
    two = list(replay_files([rich, parked], [None], jobs=2))
    assert [f.path for f in two] == [rich, parked] and two[0].session is None
    for a, b in zip(one, two, strict=True):
        (ra,), (rb,) = a.runs, b.runs
        for name in ("u", "ref", "limited", "mode", "src_seq", "bypass"):
            assert np.array_equal(getattr(ra.result, name), getattr(rb.result, name),
                                  equal_nan=name in ("u", "ref")), name
        assert ra.report.as_dict() == rb.report.as_dict()


def test_replay_imports_the_tick_not_the_service() -> None:
    code = ("import sys, motcomp.replay.offline, motcomp.replay.plots, motcomp.cli.replay; "
            "bad = sorted(m for m in sys.modules if m.startswith('motcomp.runtime')); "
            "assert not bad, bad")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=subprocess_env(), timeout=60)
    assert p.returncode == 0, p.stderr


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
    assert rails_y["max_diff"] == 0.0 and rails_y["delay_off_ms"] > 150
    assert rails_y["delay_on_ms"] < rails_y["delay_off_ms"] - 50
    assert rails_y["saturated_samples"] == rails_y["recorded_saturated"] > 100
    assert not amigo["recorded_config"]
    assert all(Path(f).is_file() for f in out["figures"]) and out["figures"]
    assert "Traceback" not in p.stderr


def test_cli_several_files_in_parallel(rich: Path, parked: Path, tmp_path: Path) -> None:
    p = subprocess.run(motcomp_cmd("replay", str(rich), str(parked), "--jobs", "2", "--json",
                                   "--quiet", "--out", str(tmp_path / "fig")),
                       capture_output=True, text=True, env=subprocess_env(), timeout=180)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert [o["file"] for o in out] == [str(rich), str(parked)]
    for o in out:
        rails_y = {a["axis"]: a for a in o["runs"][0]["axes"]}["rails_y"]
        assert rails_y["max_diff"] == 0.0 and o["jobs"] == 2
        assert o["figures"] and all(Path(f).parent.name == Path(o["file"]).stem
                                    for f in o["figures"])


def test_cli_without_a_recorded_config_asks_for_one(tmp_path: Path) -> None:
    path = tmp_path / "bare.mcap"
    from motcomp.record.recorder import SessionWriter

    with SessionWriter(path, ["sim/motion/setpoint"]) as w:
        w.write("sim/motion/setpoint", 1, b"\x81\xa3seq\x00")
    p = subprocess.run(motcomp_cmd("replay", str(path), "--quiet"), capture_output=True,
                       text=True, env=subprocess_env(), timeout=60)
    assert p.returncode == 2 and "--config" in p.stderr and "Traceback" not in p.stderr


def test_the_replay_computes_in_the_recorded_loop_s_floating_point_mode(rich: Path) -> None:
    """Subnormals flushed where the recorded service's status says its loop flushed them (a
    synthetic session says so, as the service does); not for a recording of a service that did
    not (a version before, a CPU without the mode); as the service now does without a status."""
    from motcomp.core.fpmode import FLUSHED
    from motcomp.replay.plan import build_plan, recorded_flushed

    session = read_session(rich)
    assert FLUSHED in session.status[-1][1]["realtime"]
    cfg = load_config(config_file("motcomp.toml"))
    assert build_plan(session, cfg, resolve_axes(cfg)).flushed
    loop = "normal scheduling (realtime_priority = 0); slice 100 us; one sleep per tick"
    assert not recorded_flushed([{"realtime": loop}])
    assert not recorded_flushed([{"realtime": f"{loop}; {FLUSHED}"}, {"realtime": loop}])
    assert recorded_flushed([{"realtime": f"{loop}; {FLUSHED}"}])
    assert recorded_flushed([{"t": 1.0}])


def test_a_compared_config_s_bypass_the_recording_overrides_is_said(rich: Path,
                                                                     tmp_path: Path) -> None:
    """With ``--bypass recorded`` (the default) the recording's bypass switches apply to every
    config: a compared config that bypasses an axis the recording compensated is replayed
    compensated, and the replay says so; ``--bypass config`` replays the config's."""
    from motcomp.replay.offline import config_for, read_for_replay, replay_offline

    session = read_for_replay(rich)
    other = tmp_path / "bypass.toml"
    base_cfg = config_file("motcomp.toml")
    other.write_text(f'include = ["{base_cfg}"]\n[axes.rails_y]\nbypass = true\n')
    base, byp = replay_offline(session, [config_for(session, None), config_for(session, other)])
    said = "the recording's bypass switches apply"
    assert not any(said in n for n in base.plan.notes)
    (note,) = [n for n in byp.plan.notes if said in n]
    assert note.startswith("bypass of rails_y (compensated in the recording, bypassed in this "
                           "config): "), note
    y = AXES.index("rails_y")
    assert np.array_equal(byp.result.u[:, y], base.result.u[:, y], equal_nan=True)
    (own,) = replay_offline(session, [config_for(session, other)], bypass="config")
    assert not any(said in n for n in own.plan.notes) and own.result.bypass[:, y].all()
