"""The service's tick, driven directly with a given time (in-memory adapters, real compensator).

Checks the data-path rules: bad frames never reach the output nor stop the loop; stale input
holds then ramps to neutral within the limits; input resuming rejoins without a jump; start-up
from neutral; parking; catch-up after a stall.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from motcomp.config import PARK_SETTLE_S, parse_config, read_toml, resolve_axes
from motcomp.core.axes import AXES
from motcomp.core.tick import is_parked, park
from motcomp.io.memory import MemorySink, MemorySource
from motcomp.io.wire import decode_output, encode_input
from motcomp.io.zenoh_io import ZenohEndpoints
from motcomp.runtime.service import Service
from tests.test_saturation import check_sequence

ROOT = Path(__file__).resolve().parent.parent
MS = 1_000_000  # ns


def make_service(plain_rails: bool = False, **loop: Any
                 ) -> tuple[Service, MemorySource, MemorySink]:
    """The example config's service on memory ports; ``plain_rails``: without the rails'
    prefilter (the PID alone), for the shaper's rules to be read off the command exactly."""
    data = read_toml(ROOT / "config" / "motcomp.toml")
    data["loop"].update(loop)
    if plain_rails:
        for a in ("rails_x", "rails_y"):
            data["axes"][a].pop("prediction")
    svc = Service(parse_config(data), ZenohEndpoints())
    src, sink = MemorySource(burst=True), MemorySink()
    svc.attach(src, [sink])
    return svc, src, sink


def outputs(sink: MemorySink) -> list[dict[str, Any]]:
    return [decode_output(p) for p in sink.payloads]


def column(frames: list[dict[str, Any]], axis: str) -> np.ndarray:
    return np.array([f["pos"][axis] for f in frames])


def slalom_frame(k: int) -> bytes:
    t = k / 1000.0
    # within the rails' limits once compensated (peak reference acceleration 2.2 m/s^2)
    return encode_input(k, t, {"rails_y": 0.25 * math.sin(2 * math.pi * 0.3 * t) ** 3,
                               "rails_x": 0.1 * math.sin(2 * math.pi * 0.2 * t) ** 3})


BAD_FRAMES: dict[str, bytes] = {
    "decode": b"\xc1 not msgpack",
    "decode ": msgpack.packb([1, 2, 3]),
    "schema": msgpack.packb({"seq": 10**9, "pos": {"rails_y": 0.0}, "extra": 1}),
    "schema ": msgpack.packb({"seq": 10**9}),
    "schema  ": msgpack.packb({"seq": 10**9, "pos": {}}),
    "type": msgpack.packb({"seq": "7", "pos": {"rails_y": 0.0}}),
    "type ": msgpack.packb({"seq": True, "pos": {"rails_y": 0.0}}),
    "type  ": msgpack.packb({"seq": 10**9, "t": "now", "pos": {"rails_y": 0.0}}),
    "type   ": msgpack.packb({"seq": 10**9, "pos": {"rails_y": "0.1"}}),
    "type    ": msgpack.packb({"seq": 10**9, "pos": [0.1]}),
    "axis": msgpack.packb({"seq": 10**9, "pos": {"rails_z": 0.0}}),
    "nonfinite": msgpack.packb({"seq": 10**9, "pos": {"rails_y": float("nan")}}),
    "nonfinite ": msgpack.packb({"seq": 10**9, "pos": {"hex_roll": float("inf")}}),
    "range": msgpack.packb({"seq": 10**9, "pos": {"rails_y": 40.0}}),
    "oversize": msgpack.packb({"seq": 10**9, "pos": {"rails_y": 0.0}, "pad": "x" * 5000}),
    "decode  ": b"\x81\xa3pos" + b"\x91" * 2000 + b"\x00",  # nested beyond msgpack's stack
}


def test_valid_frames_reach_the_output() -> None:
    svc, src, sink = make_service()
    for k in range(3000):
        src.push(slalom_frame(k))
        svc.tick(k * MS)
    out = outputs(sink)
    assert [f["seq"] for f in out] == list(range(3000))
    assert out[-1]["src_seq"] == 2999
    assert set(out[-1]["pos"]) == set(AXES)
    assert "bypass:hex_x" in out[-1]["flags"] and "bypass:rails_y" not in out[-1]["flags"]
    assert svc.state.accepted == 3000 and svc.state.rejected == 0
    # after the start-up blend the rails are compensated: ahead of the plain reference
    y = column(out, "rails_y")
    assert np.all(np.isfinite(y))
    for axis in AXES:
        if axis.startswith("hex"):
            assert np.all(column(out, axis) == 0.0)  # not commanded: held at neutral


def test_bad_frames_are_rejected_counted_and_change_nothing() -> None:
    """A bad frame is exactly equivalent to no frame: the run with every kind of bad frame
    interleaved gives outputs bit-identical to the run that received nothing at those ticks."""
    clean, src_c, sink_c = make_service()
    dirty, src_d, sink_d = make_service()
    bad = list(BAD_FRAMES.values())
    n_bad = 0
    for k in range(2000):
        if k % 7 == 3:
            src_d.push(bad[n_bad % len(bad)])
            n_bad += 1
        else:
            src_c.push(slalom_frame(k))
            src_d.push(slalom_frame(k))
        clean.tick(k * MS)
        dirty.tick(k * MS)
    got, ref = outputs(sink_d), outputs(sink_c)
    assert [f["pos"] for f in got] == [f["pos"] for f in ref]
    assert [f["src_seq"] for f in got] == [f["src_seq"] for f in ref]
    counts = dirty.state.rejected_by_reason
    for reason in {r.strip() for r in BAD_FRAMES}:
        assert counts[reason] > 0, reason
    assert dirty.state.rejected == n_bad and clean.state.rejected == 0
    assert dirty.state.received == clean.state.received + n_bad
    assert all(math.isfinite(v) for f in got for v in f["pos"].values())


def test_duplicate_and_old_seq_rejected_then_restart_after_stale() -> None:
    svc, src, _ = make_service()
    for k, seq in enumerate([5, 6, 6, 4, 7]):
        src.push(encode_input(seq, None, {"rails_y": 0.01}))  # type: ignore[arg-type]
        svc.tick(k * MS)
    counts = svc.state.rejected_by_reason
    assert counts["duplicate"] == 1 and counts["old"] == 1
    # 200 ms of silence makes the input stale; a restarted sender (seq 0) is accepted
    svc.tick(200 * MS)
    src.push(encode_input(0, 0.2, {"rails_y": 0.02}))
    svc.tick(201 * MS)
    assert svc.state.last_seq == 0 and svc.state.src_seq == 0


def test_frames_not_taken_count_as_superseded() -> None:
    """Two frames in one tick: the loop takes the newer; the gap in seq is counted, a restarted
    sender (seq going back after a stale spell) is not."""
    svc, src, _ = make_service()
    seqs = [0, 1, 2, 3, 5, 6, 9, 10]  # 4, 7 and 8 arrive together with their successor
    for k, seq in enumerate(seqs):
        svc.tick(k * MS)
        src.push(encode_input(seq, k / 1000, {"rails_y": 0.01}))
    svc.tick(len(seqs) * MS)
    assert svc.status()["frames"]["superseded"] == 3
    svc.tick(300 * MS)  # stale
    src.push(encode_input(0, 0.3, {"rails_y": 0.02}))
    svc.tick(301 * MS)
    assert svc.state.last_seq == 0 and svc.status()["frames"]["superseded"] == 3


def test_subset_frames_hold_the_other_axes() -> None:
    svc, src, sink = make_service()
    for k in range(1500):
        src.push(encode_input(k, k / 1000, {"rails_x": 0.05} if k < 1000 else {"rails_y": 0.05}))
        svc.tick(k * MS)
    last = outputs(sink)[-1]["pos"]
    assert last["rails_x"] == pytest.approx(0.05, abs=1e-4)  # still held


def _limits(svc: Service, axis: str) -> Any:
    from motcomp.core.saturation import AxisLimits

    i = AXES.index(axis)
    lim = svc.axes.limits
    return AxisLimits(lim.p_min[i:i + 1], lim.p_max[i:i + 1], lim.v_max[i:i + 1],
                      lim.a_max[i:i + 1])


def test_stale_input_holds_then_ramps_to_neutral_then_rejoins() -> None:
    svc, src, sink = make_service(True, stale_after_s=0.05, hold_s=0.5, rejoin_s=0.5)
    k = 0
    for k in range(2000):  # 2 s at 0.4 m (after the start-up blend)
        src.push(encode_input(k, k / 1000, {"rails_y": 0.4}))
        svc.tick(k * MS)
    stop = k
    for k in range(stop + 1, stop + 5000):  # 5 s without input
        svc.tick(k * MS)
    out = outputs(sink)
    y = column(out, "rails_y")
    flags = [f["flags"] for f in out]
    stale_from = next(i for i in range(stop, len(out)) if "stale" in flags[i])
    assert 45 <= stale_from - stop <= 55  # stale_after_s = 50 ms
    # held for 0.5 s (the compensated output settles on the held reference) ...
    assert np.all(np.abs(y[stale_from:stale_from + 450] - 0.4) < 2e-3)
    # ... then ramped to neutral within the limits
    assert abs(y[-1]) < 1e-6
    check_sequence(y, 0.0, _limits(svc, "rails_y"), 1e-3)
    # input resumes at -0.3: rejoin, still within the limits, then live
    t_resume = len(out)
    for k in range(t_resume, t_resume + 3000):
        src.push(encode_input(k, k / 1000, {"rails_y": -0.3}))
        svc.tick(k * MS)
    out = outputs(sink)
    y = column(out, "rails_y")
    check_sequence(y, 0.0, _limits(svc, "rails_y"), 1e-3)
    assert "rejoin" in out[t_resume + 10]["flags"]
    assert y[-1] == pytest.approx(-0.3, abs=1e-6)
    assert svc.state.shaper.stale_episodes == 1 and svc.state.shaper.stale_total_s > 4.0


def test_startup_blends_from_neutral() -> None:
    svc, src, sink = make_service(True, startup_s=1.0)
    for k in range(3000):
        src.push(encode_input(k, k / 1000, {"rails_y": 0.5}))
        svc.tick(k * MS)
    y = column(outputs(sink), "rails_y")
    assert y[0] == 0.0
    check_sequence(y, 0.0, _limits(svc, "rails_y"), 1e-3)
    assert y[-1] == pytest.approx(0.5, abs=1e-6)


def test_the_rails_chain_settles_a_step_as_designed() -> None:
    """The shipped rails (PID + prefilter in series, designed over 0.03-2 Hz): a held 0.5 m
    reached by the start-up blend is on the command within 1.5 mm (0.3 %) from 0.5 s after the
    blend's end, and within 10 um after 18 s (the prefilter's memory: the figures the config
    states), within the limits all along."""
    svc, src, sink = make_service(startup_s=1.0)
    for k in range(18000):
        src.push(encode_input(k, k / 1000, {"rails_y": 0.5}))
        svc.tick(k * MS)
    y = column(outputs(sink), "rails_y")
    check_sequence(y, 0.0, _limits(svc, "rails_y"), 1e-3)
    assert np.max(np.abs(y[1500:] - 0.5)) < 1.5e-3
    assert abs(y[-1] - 0.5) < 1e-5


@pytest.mark.parametrize("how", ["park", "stale"])
def test_a_ramp_to_neutral_from_beyond_the_limits_starts_at_once(how: str) -> None:
    """Input held beyond rails_y's limit (within the accepted reach, which the limiter holds
    the command from): the ramp to neutral -- SIGTERM's parking, or an input loss after its
    hold -- starts from the limit, not from the reference beyond it.  It takes the minimum-jerk
    ramp from the limit at the configured peak speed, 1.875 * 2.6 m / (0.25 * 2 m/s) = 9.75 s
    (from 3.85 m it took 14.4 s, the first 4.6 s with the platform held at its end: within
    0.6 s of park_timeout_s), the command moving home from the first tick and within the
    limits all along."""
    svc, src, sink = make_service(hold_s=0.5)
    p_max = svc.axes.limits.p_max[AXES.index("rails_y")]
    ramp_s = 1.875 * p_max / (svc.cfg.loop.ramp_speed_fraction
                           * svc.axes.limits.v_max[AXES.index("rails_y")])
    assert ramp_s == pytest.approx(9.75)
    k = 0
    for k in range(6000):
        src.push(encode_input(k, k / 1000, {"rails_y": 3.85}))
        svc.tick(k * MS)
    k0 = len(sink.payloads)
    start = k + 1
    if how == "park":
        park(svc.state, svc.params, start * MS)
    home = start + (0 if how == "park" else 500 + 50)  # stale: 50 ms unseen, then held 0.5 s
    k = start
    while not is_parked(svc.state) and k < start + 20000:
        if how == "stale" and abs(decode_output(sink.payloads[-1])["pos"]["rails_y"]) < 1e-9:
            break
        svc.tick(k * MS)
        k += 1
    y = column(outputs(sink), "rails_y")
    check_sequence(y, 0.0, _limits(svc, "rails_y"), 1e-3)
    assert y[k0 - 1] == pytest.approx(p_max)  # held at the limit before
    assert abs(y[-1]) < 1e-6
    took_s = (k - home) / 1000
    assert ramp_s - 0.05 <= took_s <= ramp_s + 0.3, took_s
    # home from the first ticks, along the minimum-jerk ramp from the limit (24 mm along after
    # 1 s; from 3.85 m the command stayed at the limit for 4.6 s)
    tau = 1.0 / ramp_s
    along = p_max * (10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5)
    assert y[k0 + home - start + 1000] == pytest.approx(p_max - along, abs=3e-3)


@pytest.mark.parametrize(("loop", "short"), [
    ({}, False), ({"park_timeout_s": 10.3}, False), ({"park_timeout_s": 10.2}, True),
    ({"ramp_speed_fraction": 0.15}, True), ({"ramp_speed_fraction": 0.15, "park_timeout_s": 16.8},
                                            False)])
def test_a_park_timeout_shorter_than_a_ramp_from_the_limits_is_warned_of(loop: dict[str, float],
                                                                         short: bool) -> None:
    """``loop.park_timeout_s`` should leave each driven axis room to ramp to neutral from its
    farther position limit, plus PARK_SETTLE_S: a timeout cuts parking short, the service
    stopping mid-ramp (the example's rails_y, 2.6 m: 9.75 s at a quarter of 2 m/s, the test
    above; 16.25 s at 0.15 of it).  The config loads with a warning (which the service logs at
    start and on a reload, and ``motcomp config check`` prints) naming the axis, the keys and
    the least timeout that would do."""
    data = read_toml(ROOT / "config" / "motcomp.toml")
    data.setdefault("loop", {}).update(loop)
    cfg = parse_config(data)
    axes = resolve_axes(cfg)
    i = AXES.index("rails_y")
    ramp_s = 1.875 * 2.6 / (cfg.loop.ramp_speed_fraction * axes.limits.v_max[i])
    assert axes.limits.p_max[i] == 2.6 and axes.limits.v_max[i] == 2.0
    assert short == (ramp_s + PARK_SETTLE_S > cfg.loop.park_timeout_s)
    said = [w for w in axes.warnings if w.startswith("rails_y: loop.park_timeout_s")]
    assert len(said) == short, axes.warnings
    if short:
        assert f"({ramp_s:.2f} s at loop.ramp_speed_fraction" in said[0]
        assert f">= {math.ceil((ramp_s + PARK_SETTLE_S) * 10) / 10:g} or a larger" in said[0]


def test_parking_reaches_neutral_within_the_limits() -> None:
    svc, src, sink = make_service()
    for k in range(3000):
        src.push(slalom_frame(k))
        svc.tick(k * MS)
    park(svc.state, svc.params, 3000 * MS)
    k = 3000
    while not is_parked(svc.state) and k < 20000:
        src.push(slalom_frame(k))  # input is ignored while parking
        svc.tick(k * MS)
        k += 1
    assert is_parked(svc.state)
    out = outputs(sink)
    for axis in ("rails_x", "rails_y"):
        y = column(out, axis)
        assert abs(y[-1]) < 1e-6
        check_sequence(y, 0.0, _limits(svc, axis), 1e-3)
    assert "parking" in out[-1]["flags"]


def test_catch_up_keeps_the_compensator_on_the_time_grid() -> None:
    """A stall of 4 periods, caught up, leaves the state exactly where ticking every period
    would have (input arriving every 5 ms, taken by the tick after the stall)."""
    a, src_a, sink_a = make_service()
    b, src_b, sink_b = make_service()
    for k in range(600):
        frame = slalom_frame(k) if k % 5 == 0 else None
        if frame:
            src_a.push(frame)
        a.tick(k * MS)
        if k % 5 == 0:
            if frame:
                src_b.push(frame)
            b.tick(k * MS, skipped=4 if k else 0)
    for axis in AXES:
        ya = column(outputs(sink_a), axis)[::5]
        yb = column(outputs(sink_b), axis)
        np.testing.assert_array_equal(yb, ya)
    assert b.state.accepted == a.state.accepted == 120


def test_tick_times_its_transport_calls_apart() -> None:
    """``io_ns`` is the time the tick spent in the adapters' calls: with a sink that takes
    2 ms to send, the tick's io is at least that, and the compute part stays small."""
    import time

    svc, src, _ = make_service()

    class SlowSink(MemorySink):
        def put(self, payload: bytes) -> None:
            time.sleep(0.002)
            super().put(payload)

    slow = SlowSink()
    svc.attach(src, [slow])
    src.push(slalom_frame(0))
    t0 = time.perf_counter_ns()
    svc.tick(0)
    whole = time.perf_counter_ns() - t0
    assert 2 * MS <= svc.io_ns <= whole
    assert len(slow.payloads) == 1
    svc.attach(src, [])
    t0 = time.perf_counter_ns()
    svc.tick(MS)
    whole = time.perf_counter_ns() - t0
    assert 0 <= svc.io_ns <= whole  # no sink: only the input take


def test_mode_switches_are_logged_with_their_reason(caplog: pytest.LogCaptureFixture) -> None:
    """The main thread's ModeLog says each switch of the loop's mode (the loop never logs)."""
    from motcomp.runtime.service import ModeLog

    svc, src, _ = make_service(stale_after_s=0.05, hold_s=0.1, startup_s=0.2, rejoin_s=0.2)
    seen = ModeLog(svc.state)
    k = 0

    def run(n: int, frames: bool) -> None:
        nonlocal k
        for _ in range(n):
            if frames:
                src.push(encode_input(k, k / 1000, {"rails_y": 0.01}))  # a 0.2 s blend
            svc.tick(k * MS)
            k += 1
            if k % 20 == 0:  # the main thread's poll
                seen.update(svc.state, svc.params)

    with caplog.at_level("INFO", logger="motcomp.service"):
        run(100, False)  # no sender yet: said, not warned
        run(100, True)   # start-up blend
        run(400, True)   # live
        run(300, False)  # stale: hold, ramp
        run(600, True)   # rejoin (0.39 s: the 1 cm gap within the rails' jerk budget), live
        from motcomp.core.tick import park
        park(svc.state, svc.params, k * MS)
        run(40, False)
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert [r.levelname for r in caplog.records if "waiting for input" in r.getMessage()] == [
        "INFO"]
    assert "input started: blending to the live input over at least 0.20 s" in text
    assert "input stale: no valid frame for 0.050 s" in text and "holding 0.10 s" in text
    assert "input resumed: blending to the live input over at least 0.20 s" in text
    assert text.count("running on live input") == 2  # after the start-up blend, after the rejoin
    assert "stop requested: parking" in text
