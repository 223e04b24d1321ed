"""The host probe: a bare loop clock in a child process, and the rule that judges a host."""

from __future__ import annotations

import time

import pytest

from motcomp.runtime.probe import (
    MAX_MISSED_SHARE,
    MAX_STALL_MS,
    HostClock,
    HostProbe,
    loop_kept_from_cpu,
)
from tests.conftest import judge_realtime


def test_probe_accounts_for_every_deadline_of_its_run() -> None:
    t0 = time.monotonic()
    with HostProbe(1000.0, 50.0, 100.0) as probe:
        time.sleep(1.0)
    elapsed = time.monotonic() - t0
    r = probe.result
    assert r is not None
    # ticks run plus deadlines missed cover the probe's life (it started before t0 + its own
    # start-up and stopped within the exit): never more than the elapsed time allows
    assert 0.8 * 1000 <= r.ticks + r.missed <= elapsed * 1000 + 1
    assert 0.0 <= r.late_p99_us <= r.late_p999_us <= r.late_max_us
    assert "deadlines" in r.describe()


@pytest.mark.parametrize(("missed", "late_max_ms", "holds"), [
    (0, 0.1, True),
    (round(MAX_MISSED_SHARE * 10_000), 1.0, True),
    (round(MAX_MISSED_SHARE * 10_000) + 2, 1.0, False),
    (0, MAX_STALL_MS + 1.0, False),
])
def test_a_host_holds_the_rate_within_both_bounds(missed: int, late_max_ms: float,
                                                  holds: bool) -> None:
    clock = HostClock(10_000 - missed, missed, 50.0, 100.0, late_max_ms * 1e3)
    assert clock.holds() is holds


def test_not_judged_is_a_skip_with_the_host_figures() -> None:
    bad = HostClock(9000, 1000, 800.0, 5000.0, 80_000.0)
    with pytest.raises(pytest.skip.Exception, match=r"not judged \(x\): .*missed 1000 of 10000"):
        judge_realtime(bad, "x")
    judge_realtime(HostClock(10_000, 0, 20.0, 40.0, 90.0), "x")  # judged: returns
    with pytest.raises(AssertionError):
        judge_realtime(None, "x")


@pytest.mark.parametrize(("waiting", "missed", "kept"), [
    (0, 0, False),
    (round(MAX_MISSED_SHARE * 10_000), 800, False),  # at the bound: held
    (round(MAX_MISSED_SHARE * 10_000) + 2, 800, True),
    (100, 3000, False),  # misses of the loop's own are never the host's
    (None, 3000, False),  # a kernel that does not say: the probe alone judges
])
def test_a_service_s_loop_kept_from_its_cpu_is_the_host_s_doing(
        waiting: int | None, missed: int, kept: bool) -> None:
    status = {"ticks": 10_000 - missed, "missed_ticks": missed, "missed_waiting_cpu": waiting}
    why = loop_kept_from_cpu(status)
    assert (why is not None) is kept
    if kept:
        assert f"missed {waiting} of 10000 deadlines" in str(why)
        assert "waiting for a CPU" in str(why)
        held = HostClock(10_000, 0, 20.0, 40.0, 90.0)
        with pytest.raises(pytest.skip.Exception, match=r"not judged \(y\): the service's loop"):
            judge_realtime(held, "y", status)
    else:
        judge_realtime(HostClock(10_000, 0, 20.0, 40.0, 90.0), "y", status)  # judged
    # the same figures of the platform's own loop, in the status' platform block
    platform = {"platform": {"received_t": 1.0, **status}, "ticks": 10_000, "missed_ticks": 0,
                "missed_waiting_cpu": 0}
    assert (loop_kept_from_cpu(platform) is not None) is kept
    if kept:
        assert "the platform's loop missed" in str(loop_kept_from_cpu(platform))


def test_since_an_earlier_status_only_the_deadlines_between_count() -> None:
    # 600 of the first 10 000 deadlines waited for a CPU (6 %: kept), none of the next 10 000
    early = {"ticks": 9_400, "missed_ticks": 600, "missed_waiting_cpu": 600,
             "platform": {"ticks": 10_000, "missed_ticks": 0, "missed_waiting_cpu": 0}}
    late = {"ticks": 19_400, "missed_ticks": 600, "missed_waiting_cpu": 600,
            "platform": {"ticks": 20_000, "missed_ticks": 0, "missed_waiting_cpu": 0}}
    assert loop_kept_from_cpu(early) is not None
    assert loop_kept_from_cpu(late) is None  # 3 % since the start: held
    assert loop_kept_from_cpu(late, since=early) is None  # nothing missed in between
    # the reverse: a quiet start, then 1 800 of the next 10 000 (18 %; 9 % since the start)
    worse = {**late, "ticks": 18_200, "missed_ticks": 1_800, "missed_waiting_cpu": 1_800}
    start = {**early, "ticks": 10_000, "missed_ticks": 0, "missed_waiting_cpu": 0}
    why = loop_kept_from_cpu(worse, since={**worse, "ticks": 8_200, "missed_ticks": 1_800,
                                          "missed_waiting_cpu": 1_800})
    assert why is None  # the same misses before and after: none in between
    why = loop_kept_from_cpu(worse, since=start)
    assert why is not None and "missed 1800 of 10000 deadlines (18.0 %)" in why
    # the platform's own loop, between two statuses
    plat = {**late, "platform": {"ticks": 18_800, "missed_ticks": 1_200,
                                 "missed_waiting_cpu": 1_200}}
    assert "the platform's loop missed 1200 of 10000" in str(loop_kept_from_cpu(plat, since=early))


def test_an_identification_the_product_warned_about_is_not_judged() -> None:
    import subprocess

    held = HostClock(10_000, 0, 20.0, 40.0, 90.0)
    warned = subprocess.CompletedProcess(
        ["motcomp", "identify"], 0, "", "wrote x\nwarning: the service missed 300 of 10000 "
        "deadlines (3.0 %) while the data were recorded: the host took the loop's time, and "
        "the fitted delay and dynamics carry its stalls; identify again on a quiet host\n")
    with pytest.raises(pytest.skip.Exception, match=r"not judged \(z\): identify warned: "
                       r"warning: the service missed 300"):
        judge_realtime(held, "z", None, warned)
    clean = subprocess.CompletedProcess(["motcomp", "identify"], 0, "", "wrote x\n")
    judge_realtime(held, "z", None, clean)  # judged
