"""The limits across missed ticks (docs/WIRE.md, "The limits across missed ticks"): between two
consecutive outputs, however many periods apart, the command's velocity is at most ``vel_max``
and its divided second difference at most ``acc_max``, because every deadline missed is
computed (caught up) on the grid with the samples that had landed by it.  The tick with stalls
of 10-200 ms injected, as a property; and the real service stopped with SIGSTOP for as long."""

from __future__ import annotations

import math
import os
import signal
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from motcomp.config import load_config, new_tick, resolve_axes
from motcomp.core.axes import AXES, AXIS_INDEX
from motcomp.core.saturation import AxisLimits
from motcomp.core.tick import MAX_CATCH_UP, step
from motcomp.io.wire import encode_input
from motcomp.io.zenoh_io import ZenohEndpoints, free_tcp_port, loopback, open_session
from motcomp.resources import config_file
from tests.test_service_process import process, wait_status, write_config

ROOT = Path(__file__).resolve().parent.parent
MS = 1_000_000
Y = AXIS_INDEX["rails_y"]
X = AXIS_INDEX["rails_x"]
REL, ABS = 1e-9, 1e-9


def assert_limits_across(t_s: np.ndarray, u: np.ndarray, lim: AxisLimits, axes: list[int]
                         ) -> tuple[float, float]:
    """Consecutive outputs ``(t_s[k], u[k])``, any spacing: positions within the range, the
    velocity between two within ``v_max``, the divided second difference of three within
    ``a_max`` (to rounding).  Returns the largest of each ratio to its limit."""
    worst_v = worst_a = 0.0
    for i in axes:
        x = u[:, i]
        assert np.all(x <= lim.p_max[i] + 1e-12) and np.all(x >= lim.p_min[i] - 1e-12)
        dt = np.diff(t_s)
        v = np.diff(x) / dt
        a = 2.0 * np.diff(v) / (t_s[2:] - t_s[:-2])
        rv, ra = np.max(np.abs(v)) / lim.v_max[i], np.max(np.abs(a)) / lim.a_max[i]
        scale = max(1.0, abs(lim.p_max[i]))
        assert np.max(np.abs(v)) <= lim.v_max[i] * (1 + REL) + ABS * scale / dt.min(), rv
        assert np.max(np.abs(a)) <= lim.a_max[i] * (1 + REL) + ABS * scale / dt.min() ** 2, ra
        worst_v, worst_a = max(worst_v, rv), max(worst_a, ra)
    return worst_v, worst_a


def motion(t: float) -> dict[str, float]:
    """A slalom with lane changes on the rails, fast enough to keep the limiter busy (0.8 m at
    0.6 Hz, 1 m steps every 2 s)."""
    step_ = 1.0 if math.floor(t / 2.0) % 2 else -0.2
    return {"rails_y": 0.8 * math.sin(2 * math.pi * 0.6 * t),
            "rails_x": step_ + 0.3 * math.sin(2 * math.pi * 1.3 * t)}


@settings(max_examples=12, deadline=None)
@given(stalls=st.lists(st.tuples(st.integers(200, 5500), st.integers(10, 200)), min_size=1,
                       max_size=6),
       sender_late=st.integers(0, 30))
def test_outputs_across_stalls_keep_the_limits(stalls: list[tuple[int, int]],
                                               sender_late: int) -> None:
    """The example config, a 1 kHz sender (its frames landing ``sender_late`` ticks late now
    and then), stalls of 10-200 ms injected at random ticks: the outputs that were sent, read
    at their own instants, keep every limit."""
    cfg = load_config(config_file("motcomp.toml"))
    params, state = new_tick(cfg, resolve_axes(cfg))
    stalled: dict[int, int] = {}
    for at, length in stalls:
        stalled[at] = max(stalled.get(at, 0), length)
    t_out, u_out = [], []
    pending: list[bytes] = []
    k = 0
    end = 6000
    while k < end:
        if k in stalled:  # the loop sleeps through these deadlines; frames keep landing
            n = min(stalled[k], end - k - 1)
            for j in range(k, k + n):
                pending.append(encode_input(j, 1.7e9 + j * 1e-3, motion(j * 1e-3)))
            k += n
            skipped = n
        else:
            skipped = 0
        pending.append(encode_input(k, 1.7e9 + k * 1e-3, motion(k * 1e-3)))
        if sender_late and k % 97 == 0:  # this tick's frames land later
            held, pending = pending[-min(sender_late, len(pending)):], pending[:-sender_late]
            out = step(state, params, k * MS, pending, skipped)
            pending = held
        else:
            out = step(state, params, k * MS, pending, skipped)
            pending = []
        t_out.append(k * 1e-3)
        u_out.append(out.u)
        k += 1
    assert state.rejected == 0
    assert_limits_across(np.array(t_out), np.array(u_out), state.comp.limits, [X, Y])


def test_a_stall_is_computed_as_if_every_deadline_had_ticked() -> None:
    """The command after a 150 ms stall, its frames landing meanwhile, is the command of the
    loop that ticked every deadline: the stall costs the platform its setpoints, not the
    motion."""
    cfg = load_config(config_file("motcomp.toml"))
    params, a = new_tick(cfg)
    _, b = new_tick(cfg)
    frames = [encode_input(k, 1.7e9 + k * 1e-3, motion(k * 1e-3)) for k in range(3000)]
    for k in range(2000):
        out_a = step(a, params, k * MS, frames[k])
        out_b = step(b, params, k * MS, frames[k])
    for k in range(2000, 2150):
        out_a = step(a, params, k * MS, frames[k])
    out_a = step(a, params, 2150 * MS, frames[2150])
    out_b = step(b, params, 2150 * MS, frames[2000:2151], skipped=150)
    assert out_a.u == out_b.u
    assert MAX_CATCH_UP > 150


@pytest.mark.parametrize("stamped", [False, True])
def test_a_stall_of_the_loop_does_not_move_the_playback(stamped: bool) -> None:
    """A 1 kHz sender (with ``t`` or without) whose frames land 0.3-0.9 ms late, the loop
    stalled for 15 ms at a time: the frames that landed meanwhile are taken at the tick after
    it, and none of them may say it landed before it did, so the playback's offset (the
    smallest transit) and delay stay where they were.  A frame without ``t`` taken at a missed
    deadline used to read as having landed up to the whole stall early: the playback then ran
    up to 15 ms ahead of the samples for ten seconds."""
    cfg = load_config(config_file("motcomp.toml"))
    params, state = new_tick(cfg, resolve_axes(cfg))
    rng = np.random.default_rng(5)
    landed = [j + rng.uniform(0.3, 0.9) for j in range(9000)]  # ms
    j = 0
    offsets, delays = [], []
    k = 0
    while k < 9000:
        stall = 15 if k % 1500 == 700 and k > 3000 else 0
        k += stall
        frames = []
        while landed[j] <= k:
            frames.append(encode_input(j, 1.7e9 + j * 1e-3 if stamped else None,
                                       motion(j * 1e-3)))
            j += 1
        step(state, params, k * MS, frames, stall)
        pb = state.shaper.playback
        offsets.append(pb.offset)
        delays.append(pb.delay)
        k += 1
    assert state.rejected == 0
    settled = np.array(delays[2500:3000])  # before the first stall
    after = np.array(delays[3000:])
    assert np.all(after >= settled.min() - 1e-4), (settled.min(), after.min())
    assert np.all(np.array(offsets[3000:]) >= min(offsets[2500:3000]) - 1e-4)


def _sender(endpoint: str, stop: threading.Event) -> None:
    with open_session(ZenohEndpoints(connect=(endpoint,))) as session:
        pub = session.declare_publisher("sim/motion/setpoint")
        t0 = time.time()
        k = 0
        while not stop.is_set():
            due = t0 + k * 1e-3
            while (now := time.time()) < due:
                time.sleep(min(2e-4, due - now))
            pub.put(encode_input(k, due, motion(due - t0)))
            k += 1


@pytest.mark.slow
def test_the_service_stopped_by_sigstop_keeps_the_limits_across_its_outputs(tmp_path: Path
                                                                             ) -> None:
    """``motcomp run`` (the example config) driven at 1 kHz, stopped with SIGSTOP for 10-200 ms
    a few times: its outputs, received here, keep every limit across the gaps."""
    endpoint = loopback(free_tcp_port())
    cfg = write_config(tmp_path)
    outputs: list[tuple[float, list[float]]] = []
    stop = threading.Event()

    def on_out(sample: zenoh.Sample) -> None:
        frame = msgpack.unpackb(sample.payload.to_bytes())
        outputs.append((frame["t"], [frame["pos"][a] for a in AXES]))

    with process(["run", "--config", str(cfg), "-l", endpoint], tmp_path / "svc.log") as svc:
        with open_session(ZenohEndpoints(connect=(endpoint,))) as session:
            sub = session.declare_subscriber("platform/setpoint", on_out)
            wait_status(session)
            sender = threading.Thread(target=_sender, args=(endpoint, stop), daemon=True)
            sender.start()
            time.sleep(2.5)  # past the start-up blend
            rng = np.random.default_rng(7)
            for length_ms in (10, 60, 200, 120, 30):
                os.kill(svc.pid, signal.SIGSTOP)
                time.sleep(length_ms / 1000.0)
                os.kill(svc.pid, signal.SIGCONT)
                time.sleep(rng.uniform(0.4, 0.8))
            stop.set()
            sender.join(5.0)
            sub.undeclare()
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(30) == 0
    outputs.sort()
    t = np.array([o[0] for o in outputs])
    t = np.round((t - t[0]) / 1e-3) * 1e-3  # the tick instants (epoch floats resolve 0.24 us)
    u = np.array([o[1] for o in outputs])
    assert np.diff(t).max() > 0.15, "the longest stall does not show in the outputs"
    assert_limits_across(t, u, resolve_axes(load_config(cfg)).limits, [X, Y])


def test_degraded_windows_are_logged_once_a_minute_while_they_last() -> None:
    """A host that starves the loop for minutes: the first degraded 10 s window is logged at
    once, then one a minute, each saying how many went unlogged; the first window that holds
    again after unlogged ones says so, and the next degraded one is logged at once."""
    from motcomp.runtime.service import REPEAT_WARNING_S, DegradedLog

    assert REPEAT_WARNING_S == 60.0
    d = DegradedLog()
    said = [d.window(True, 10.0 * k) for k in range(1, 15)]  # 10-140 s, all degraded
    assert [(k, s) for k, s in enumerate(said, 1) if s] == [
        (1, ("warning", 0)), (7, ("warning", 5)), (13, ("warning", 5))]
    assert d.window(False, 150.0) == ("kept", 1)  # the window at 140 s went unlogged
    assert d.window(False, 160.0) is None
    assert d.window(True, 170.0) == ("warning", 0)  # a new episode: at once
    assert d.window(False, 180.0) is None  # nothing went unlogged
    assert d.window(True, 190.0) == ("warning", 0)
