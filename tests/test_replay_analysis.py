"""The replay's report against closed forms: the apparent delay of the platform model without
compensation ("delay off") on a host that missed deadlines, the config's model against a
recorded platform that differs from it, and numbers at the bottom of the double range.

The sessions are built by hand (a plan, the tick's results, the recorded streams), so that
what each figure must read follows from the P1D's phase delay
``Td + atan(2 pi f Tp1) / (2 pi f)`` of a pure sine, not from motcomp's own output.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from motcomp.config import load_config, resolve_axes
from motcomp.core.axes import AXES
from motcomp.core.models import P1D, simulate_axis
from motcomp.record.session import FeedbackStream, OutputStream, Session
from motcomp.replay.analysis import (
    AxisReport,
    ReplayReport,
    analyse,
    flush_subnormal,
    number,
    report_text,
)
from motcomp.replay.engine import EngineResult
from motcomp.replay.plan import TickPlan
from motcomp.resources import config_file

CFG = load_config(config_file("motcomp.toml"))
AXES_CFG = resolve_axes(CFG)
RAILS_Y = AXES.index("rails_y")
PERIOD_NS = 1_000_000
RATE = 1000.0
F_HZ = 0.31
AMPLITUDE = 0.4
DURATION_S = 40.0
WALL0 = 1_750_000_000.0
BAND_S = 0.007009175984381921  # the example config's 48 Hz Bessel band limit: a pure delay


def phase_delay_s(model: P1D, f_hz: float) -> float:
    w = 2 * math.pi * f_hz
    return model.Td + math.atan(w * model.Tp1) / w


def motion(t: np.ndarray) -> np.ndarray:
    """A 0.31 Hz sine faded in by a minimum-jerk ramp over 3 s (within the rails' limits)."""
    r = np.clip(t / 3.0, 0, 1)
    return AMPLITUDE * r**3 * (10 - 15 * r + 6 * r**2) * np.sin(2 * math.pi * F_HZ * t)


def stalls(seed: int, share: float) -> list[tuple[int, int]]:
    """``(first missed deadline, count)``: runs of 39-99 missed deadlines, ``share`` of all."""
    rng = np.random.default_rng(seed)
    out, k = [], 2000
    while True:
        n = int(rng.integers(39, 100))
        k += int(n / share * rng.uniform(0.6, 1.4))
        if k + n >= int(DURATION_S * RATE) - 10:
            return out
        out.append((k, n))


def losses(seed: int, every_s: float, most: int) -> list[tuple[int, int]]:
    """``(first lost output, count)``: runs of 1-``most`` outputs about every ``every_s``."""
    rng = np.random.default_rng(seed)
    out, k = [], 500
    while True:
        k += int(every_s * RATE * rng.uniform(0.5, 1.5))
        n = int(rng.integers(1, most + 1))
        if k + n >= int(DURATION_S * RATE) - 10:
            return out
        out.append((k, n))


def session_of(missed: list[tuple[int, int]], u_offset: float = 0.0,
               platform: P1D | None = None, age_s: float = 0.0002,
               lost: Sequence[tuple[int, int]] = ()
               ) -> tuple[Session, TickPlan, EngineResult]:
    """A compensated rails_y session whose reference is :func:`motion` and whose command is
    the reference itself (a feasible target passes the limiter exactly); the deadlines in
    ``missed`` sent nothing (catch-up rows); the recorded outputs are the command plus
    ``u_offset`` on hex_z, less those in ``lost`` (the recorder lost them: gaps in ``seq``);
    the feedback (without ``platform``: none) is ``platform`` driven by the commands as sent,
    held between outputs, its cycles ``age_s`` after the service's ticks (each applies the
    output of the tick before it: the setpoints' age)."""
    n = int(DURATION_S * RATE)
    now_ns = 10**12 + np.arange(n, dtype=np.int64) * PERIOD_NS
    emit = np.ones(n, bool)
    for k, count in missed:
        emit[k:k + count] = False
    t = np.arange(n) / RATE
    ref = np.zeros((n, len(AXES)))
    ref[:, RAILS_Y] = motion(t)
    ref[~emit] = np.nan
    res = EngineResult(ref=ref, u=ref.copy(), limited=np.zeros((n, len(AXES)), bool),
                       mode=np.zeros(n, np.int8), src_seq=np.arange(n),
                       bypass=np.zeros((n, len(AXES)), bool), emit=emit)
    sent = np.flatnonzero(emit)
    kept = np.ones(sent.size, bool)
    for k, count in lost:
        kept[k:k + count] = False
    output = np.full(n, -1)
    output[sent[kept]] = np.arange(int(kept.sum()))  # the recorded output of each row
    plan = TickPlan(now_ns, np.arange(n), output, emit, None, [], None, False,
                    "outputs+clock", PERIOD_NS)
    t_out = WALL0 + sent / RATE
    pos = ref[sent].copy()
    pos[:, AXES.index("hex_z")] += u_offset
    log_ns = np.round(t_out * 1e9).astype(np.int64) + 200_000
    outputs = OutputStream("platform/setpoint", log_ns[kept], log_ns[kept],
                           seq=np.arange(sent.size)[kept], t=t_out[kept], src_seq=sent[kept],
                           pos=pos[kept], flags=np.zeros(int(kept.sum()), np.int64),
                           valid=np.ones(int(kept.sum()), bool))
    feedback = None
    if platform is not None:
        held = pos[np.cumsum(emit) - 1]  # the output in force at each deadline
        y = np.zeros((n, len(AXES)))
        y[:, RAILS_Y] = simulate_axis(platform, held[:, RAILS_Y], RATE)
        fb_t = WALL0 + np.arange(n) / RATE + age_s
        fb_ns = np.round(fb_t * 1e9).astype(np.int64) + 300_000
        feedback = FeedbackStream("platform/feedback", fb_ns, fb_ns, t=fb_t, pos=y,
                                  acc=np.full((n, len(AXES)), np.nan), valid=np.ones(n, bool))
    keys = {"input": "sim/motion/setpoint", "output": "platform/setpoint",
            "feedback": "platform/feedback", "status": "motcomp/status"}
    session = Session([Path("hand.mcap")], keys, {}, None, None, outputs, feedback, [], {}, [],
                      False, 0)
    return session, plan, res


def rails_y(session: Session, plan: TickPlan, res: EngineResult) -> AxisReport:
    rep = analyse(session, plan, res, CFG, AXES_CFG, "hand")
    return {a.axis: a for a in rep.axes}["rails_y"]


def test_delay_off_reads_the_platform_lag_on_a_host_that_misses_deadlines() -> None:
    """15 % of the deadlines missed in runs of 39-99: the limiter of "off" stepped on the
    reference held through the stalls lagged it by 300 ms (a recorded slalom read 494 ms for
    the rails' 196 ms); now it reads the model's phase delay plus what holding the commands
    through the stalls costs, as "on" does."""
    missed = stalls(seed=2, share=0.15)
    share = sum(n for _, n in missed) / (DURATION_S * RATE)
    assert 0.12 < share < 0.18
    quiet = rails_y(*session_of([]))
    loaded = rails_y(*session_of(missed))
    expected_ms = (phase_delay_s(AXES_CFG.plants[RAILS_Y], F_HZ) + BAND_S) * 1e3
    # plus half a period: the model is driven by the commands held over each period
    assert quiet.delay_off_ms == pytest.approx(expected_ms + 0.5, abs=0.5)
    assert quiet.delay_on_ms == pytest.approx(quiet.delay_off_ms, abs=1e-6)  # u = ref
    # holding a command for s periods lags it by s/2 periods on average over the stall
    hold_ms = sum((n * 1e-3) ** 2 / 2 for _, n in missed) / DURATION_S * 1e3
    assert 3.0 < hold_ms < 12.0
    assert loaded.delay_off_ms - quiet.delay_off_ms == pytest.approx(hold_ms, abs=3.0)
    # (the reference joined by straight lines across a stall has kinks the limiter rounds)
    assert loaded.delay_on_ms == pytest.approx(loaded.delay_off_ms, abs=0.1)


def test_the_simulated_delays_count_the_input_s_reconstruction_as_the_recorded_ones_do() -> None:
    """The replayed tick's reference lies behind the input by what its reconstruction adds (the
    playback lag, here 1.7 ms, and 2.5 ms in a stretch of a late sender's): the simulated
    delays, measured behind that reference, add the window's median of it, as the recorded
    delays (behind the recorded input) hold it."""
    session, plan, res = session_of([])
    bare = rails_y(session, plan, res)
    res.lag_s = np.full(plan.rows, 0.0017)
    res.lag_s[:plan.rows // 4] = 0.0025  # a quarter of the run: not the median
    res.lag_s[:10] = np.nan  # before the playback starts
    lagged = rails_y(session, plan, res)
    assert lagged.delay_off_ms == pytest.approx(bare.delay_off_ms + 1.7, abs=1e-6)
    assert lagged.delay_on_ms == pytest.approx(bare.delay_on_ms + 1.7, abs=1e-6)


def test_an_axis_compensated_by_its_prediction_alone_is_compensated() -> None:
    """An axis whose PID is bypassed while its prediction acts (a delay-dominated one: the
    hexapod's in the example config) is compensated, in the replay and in the recording; off
    is the PID bypassed and the prediction off (``nopredict`` or ``fallback``) -- or the PID
    bypassed alone on an axis the config does not predict."""
    from motcomp.record.frames import FLAG_BITS, compensation_off

    bypass, nopredict, fallback = (FLAG_BITS[f"{k}:rails_y"]
                                   for k in ("bypass", "nopredict", "fallback"))
    flags = np.array([0, bypass, bypass | nopredict, bypass | fallback, nopredict])
    assert compensation_off(flags, "rails_y", True).tolist() == [False, False, True, True, False]
    assert compensation_off(flags, "rails_y", False).tolist() == [False, True, True, True, False]
    assert compensation_off(flags, "rails_x", True).tolist() == [False] * 5
    session, plan, res = session_of([])
    # rails_y's PID bypassed throughout (the engine's mask says so), its prediction acting
    res.bypass[:, RAILS_Y] = True
    res.flags = np.full(plan.rows, bypass, np.int64)
    assert session.outputs is not None
    session.outputs.flags[:] = bypass
    predicted = rails_y(session, plan, res)
    assert predicted.compensated and math.isfinite(predicted.delay_on_ms)
    res.flags[:] = bypass | nopredict
    session.outputs.flags[:] = bypass | nopredict
    off = rails_y(session, plan, res)
    assert not off.compensated


def test_the_stack_s_share_is_the_platform_s_not_the_model_s() -> None:
    """A platform that is the config's model but applies each setpoint 0.7 ms after its tick
    (its cycles that much after the service's): the platform's lag behind the commands holds
    those 0.7 ms, which the compensator does not cancel, so the report's error and its *live,
    about* say them (sampled on the platform's cycles, the commands reached the model 0.7 ms
    late too, and the error read 0)."""
    model = AXES_CFG.plants[RAILS_Y]
    session, plan, res = session_of([], platform=model, age_s=0.0007)
    ry = rails_y(session, plan, res)
    assert ry.model_error_ms == pytest.approx(0.7, abs=0.1)
    assert ry.platform_lag_ms - ry.model_lag_ms == pytest.approx(0.7, abs=0.1)
    assert ry.expected_on_ms == pytest.approx(ry.delay_on_ms + 0.7, abs=0.1)


def test_the_model_is_judged_against_the_recorded_platform() -> None:
    """A platform faster than the config's model (Tp1 150 ms against 185.8 ms): the report
    reads the difference of their phase delays at the motion's frequency, which the
    compensator inherits, and says it cannot judge an axis without feedback."""
    model = AXES_CFG.plants[RAILS_Y]
    assert isinstance(model, P1D)
    truth = P1D(K=1.0, Td=model.Td, Tp1=0.150)
    session, plan, res = session_of(stalls(seed=3, share=0.1), platform=truth)
    rep = analyse(session, plan, res, CFG, AXES_CFG, "hand")
    ry = {a.axis: a for a in rep.axes}["rails_y"]
    expected_ms = (phase_delay_s(truth, F_HZ) - phase_delay_s(model, F_HZ)) * 1e3
    assert expected_ms < -20
    assert not ry.model_check
    assert ry.model_error_ms == pytest.approx(expected_ms, abs=1.5)
    assert ry.platform_lag_ms == pytest.approx(phase_delay_s(truth, F_HZ) * 1e3, abs=1.0)
    assert 0.9 < ry.model_fit < 0.999  # a model that differs explains less than all
    assert ry.expected_on_ms == pytest.approx(ry.delay_on_ms + expected_ms, abs=1.5)
    # the same platform as the model: no error, everything explained
    same = rails_y(*session_of(stalls(seed=3, share=0.1), platform=model))
    assert abs(same.model_error_ms) < 0.3 and same.model_fit > 0.99999
    # no feedback at all: said, and the 'on' figure is flagged as the model's answer
    blind = analyse(*session_of([]), CFG, AXES_CFG, "hand")
    text = report_text([blind], [])
    assert "rails_y: a model error cannot be judged offline (no platform feedback recorded)" \
        in text
    assert {a.axis: a for a in blind.axes}["rails_y"].model_check


def test_outputs_the_recorder_lost_neither_bias_the_model_check_nor_hide_it() -> None:
    """A recorder on a loaded host loses a few outputs a second (runs of 1-8): the model check
    reads what it reads on the whole recording -- an 18 ms error where the model was right
    before (its model restarted at rest mid-motion at each loss, in windows of 3-4 s), or no
    judgement at all ("the recorded commands do not move this axis").  Longer losses, which it
    does not bridge, restart the model and leave the model's settling time out of the window."""
    model = AXES_CFG.plants[RAILS_Y]
    assert isinstance(model, P1D)
    faster = P1D(K=1.0, Td=model.Td, Tp1=0.150)
    expected_ms = (phase_delay_s(faster, F_HZ) - phase_delay_s(model, F_HZ)) * 1e3
    frequent = losses(seed=4, every_s=0.4, most=8)
    assert len(frequent) > 60
    for truth, error_ms in ((model, 0.0), (faster, expected_ms)):
        whole = rails_y(*session_of([], platform=truth))
        cut = rails_y(*session_of([], platform=truth, lost=frequent))
        assert not cut.model_check
        assert cut.model_error_ms == pytest.approx(error_ms, abs=1.5)
        assert cut.model_error_ms == pytest.approx(whole.model_error_ms, abs=0.1)
        assert cut.model_fit == pytest.approx(whole.model_fit, abs=1e-3)
    # losses of 30-60 ms about every 6 s: each restarts the model, mid-motion
    long = [(k, int(n)) for k, n in losses(seed=5, every_s=6.0, most=1)]
    long = [(k, 30 + 10 * (i % 4)) for i, (k, _) in enumerate(long)]
    cut = rails_y(*session_of([], platform=model, lost=long))
    assert abs(cut.model_error_ms) < 0.3 and cut.model_fit > 0.9999
    # so often that no window fits between them: said so
    dense = [(k, 30) for k in range(1000, int(DURATION_S * RATE) - 100, 1500)]
    blind = rails_y(*session_of([], platform=model, lost=dense))
    assert math.isnan(blind.model_error_ms)
    assert blind.model_check.startswith("the recorder lost outputs too often"), blind.model_check


def test_lost_outputs_are_bridged_within_the_acceleration_bound() -> None:
    """The commands in force where the recorder lost outputs: on the line joining the outputs
    kept on either side, the lost one in force at each instant (zero-order hold at instants
    spread evenly between them) -- exact for a ramp, within ``a T**2 / 8`` of a parabola of
    acceleration ``a`` over a span ``T``; unknown beyond ``bridge_s`` or before any output."""
    a = 6.0
    t = WALL0 + np.arange(200) / RATE
    for shape, bound in ((lambda x: 0.3 * x, 1e-12), (lambda x: 0.5 * a * x * x, None)):
        pos = np.zeros((t.size, len(AXES)))
        pos[:, RAILS_Y] = shape(np.arange(t.size) / RATE)
        keep = np.ones(t.size, bool)
        keep[50:69] = False  # 19 lost: a span of 20 ms
        keep[120:150] = False  # 30 lost: 31 ms, beyond the bridge
        n = int(keep.sum())
        outputs = OutputStream("platform/setpoint", np.zeros(n, np.int64), np.zeros(n, np.int64),
                               seq=np.arange(t.size)[keep], t=t[keep], src_seq=np.arange(n),
                               pos=pos[keep], flags=np.zeros(n, np.int64),
                               valid=np.ones(n, bool))
        fb = FeedbackStream("platform/feedback", np.zeros(1, np.int64), np.zeros(1, np.int64),
                            t=t[:1], pos=np.zeros((1, len(AXES))),
                            acc=np.zeros((1, len(AXES))), valid=np.ones(1, bool))
        session = Session([Path("hand.mcap")], {}, {}, None, None, outputs, fb, [], {}, [],
                          False, 0)
        at = t + 0.4 / RATE  # between ticks: the output of the tick before is in force
        cmd, known = session.command_in_force("rails_y", at, bridge_s=0.02)
        assert known.tolist() == keep.tolist() and np.isnan(cmd[120:150]).all()
        assert np.array_equal(cmd[keep], pos[keep, RAILS_Y])
        err = np.abs(cmd[50:69] - pos[50:69, RAILS_Y])
        assert err.max() <= (bound if bound is not None else a * 0.02**2 / 8 * (1 + 1e-9))
        if bound is None:
            assert err.max() > 0.5 * a * 0.02**2 / 8  # the bound is the parabola's, not loose
        assert np.isnan(session.command_in_force("rails_y", t[:1] - 1.0, bridge_s=0.02)[0]).all()
        assert np.isnan(session.command_in_force("rails_y", at)[0][50:69]).all()  # no bridge


def test_a_model_forgets_its_start_as_its_step_response_settles() -> None:
    """P1D: the step response is within 1 % of the gain after Td + Tp1 ln(100) (one sample of
    the zero-order hold either way); a pure gain at once; at most the preroll."""
    from motcomp.replay.analysis import PREROLL_S, settle_samples

    m = P1D(K=2.0, Td=0.0175, Tp1=0.1857683128)
    assert settle_samples(m, RATE) == pytest.approx((m.Td + m.Tp1 * math.log(100)) * RATE,
                                                    abs=1.5)
    assert settle_samples(P1D(K=1.0, Td=0.0, Tp1=1e-9), RATE) <= 1
    assert settle_samples(P1D(K=1.0, Td=0.0, Tp1=10.0), RATE) == int(PREROLL_S * RATE)


def test_numbers_at_the_bottom_of_the_range_are_zero() -> None:
    """A replayed command that differs from the recorded one by a subnormal (1.28e-321) is
    the same command: the difference is flushed where it is computed and prints as 0."""
    assert flush_subnormal(1.28e-321) == 0.0 and flush_subnormal(-5e-324) == 0.0
    assert flush_subnormal(2.3e-308) == 2.3e-308 and flush_subnormal(1e-12) == 1e-12
    assert number(1.28e-321, ".2e") == "0" and number(0.0, ".1f") == "0"
    assert number(math.nan, ".1f") == "-" and number(3.25e-7, ".2e") == "3.25e-07"
    session, plan, res = session_of([], u_offset=1.28e-321)
    rep = analyse(session, plan, res, CFG, AXES_CFG, "hand")
    hex_z = {a.axis: a for a in rep.axes}["hex_z"]
    assert hex_z.max_diff == 0.0 and hex_z.rms_diff == 0.0
    assert "e-321" not in report_text([rep], []) and "e-321" not in str(rep.as_dict())
    rep.axes = [AxisReport("rails_y", True, max_diff=1.28e-321)]
    assert "e-321" not in report_text([ReplayReport("x", rep.axes, 1, 1, 1.0, 1)], [])


@pytest.mark.parametrize("superseded", [None, 0, 40, 55])
def test_frames_missing_from_the_recording_are_explained(tmp_path: Path,
                                                         superseded: int | None) -> None:
    """40 input frames missing from a recording: the note says what it means from the
    service's own count of the frames it never received (its status' ``superseded``): none
    (the recorder lost them: what to do), all of them (the sender skipped them: harmless), or
    no such count (both possibilities, and how to tell next time)."""
    import msgpack

    from motcomp.record.mcapio import ScanResult, iter_records
    from motcomp.record.recorder import SessionWriter
    from motcomp.replay.offline import replay_files
    from motcomp.replay.synth import SynthOptions, synthesize

    full = tmp_path / "full.mcap"
    synthesize(full, CFG, SynthOptions(duration_s=3.0, seed=5, axes=("rails_y",)))
    res = ScanResult(full)
    records = list(iter_records(full, result=res))
    (_, _, cfg_json), = res.attachments
    holed = tmp_path / "holed.mcap"
    inputs = 0
    with SessionWriter(holed, sorted({r.topic for r in records}), None, cfg_json, flush_s=0,
                       fsync=False) as w:
        for rec in records:
            data = rec.data
            if rec.topic == "sim/motion/setpoint":
                inputs += 1
                if 1500 <= inputs < 1540:
                    continue
            if rec.topic == "motcomp/status":
                st = msgpack.unpackb(data)
                if superseded is None:  # a service that did not count them
                    del st["frames"]["superseded"]
                else:
                    st["frames"]["superseded"] = superseded if st["t"] > 1_750_000_002 else 0
                data = msgpack.packb(st)
            w.write_raw(rec.topic, rec.log_ns, rec.publish_ns, rec.sequence, data)
    (fr,) = replay_files([holed], [None])
    notes = " ".join(fr.runs[0].plan.notes)
    assert "40 sequence numbers between the first and the last input frame the service used " \
           "are not in the recording" in notes, notes
    if superseded == 40:
        assert "the service did not receive them either" in notes and "nothing it used is " \
            "missing" in notes
    elif superseded == 55:
        assert "but the service's status counted 55 input frames it never received" in notes
        assert "15 frames the recorder received never reached the service" in notes
    elif superseded == 0:
        assert "the service received 40 of them" in notes and "the recorder lost those" in notes
        assert "run `motcomp record` where it gets its CPU" in notes
    else:
        assert "either the sender skipped them (harmless) or the recorder lost" in notes
        assert "record the status key too" in notes


def test_a_restarted_sender_and_a_recording_begun_mid_run_lose_no_frames(tmp_path: Path) -> None:
    """A sender that starts its ``seq`` over after a pause (as every ``motcomp source`` run
    does), recorded from within the pause: the frame the service held when the recording began
    was taken before it, and the new run's numbers repeat the old run's -- neither is a frame
    the recorder lost.  A hole in the second run is still found, though the first run carried
    the same numbers."""
    from motcomp.record.mcapio import ScanResult, iter_records
    from motcomp.record.recorder import SessionWriter
    from motcomp.replay.offline import replay_files
    from motcomp.replay.synth import SynthOptions, synthesize

    mid = tmp_path / "mid.mcap"
    synthesize(mid, CFG, SynthOptions(duration_s=9.0, seed=3, axes=("rails_y",),
                                      gaps=[(5.5, 1.0)], restart_after_gaps=True,
                                      record_from_s=6.0))
    (fr,) = replay_files([mid], [None])
    notes = " ".join(fr.runs[0].plan.notes)
    assert "warm start" in notes and "not in the recording" not in notes, notes

    full = tmp_path / "full.mcap"
    synthesize(full, CFG, SynthOptions(duration_s=5.0, seed=3, axes=("rails_y",),
                                       gaps=[(2.0, 0.5)], restart_after_gaps=True))
    (fr,) = replay_files([full], [None])
    assert not [n for n in fr.runs[0].plan.notes if "not in the recording" in n]
    res = ScanResult(full)
    records = list(iter_records(full, result=res))
    (_, _, cfg_json), = res.attachments

    def holed(name: str, lost: range) -> str:
        """The recording without the input frames numbered ``lost`` (1-based, in order)."""
        path = tmp_path / name
        inputs = 0
        with SessionWriter(path, sorted({r.topic for r in records}), None, cfg_json,
                           flush_s=0, fsync=False) as w:
            for rec in records:
                if rec.topic == "sim/motion/setpoint":
                    inputs += 1
                    if inputs in lost:
                        continue
                w.write_raw(rec.topic, rec.log_ns, rec.publish_ns, rec.sequence, rec.data)
        (fr,) = replay_files([path], [None])
        return " ".join(fr.runs[0].plan.notes)

    # numbers 399-428 of the second run (the first run's frames of those numbers are older):
    notes = holed("second.mcap", range(2400, 2430))
    assert "30 sequence numbers between the first and the last input frame the service used " \
           "are not in the recording" in notes, notes
    assert "30 input frames the service used are not in the recording" in notes, notes
    # number 1500 of the first run, which the second run reaches later: its frame is not the
    # one, and the first run's later numbers stay found
    notes = holed("first.mcap", range(1501, 1502))
    assert "1 input frames the service used are not in the recording" in notes, notes


def test_a_frame_the_service_never_received_is_found_and_the_replay_is_bit_for_bit(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two input frames the recorder holds never reached the service (its link dropped them;
    the service counts them superseded): the outputs cannot say which, the replay finds them by
    where it departs from the recorded outputs, leaves them out and is the service again, bit
    for bit -- and so does another config's replay, in one process or in workers.  Limited to
    one frame, the search finds one and says why the replay still departs."""
    from motcomp.replay import offline
    from motcomp.replay.engine import run_ticks
    from motcomp.replay.offline import config_for, plan_for, read_for_replay, replay_files
    from motcomp.replay.synth import SynthOptions, synthesize

    path = tmp_path / "dropped.mcap"
    synthesize(path, CFG, SynthOptions(duration_s=6.0, seed=5, axes=("rails_y", "hex_z"),
                                       service_misses=[2.0005, 4.2115]))  # seq 2001, 4212
    other = tmp_path / "other.toml"  # the same rate, another tuning
    other.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[axes.rails_y]\n'
                     "bypass = true\n")
    s = read_for_replay(path)
    cfg, _, _ = config_for(s, None)
    axes = resolve_axes(cfg)
    assert s.outputs is not None and s.inputs is not None
    # without the search the replay takes the two frames and departs from the recording
    bare = plan_for(s, cfg, axes, absent=False)
    assert bare.superseded == 2
    rows = np.flatnonzero(bare.output >= 0)
    rec = s.outputs.pos[bare.output[rows]]
    assert not np.array_equal(run_ticks(bare, s.inputs, cfg).u[rows], rec)
    # with it: the two frames named, left out, and the replay equal to the recording
    (fr,) = replay_files([path], [None, other])
    run, second = fr.runs
    wanted = tuple(int(np.searchsorted(s.inputs.seq, k)) for k in (2001, 4212))
    assert run.plan.absent == wanted, (run.plan.absent, run.plan.notes)
    notes = " ".join(run.plan.notes)
    assert "2 input frames the recorder holds never reached the service (seq 2001, 4212; " \
           "its status counted 2 superseded)" in notes, notes
    assert "departs" not in notes, notes
    assert np.array_equal(run.result.u[rows], rec)
    assert run.recorded_config and run.report.axes[0].max_diff == 0.0
    assert not second.recorded_config and second.plan.absent == wanted
    (par,) = replay_files([path], [None, other], jobs=2)
    for a, b in zip(fr.runs, par.runs, strict=True):
        assert a.plan.absent == b.plan.absent and a.plan.notes == b.plan.notes
        assert np.array_equal(a.result.u, b.result.u, equal_nan=True)
    # at most one frame: found, and the departure the other leaves is named with the reason
    monkeypatch.setattr(offline, "ABSENT_MAX", 1)
    (one,) = replay_files([path], [None])
    notes = " ".join(one.runs[0].plan.notes)
    assert len(one.runs[0].plan.absent) == 1 and "1 input frame the recorder holds" in notes
    assert "which the search for input frames the service never received did not explain " \
           "(it stops at 1 frame; its status counted 2 superseded)" in notes, notes


def test_a_replay_that_departs_from_the_recording_names_where(tmp_path: Path) -> None:
    """A recorded output the replay does not reproduce, where the service counted no frame
    superseded: the replay says from which output on, and by how much."""
    from motcomp.replay.offline import config_for, read_for_replay, replay_offline
    from motcomp.replay.synth import SynthOptions, synthesize

    path = tmp_path / "clean.mcap"
    synthesize(path, CFG, SynthOptions(duration_s=4.0, seed=2, axes=("rails_y",)))
    s = read_for_replay(path)
    (clean,) = replay_offline(s, [config_for(s, None)])
    assert not [n for n in clean.plan.notes if "departs" in n], clean.plan.notes
    assert s.outputs is not None
    k = 2500
    s.outputs.pos[k, AXES.index("rails_y")] += 1e-9  # what the replay cannot have computed
    (run,) = replay_offline(s, [config_for(s, None)])
    (note,) = [n for n in run.plan.notes if "departs" in n]
    assert (f"departs from the recorded outputs from output seq {int(s.outputs.seq[k])} "
            in note and "by up to 1e-09 in axis units" in note
            and "the service's status counted no input frame superseded" in note), note
