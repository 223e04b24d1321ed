"""The simulated platform and the motion source stay on wall time when their loops stall.

A real platform keeps moving while the simulator's thread is stalled, and a vehicle model does
not slow down when its publisher does: a stall must not stretch either in time (it made the
demo's platform look slower than its true dynamics under a few percent of missed ticks).
"""

from __future__ import annotations

import math
import threading
import time

import msgpack
import numpy as np
import pytest

from motcomp.core.axes import AXES
from motcomp.core.models import P1D
from motcomp.io.wire import encode_output
from motcomp.io.zenoh_io import ZenohEndpoints, free_tcp_port, loopback, open_session
from motcomp.sim import source as source_mod
from motcomp.sim.hil import AGE_WINDOW_S, HilConfig, HilPlatform
from motcomp.sim.platform import Accelerometer

RATE = 1000.0
RAILS = P1D(K=1.0, Td=0.0175, Tp1=0.1857683128)


def p1d_step(t: float, amp: float, m: P1D = RAILS) -> float:
    """Closed form: response of ``K e^{-Td s}/(1 + Tp1 s)`` to a step of ``amp`` at t = 0."""
    return 0.0 if t <= m.Td else amp * m.K * (1.0 - math.exp(-(t - m.Td) / m.Tp1))


def platform() -> HilPlatform:
    n = len(AXES)
    return HilPlatform(HilConfig(models=[RAILS] * n, p_min=np.full(n, -1.0),
                                 p_max=np.full(n, 1.0), v_max=None, rate_hz=RATE,
                                 accelerometer=Accelerometer()))


def frame(seq: int, value: float) -> bytes:
    return encode_output(seq, seq / RATE, seq, [value] * len(AXES), [])


@pytest.mark.parametrize("stalls", [[], [(40, 3), (200, 17), (201, 1), (350, 60)]])
def test_platform_follows_the_closed_form_step_response_through_stalls(
        stalls: list[tuple[int, int]]) -> None:
    """A step setpoint at t = 0; ticks at the deadlines the loop met, with ``skipped`` periods
    before some of them.  The position after each tick must be the continuous P1D step response
    at that tick's wall time, stalls or not."""
    plat = platform()
    skipped = dict(stalls)
    plat.take_frame(frame(0, 0.1))
    periods = 0
    checked = 0
    for tick in range(500):
        plat.catch_up(skipped.get(tick, 0))
        plat.step()
        periods += skipped.get(tick, 0) + 1
        y = plat.sim.position[0]
        assert y == pytest.approx(p1d_step(periods / RATE, 0.1), abs=1e-12)
        checked += 1
    assert checked == 500 and plat.caught_up == sum(skipped.values())


def test_the_setpoint_held_during_a_stall_is_the_one_before_it() -> None:
    """Stall of 30 periods, then a new frame: the stall is simulated on the old setpoint (0.1
    from t = 0), the new one (0.3) applies from the tick that ends the stall on."""
    stalled, smooth = platform(), platform()
    for p in (stalled, smooth):
        p.take_frame(frame(0, 0.1))
        p.step()
    for _ in range(30):  # what the simulator should have done during the stall
        smooth.step()
    stalled.catch_up(30)
    for p in (stalled, smooth):
        p.take_frame(frame(1, 0.3))
        p.step()
    np.testing.assert_array_equal(stalled.sim.position, smooth.sim.position)
    # and by superposition: step of 0.1 at 0, of 0.2 more at 31 periods
    t = 32 / RATE
    assert stalled.sim.position[0] == pytest.approx(
        p1d_step(t, 0.1) + p1d_step(t - 31 / RATE, 0.2), abs=1e-12)


def test_frames_received_during_a_stall_apply_at_their_own_times() -> None:
    """The service keeps sending while the simulator stalls: after the stall, each skipped
    period is simulated with the frames stamped before its start, so the platform ends where
    it would have been without the stall (a ramp of setpoints, one per period, each stamped
    half a period before the period that takes it)."""
    stalled, smooth = platform(), platform()
    ramp = [0.001 * k for k in range(200)]

    def ramp_frame(k: int) -> bytes:
        return encode_output(k, (k - 0.5) / RATE, k, [ramp[k]] * len(AXES), [])

    for k in range(200):  # smooth: frame k arrives just before period k
        smooth.take_frame(ramp_frame(k))
        smooth.step()
    for k in range(100):  # stalled: the same up to period 99 ...
        stalled.take_frame(ramp_frame(k))
        stalled.step()
    for k in range(100, 200):  # ... then frames 100-199 all arrive while the loop is stalled
        stalled.take_frame(ramp_frame(k))
    stalled.catch_up(99, tick_t=199 / RATE)  # the tick of period 199 ends the stall
    stalled.step()
    np.testing.assert_array_equal(stalled.sim.position, smooth.sim.position)
    assert stalled.caught_up == 99
    # without a tick time (CAN frames carry none) the stall is simulated on the setpoint held
    # before it, and the frames queued meanwhile apply from the tick that ends it
    held = platform()
    for k in range(100):
        held.take_frame(ramp_frame(k))
        held.step()
    for k in range(100, 200):
        held.take_frame(ramp_frame(k))
    held.catch_up(99)
    assert held.setpoint[0] == ramp[99]
    held.step()
    assert held.setpoint[0] == ramp[199]


def test_bad_frames_are_counted_and_change_nothing() -> None:
    plat = platform()
    plat.take_frame(frame(0, 0.1))
    plat.take_frame(b"\xc1 not msgpack")
    plat.take_frame(msgpack.packb({"seq": 1, "t": "late", "src_seq": 1, "pos": {}, "flags": []}))
    plat.step()
    assert plat.bad == 2 and plat.frames == 3 and plat.setpoint[0] == 0.1


def test_catch_up_is_bounded() -> None:
    plat = platform()
    plat.catch_up(10**9)
    assert plat.caught_up == round(HilPlatform.max_catch_up_s * RATE)


def test_source_drops_the_samples_of_a_stall_instead_of_stretching_the_motion(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A ramp (value = its own sample time) published with a 30 ms stall in the middle: every
    frame's value must still match its timestamp, seq counts frames sent, and the samples due
    during the stall are never sent."""
    n = 1500
    traj = source_mod.Trajectory(RATE, {"rails_x": np.arange(n) / RATE})
    encode = source_mod.encode_input
    stalled: list[int] = []

    def slow_encode(seq: int, t: float, pos: dict[str, float]) -> bytes:
        if seq == 700 and not stalled:
            stalled.append(seq)
            time.sleep(0.03)
        return encode(seq, t, pos)

    monkeypatch.setattr(source_mod, "encode_input", slow_encode)
    port = free_tcp_port()
    import zenoh

    got: list[tuple[int, float, float]] = []
    with open_session(ZenohEndpoints(listen=(loopback(port),))) as session:
        sub = session.declare_subscriber("sim/motion/setpoint", zenoh.handlers.FifoChannel(4096))
        pub = threading.Thread(target=source_mod.publish, args=(
            traj, ZenohEndpoints(connect=(loopback(port),))), kwargs={"lead_in_s": 1.0})
        pub.start()
        t_end = time.monotonic() + 20.0
        while (pub.is_alive() or got == []) and time.monotonic() < t_end:
            while (s := sub.try_recv()) is not None:
                f = msgpack.unpackb(s.payload.to_bytes())
                got.append((f["seq"], f["t"], f["pos"]["rails_x"]))
            time.sleep(0.01)
        pub.join(timeout=5.0)
        while (s := sub.try_recv()) is not None:
            f = msgpack.unpackb(s.payload.to_bytes())
            got.append((f["seq"], f["t"], f["pos"]["rails_x"]))
        sub.undeclare()
    assert stalled and len(got) > 500  # (a busy host's own stalls drop samples too)
    seq = np.array([g[0] for g in got])
    t = np.array([g[1] for g in got])
    value = np.array([g[2] for g in got])
    assert np.all(np.diff(seq) > 0)  # (the data path drops frames under congestion)
    offset = t - value  # constant if the motion is on wall time
    assert np.ptp(offset) < 1e-5
    dropped = np.round(value * RATE).astype(int) - seq  # samples never sent, so far
    assert np.all(np.diff(dropped) >= 0)
    assert dropped[-1] - dropped[0] >= 25  # the stall's (and any the machine's own stalls cost)


def test_the_setpoints_age_when_applied_is_measured() -> None:
    """Frames stamped 0.3 ms before the period they are applied at (and one during a stall,
    applied at its own time): the age is what the simulator adds to its truth's delay as
    the service's stamps see it (identify measures the sum)."""
    plat = platform()
    assert math.isnan(plat.setpoint_age_s)
    for k in range(10):
        plat.take_frame(encode_output(k, k / RATE - 3e-4, k, [0.0] * len(AXES), []))
        plat.step(k / RATE)
    assert plat.setpoint_age_s == pytest.approx(3e-4, abs=1e-12)
    plat.take_frame(encode_output(10, 10 / RATE - 3e-4, 10, [0.0] * len(AXES), []))
    plat.catch_up(1, 11 / RATE)  # the stall's period starts at 10 / RATE: the frame is 0.3 ms old
    assert plat.setpoint_age_mean_s == pytest.approx(3e-4, abs=1e-12)
    assert plat.age_n == 11
    # the median is what a fit sees: a few late frames move only the mean
    assert plat.setpoint_age_s == pytest.approx(3e-4, abs=1e-12)
    for k in range(12, 16):
        plat.take_frame(encode_output(k, k / RATE - 0.04, k, [0.0] * len(AXES), []))
        plat.step(k / RATE)
    assert plat.setpoint_age_mean_s == pytest.approx((11 * 3e-4 + 4 * 0.04) / 15, abs=1e-12)
    assert plat.setpoint_age_s == pytest.approx(3e-4, abs=1e-12)
    # both are over the frames applied in the last AGE_WINDOW_S, up to the newest: a host that
    # got slower shows in the figures within that time, whatever came before
    k0 = 16
    last = k0 + round(AGE_WINDOW_S * RATE) + 5
    for k in range(k0, last + 1):
        plat.take_frame(encode_output(k, k / RATE - 2e-3, k, [0.0] * len(AXES), []))
        plat.step(k / RATE)
    assert plat.age_n == 15 + last + 1 - k0
    assert plat.setpoint_age_s == pytest.approx(2e-3, abs=1e-12)
    assert plat.setpoint_age_mean_s == pytest.approx(2e-3, abs=1e-12)
