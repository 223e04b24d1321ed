"""Real-time scheduling and pinning are best effort and report what happened."""

from __future__ import annotations

import math
import os
import platform
import struct
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest

from motcomp.config import load_config, new_tick
from motcomp.core.axes import AXES
from motcomp.core.fpmode import subnormals_flushed
from motcomp.core.tick import step
from motcomp.errors import ConfigError
from motcomp.io.wire import encode_input
from motcomp.resources import config_file
from motcomp.runtime.rt import (
    CPU_LATENCY_DEVICE,
    hold_cpu_latency,
    idle_driver,
    pin_to_cpu,
    set_realtime,
)

T = TypeVar("T")


def test_off_by_default() -> None:
    assert "normal" in set_realtime(0)
    assert pin_to_cpu(-1).startswith("not pinned")


@pytest.mark.skipif((os.cpu_count() or 1) < 2 or not hasattr(os, "sched_setaffinity"),
                    reason="needs two CPUs and Linux")
def test_not_pinned_says_where_a_restricted_process_may_run() -> None:
    """Unpinned in a process that a taskset or a cpuset keeps on one CPU: the report says so
    (an operator reading "not pinned" would expect every CPU)."""
    cpu = max(os.sched_getaffinity(0))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    out = subprocess.run(
        [sys.executable, "-c", "from motcomp.runtime.rt import pin_to_cpu; print(pin_to_cpu(-1))"],
        capture_output=True, text=True, env=env, check=True, timeout=60,
        preexec_fn=lambda: os.sched_setaffinity(0, {cpu})).stdout.strip()
    assert out == f"not pinned (the process may run on CPU {cpu})"


def test_reports_match_the_kernel_state() -> None:
    # in a child process, so this test process keeps its own policy
    code = (
        "import os, threading\n"
        "from motcomp.runtime.rt import set_realtime, pin_to_cpu\n"
        "out = {}\n"
        "def run():\n"
        "    out['rt'] = set_realtime(1)\n"
        "    out['pol'] = os.sched_getscheduler(0)\n"
        "    out['pin'] = pin_to_cpu(0)\n"
        "    out['aff'] = os.sched_getaffinity(0)\n"
        "t = threading.Thread(target=run); t.start(); t.join()\n"
        "print(out['rt']); print(out['pol'] == os.SCHED_FIFO); print(out['pin']);"
        " print(out['aff'] == {0})\n"
        "print(os.sched_getscheduler(0) == os.SCHED_FIFO)\n"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    lines = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           env=env, check=True, timeout=60).stdout.splitlines()
    rt, is_fifo, pin, pinned, main_fifo = lines
    assert ("SCHED_FIFO priority 1" in rt) == (is_fifo == "True")
    assert ("pinned to CPU 0" in pin) == (pinned == "True")
    assert main_fifo == "False"  # only the calling thread was raised


def _in_thread(code: str, then: str = "") -> list[str]:
    """Run ``code`` (which fills ``out``) in a new thread of a child process, then ``then`` in
    that process' main thread; the printed lines of ``out``'s values."""
    prog = (
        "import os, threading\n"
        "from motcomp.runtime.rt import get_slice_us, set_realtime, set_slice\n"
        "out = {}\n"
        "def run():\n" + "".join(f"    {line}\n" for line in code.splitlines()) +
        "t = threading.Thread(target=run); t.start(); t.join()\n" + then +
        "for v in out.values(): print(v)\n"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    return subprocess.run([sys.executable, "-c", prog], capture_output=True, text=True,
                          env=env, check=True, timeout=60).stdout.splitlines()


def test_slice_report_matches_what_the_kernel_reads_back() -> None:
    before, report, after, clamped, clamped_after = _in_thread(
        "out['before'] = get_slice_us()\n"
        "out['report'] = set_slice(250)\n"
        "out['after'] = get_slice_us()\n"
        "out['clamped'] = set_slice(20)\n"
        "out['clamped_after'] = get_slice_us()\n")
    if report.startswith("slice 250 us"):  # Linux 6.12+: the kernel keeps the request
        assert float(after) == 250.0
        assert clamped == "slice 100 us" and float(clamped_after) == 100.0  # the kernel's floor
    else:  # older kernels ignore it, and the report says so
        assert "not supported" in report or "not set" in report, report
        assert float(after) == float(before)


def test_slice_is_per_thread_and_zero_leaves_the_default() -> None:
    report, zero, kept, main = _in_thread(
        "out['report'] = set_slice(300)\n"
        "out['zero'] = set_slice(0)\n"
        "out['kept'] = get_slice_us()\n",
        then="out['main'] = get_slice_us()\n")
    assert zero == "default slice"
    if report == "slice 300 us":
        assert float(kept) == 300.0  # 0 leaves the thread's slice as it is
        assert float(main) != 300.0  # the process' main thread kept its own
    else:
        assert "not" in report, report


def test_slice_not_applied_under_a_real_time_policy() -> None:
    rt, report = _in_thread("out['rt'] = set_realtime(1)\nout['slice'] = set_slice(200)\n")
    if "SCHED_FIFO priority 1" in rt:
        assert report == "slice not set (not under the normal scheduler)"
    else:
        assert report.startswith(("slice 200 us", "slice 200 us not supported"))


@pytest.mark.parametrize(("key", "value", "ok"), [
    ("slice_us", 0, True), ("slice_us", 100, True), ("slice_us", 2500, True),
    ("slice_us", 50, False), ("slice_us", -1, False), ("slice_us", 200_000, False),
    ("cpu_latency_us", -1, True), ("cpu_latency_us", 0, True), ("cpu_latency_us", 20, True),
    ("cpu_latency_us", -2, False), ("cpu_latency_us", 2_000_000, False)])
def test_config_loop_ranges(tmp_path: Path, key: str, value: float, ok: bool) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[loop]\n{key} = {value}\n')
    if ok:
        assert getattr(load_config(cfg).loop, key) == value
    else:
        with pytest.raises(ConfigError, match=key):
            load_config(cfg)


def test_the_cpu_latency_request_is_left_or_says_why_it_is_not_held(tmp_path: Path) -> None:
    assert hold_cpu_latency(-1) == ("CPU wake-up latency left to the system", None)
    report, fd = hold_cpu_latency(0, device=str(tmp_path))  # not a device one can write
    assert fd is None
    assert report == (f"CPU wake-up latency not held ({tmp_path}: Is a directory; "
                      "docs/DEPLOYMENT.md)")
    if os.path.exists("/dev/full"):  # opens, but refuses every write: nothing held, fd closed
        before = len(os.listdir("/proc/self/fd"))
        report, fd = hold_cpu_latency(0, device="/dev/full")
        assert fd is None and len(os.listdir("/proc/self/fd")) == before
        assert report == "CPU wake-up latency not held (/dev/full: No space left on device)"


@pytest.mark.skipif(not os.access(CPU_LATENCY_DEVICE, os.W_OK),
                    reason=f"{CPU_LATENCY_DEVICE} is not writable here (root's by default)")
def test_the_cpu_latency_request_holds_while_its_descriptor_is_open() -> None:
    report, fd = hold_cpu_latency(7)
    assert fd is not None
    try:
        # the kernel's answer, read apart: the least of every request held now
        with open(CPU_LATENCY_DEVICE, "rb") as dev:
            system = struct.unpack("i", dev.read(4))[0]
        assert 0 <= system <= 7
        held = f"CPU wake-up latency at most 7 us (the system's now {system} us)"
        moot = idle_driver()  # this machine's idle: the request may be moot
        assert report == held if moot is None else report.startswith(f"{held}, held but moot here: "
                                                                     f"{moot}")
    finally:
        os.close(fd)


def cpuidle(tmp_path: Path, driver: str | None) -> str:
    """A sysfs ``cpu`` directory whose ``cpuidle/current_driver`` reads ``driver`` (None: a
    kernel without cpuidle, no such directory); returns the cpuidle directory's path."""
    base = tmp_path / "cpu" / "cpuidle"
    if driver is None:
        base.parent.mkdir(parents=True)
    else:
        base.mkdir(parents=True)
        (base / "current_driver").write_text(driver + "\n")
    return str(base)


def test_the_latency_request_says_when_no_idle_driver_can_honour_it(tmp_path: Path) -> None:
    quiet = tmp_path / "cmdline"
    quiet.write_text("console=ttyS0 quiet\n")
    for driver in ("haltpoll", "intel_idle", "acpi_idle"):
        assert idle_driver(cpuidle(tmp_path / driver, driver), str(quiet)) is None
    assert idle_driver(cpuidle(tmp_path / "a", "none"), str(quiet)) == (
        "no cpuidle driver, idle CPUs halt (docs/DEPLOYMENT.md)")
    assert idle_driver(cpuidle(tmp_path / "b", None), str(quiet)) == (
        "no cpuidle driver, idle CPUs halt (docs/DEPLOYMENT.md)")
    assert idle_driver(str(tmp_path / "no-sysfs" / "cpuidle"), str(quiet)) is None  # unknown
    polling = tmp_path / "poll"
    polling.write_text("console=ttyS0 idle=poll quiet\n")
    assert idle_driver(cpuidle(tmp_path / "c", "none"), str(polling)) == (
        "idle CPUs poll already (idle=poll)")
    # the request through a file that takes it as the device does (written, read back)
    device = tmp_path / "latency"
    device.write_bytes(struct.pack("i", 2_000_000_000))
    report, fd = hold_cpu_latency(0, device=str(device),
                                  cpuidle_dir=cpuidle(tmp_path / "d", "none"), cmdline=str(quiet))
    assert fd is not None
    os.close(fd)
    assert report == ("CPU wake-up latency at most 0 us (the system's now 0 us), held but moot "
                      "here: no cpuidle driver, idle CPUs halt (docs/DEPLOYMENT.md)")
    report, fd = hold_cpu_latency(0, device=str(device),
                                  cpuidle_dir=cpuidle(tmp_path / "e", "haltpoll"),
                                  cmdline=str(quiet))
    assert fd is not None
    os.close(fd)
    assert report == "CPU wake-up latency at most 0 us (the system's now 0 us)"


def test_the_cpu_latency_needs_a_restart(tmp_path: Path) -> None:
    from motcomp.runtime.reload import restart_changes

    base = load_config(config_file("motcomp.toml"))
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[loop]\ncpu_latency_us = -1\n')
    assert restart_changes(base, load_config(cfg)) == ["loop.cpu_latency_us"]


SUBNORMAL = struct.unpack("<d", struct.pack("<Q", 1))[0]
"""The smallest subnormal double, 4.9e-324 (built from its bits: no arithmetic)."""
FLUSHING = platform.machine() in ("x86_64", "aarch64") and sys.platform.startswith("linux")


def in_thread(fn: Callable[[], T]) -> T:
    """``fn()`` in a thread of its own (a floating-point mode set there leaves this one alone)."""
    out: list[T] = []
    th = threading.Thread(target=lambda: out.append(fn()))
    th.start()
    th.join()
    assert out, "the thread raised"
    return out[0]


def arithmetic(x: float, y: float) -> tuple[float, float, float]:
    """A subnormal result, a subnormal input times one, and numpy's product of the two."""
    return x / 4.0, y * 1.0, float(np.multiply(np.array([y]), 1.0)[0])


@pytest.mark.skipif(not FLUSHING, reason="flushing is known on x86-64 and AArch64 Linux")
def test_subnormals_are_flushed_in_the_block_and_its_threads_and_nowhere_else() -> None:
    normal = sys.float_info.min  # 2.2e-308: a quarter of it is subnormal
    assert arithmetic(normal, SUBNORMAL) == (normal / 4, SUBNORMAL, SUBNORMAL)

    def block() -> tuple[str, tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        with subnormals_flushed() as report:
            inside = arithmetic(normal, SUBNORMAL)
            child = in_thread(lambda: arithmetic(normal, SUBNORMAL))  # inherits the mode
        return report, inside, child, arithmetic(normal, SUBNORMAL)

    report, inside, child, after = in_thread(block)  # compared here, in this thread's mode
    assert report == "subnormals flushed to zero"
    assert inside == child == (0.0, 0.0, 0.0)
    assert after == (normal / 4, SUBNORMAL, SUBNORMAL)  # the block's end restores the mode
    assert arithmetic(normal, SUBNORMAL) == (normal / 4, SUBNORMAL, SUBNORMAL)  # this thread's


def is_subnormal(x: float) -> bool:
    """From the bits (a comparison would read a subnormal as zero in the flushed mode)."""
    bits = struct.unpack("<Q", struct.pack("<d", x))[0] & 0x7FFF_FFFF_FFFF_FFFF
    return 0 < bits < 0x0010_0000_0000_0000


def rest_after_a_tiny_motion(flush: bool) -> list[float]:
    """The tick's outputs and reference of the rails while a motion of 1e-290 m ends and they
    come to rest (a large motion sinks as far, only later), the subnormal ones."""
    cfg = load_config(config_file("motcomp.toml"))
    params, state = new_tick(cfg)

    def run() -> list[float]:
        found = []
        for k in range(4000):
            now = 10**12 + k * 10**6
            y = 1e-290 * math.sin(2 * math.pi * 0.5 * k / 1000) if k < 1000 else 0.0
            frame = encode_input(k, now / 1e9, {a: y if a.startswith("rails") else 0.0
                                                for a in AXES})
            out = step(state, params, now, [frame])
            found += [x for x in (*out.u, *state.shaper.ref) if is_subnormal(x)]
        return found

    def flushed() -> list[float]:
        with subnormals_flushed():
            return run()

    return in_thread(flushed if flush else run)


@pytest.mark.skipif(not FLUSHING, reason="flushing is known on x86-64 and AArch64 Linux")
def test_the_tick_computes_no_subnormal_where_it_flushes_them() -> None:
    """At rest the states of decaying filters sink towards zero through the subnormals (slow
    on some CPUs): in the loop's mode the tick never holds one."""
    assert rest_after_a_tiny_motion(flush=False)  # they arise where they are not flushed
    assert rest_after_a_tiny_motion(flush=True) == []


@pytest.mark.skipif(not FLUSHING, reason="flushing is known on x86-64 and AArch64 Linux")
def test_the_block_restores_the_floating_point_environment_exactly() -> None:
    """A thread already flushing keeps flushing after a block that asked for no flushing, and
    one that was not, after a block that flushed: the environment comes back as it was."""
    normal = sys.float_info.min

    def nested() -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        with subnormals_flushed():
            with subnormals_flushed(on=False) as report:
                assert report == "subnormals kept"
                kept = arithmetic(normal, SUBNORMAL)
            still = arithmetic(normal, SUBNORMAL)
        return kept, still, arithmetic(normal, SUBNORMAL)

    kept, still, after = in_thread(nested)
    assert kept == after == (normal / 4, SUBNORMAL, SUBNORMAL)
    assert still == (0.0, 0.0, 0.0)
