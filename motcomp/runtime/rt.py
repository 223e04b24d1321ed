"""Optional real-time scheduling, scheduler slice and CPU pinning of the calling thread, and the
CPUs' wake-up latency while the process runs (Linux).

All are best effort: each call reports what happened and the loop runs whatever the answer.
Open zenoh *before* raising the loop thread: zenoh's threads inherit the policy of the thread
that opens the session.

- SCHED_FIFO needs a privilege (``CAP_SYS_NICE`` or an ``RLIMIT_RTPRIO``).
- The *slice* needs none.  Since Linux 6.12 the normal scheduler (EEVDF) takes a per-thread
  request ``sched_attr.sched_runtime`` (0.1-100 ms; default about 0.7 ms x (1 + log2 CPUs)): a
  thread with a shorter slice than the running one preempts it when it wakes up, instead of
  waiting for that one's slice or the next scheduler tick.  For a loop that sleeps between ticks
  this removes most stalls of a few milliseconds behind other normal-priority work (measured in
  docs/BENCHMARKS.md).  Older kernels accept the call and ignore the value: the report says so
  (read back with ``sched_getattr``).  Python has no wrapper for these two system calls, hence
  ``ctypes``.
- The *wake-up latency* is the kernel's CPU latency QoS (``/dev/cpu_dma_latency``): while a
  process keeps that file open with a value written to it, no CPU enters an idle state that
  takes longer than that to leave.  A loop that sleeps between ticks then wakes on time and on
  warmer caches (with 0, idle CPUs poll; on a virtual machine its virtual CPUs stop halting).
  The file is root's by default; docs/DEPLOYMENT.md gives the service's user access to it.
  Only a cpuidle driver honours the request: on a kernel without one (``current_driver``
  ``none``, as on some virtual machines) idle CPUs halt whatever is asked, and the report says
  so (:func:`idle_driver`).
- *Subnormals* are flushed to zero in the loop thread (:mod:`motcomp.core.fpmode`).
"""

from __future__ import annotations

import ctypes
import os
import platform
import struct
from pathlib import Path

from motcomp.config import SLICE_MAX_US, SLICE_MIN_US, LoopConfig
from motcomp.core.fpmode import flush_subnormals

__all__ = ["CPUIDLE_DIR", "CPU_LATENCY_DEVICE", "get_slice_us", "hold_cpu_latency", "idle_driver",
           "pin_to_cpu", "schedule_loop", "set_realtime", "set_slice"]

CPU_LATENCY_DEVICE = "/dev/cpu_dma_latency"
"""The kernel's CPU latency QoS: a request holds while its file descriptor stays open."""
CPUIDLE_DIR = "/sys/devices/system/cpu/cpuidle"
"""The kernel's cpuidle subsystem in sysfs: ``current_driver`` names the driver of idle states."""

_NO_DRIVER = "no cpuidle driver, idle CPUs halt (docs/DEPLOYMENT.md)"

_SYSCALLS = {"x86_64": (314, 315), "aarch64": (274, 275)}
"""(sched_setattr, sched_getattr) system call numbers."""


class _SchedAttr(ctypes.Structure):
    """``struct sched_attr`` (include/uapi/linux/sched/types.h), SCHED_ATTR_SIZE_VER1."""

    _fields_ = [("size", ctypes.c_uint32), ("sched_policy", ctypes.c_uint32),
                ("sched_flags", ctypes.c_uint64), ("sched_nice", ctypes.c_int32),
                ("sched_priority", ctypes.c_uint32), ("sched_runtime", ctypes.c_uint64),
                ("sched_deadline", ctypes.c_uint64), ("sched_period", ctypes.c_uint64),
                ("sched_util_min", ctypes.c_uint32), ("sched_util_max", ctypes.c_uint32)]


def _syscall(index: int, *args: object) -> None:
    nrs = _SYSCALLS.get(platform.machine())
    if nrs is None or not hasattr(os, "sched_getscheduler"):
        raise OSError(0, f"sched_setattr is not known on {platform.system()} "
                         f"{platform.machine()}")
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.syscall(ctypes.c_long(nrs[index]), *args) != 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))


def _get_attr() -> _SchedAttr:
    attr = _SchedAttr()
    _syscall(1, ctypes.c_int(0), ctypes.byref(attr), ctypes.c_uint(ctypes.sizeof(attr)),
             ctypes.c_uint(0))
    return attr


def get_slice_us() -> float:
    """The calling thread's scheduler slice (us) as the kernel reports it (0: not reported)."""
    return _get_attr().sched_runtime / 1e3


def set_slice(slice_us: float) -> str:
    """Ask the normal scheduler for a ``slice_us`` slice for the calling thread (0: leave the
    kernel's default); returns what happened.  A thread under a real-time policy is left as it
    is (its slice means nothing there)."""
    if slice_us <= 0:
        return "default slice"
    slice_us = min(max(float(slice_us), SLICE_MIN_US), SLICE_MAX_US)  # what the kernel does
    try:
        attr = _get_attr()
        if attr.sched_policy != 0:  # SCHED_OTHER
            return "slice not set (not under the normal scheduler)"
        attr.size = ctypes.sizeof(attr)
        attr.sched_flags = 0
        attr.sched_runtime = round(slice_us * 1e3)
        _syscall(0, ctypes.c_int(0), ctypes.byref(attr), ctypes.c_uint(0))
        got = get_slice_us()
    except OSError as exc:
        return f"slice {slice_us:g} us not set ({exc.strerror}); default slice"
    if abs(got - slice_us) > 1.0:
        return (f"slice {slice_us:g} us not supported by this kernel (it reports {got:g} us; "
                "needs Linux 6.12 or later); default slice")
    return f"slice {got:g} us"


def set_realtime(priority: int) -> str:
    """SCHED_FIFO at ``priority`` (1-99) for the calling thread; returns what happened."""
    if priority <= 0:
        return "normal scheduling (realtime_priority = 0)"
    if not hasattr(os, "sched_setscheduler"):
        return "SCHED_FIFO not available on this OS"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError) as exc:
        return f"SCHED_FIFO {priority} not permitted ({exc.strerror}); normal scheduling"
    return f"SCHED_FIFO priority {priority}"


def pin_to_cpu(cpu: int) -> str:
    """Pin the calling thread to ``cpu`` (-1: no pinning); returns what happened."""
    if cpu < 0:
        allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        if allowed and len(allowed) < (os.cpu_count() or 0):  # a taskset, a cgroup's cpuset
            return f"not pinned (the process may run on CPU {', '.join(map(str, allowed))})"
        return "not pinned"
    if not hasattr(os, "sched_setaffinity"):
        return "CPU pinning not available on this OS"
    try:
        os.sched_setaffinity(0, {cpu})
    except (OSError, ValueError) as exc:
        return f"cannot pin to CPU {cpu} ({exc}); not pinned"
    return f"pinned to CPU {cpu}"


def idle_driver(cpuidle_dir: str = CPUIDLE_DIR, cmdline: str = "/proc/cmdline") -> str | None:
    """How this machine's idle CPUs wait, where that makes a wake-up latency request moot: why
    none can take effect, or None where a cpuidle driver honours it (or sysfs does not say).

    Without a cpuidle driver the kernel idles a CPU the architecture's default way (``hlt`` on
    x86: on a virtual machine its virtual CPU halts and exits to the host), whatever is asked;
    with ``idle=poll`` on its command line every idle CPU polls already."""
    try:
        args = Path(cmdline).read_text().split()
    except OSError:
        args = []
    if "idle=poll" in args:
        return "idle CPUs poll already (idle=poll)"
    base = Path(cpuidle_dir)
    try:
        driver = (base / "current_driver").read_text().strip()
    except OSError:
        # a kernel without cpuidle has no such directory beside its CPUs'
        return _NO_DRIVER if base.parent.is_dir() and not base.exists() else None
    return _NO_DRIVER if driver == "none" else None


def hold_cpu_latency(latency_us: int, device: str = CPU_LATENCY_DEVICE,
                     cpuidle_dir: str = CPUIDLE_DIR, cmdline: str = "/proc/cmdline"
                     ) -> tuple[str, int | None]:
    """Ask that no CPU take longer than ``latency_us`` to wake from idle while the returned file
    descriptor stays open (-1: leave the system's setting; ``(report, None)``).  Returns what
    happened -- including that the request cannot take effect on this machine
    (:func:`idle_driver`) -- and the descriptor to close when the request should end (None
    where nothing is held).  The request ends with the process in any case."""
    if latency_us < 0:
        return "CPU wake-up latency left to the system", None
    try:
        fd = os.open(device, os.O_RDWR)
    except OSError as exc:
        return (f"CPU wake-up latency not held ({device}: {exc.strerror}; "
                "docs/DEPLOYMENT.md)"), None
    try:
        os.write(fd, struct.pack("i", int(latency_us)))
        held = struct.unpack("i", os.pread(fd, 4, 0))[0]
    except OSError as exc:
        os.close(fd)
        return f"CPU wake-up latency not held ({device}: {exc.strerror})", None
    report = f"CPU wake-up latency at most {latency_us} us (the system's now {held} us)"
    moot = idle_driver(cpuidle_dir, cmdline)
    if moot is not None:
        report += f", held but moot here: {moot}"
    return report, fd


def schedule_loop(loop: LoopConfig) -> tuple[str, int | None]:
    """Schedule the calling thread as ``loop`` asks for the service's loop thread (real-time
    priority, slice, CPU), hold the CPUs' wake-up latency and flush its subnormals; returns
    what happened (the status' ``realtime``) and the latency request's descriptor (None: none
    held), to close when the loop ends."""
    naps = f"naps of {loop.sleep_max_us:g} us" if loop.sleep_max_us > 0 else "one sleep per tick"
    latency, fd = hold_cpu_latency(loop.cpu_latency_us)
    return (f"{set_realtime(loop.realtime_priority)}; {set_slice(loop.slice_us)}; {naps}; "
            f"{pin_to_cpu(loop.cpu)}; {latency}; {flush_subnormals()}"), fd
