"""Optional real-time scheduling and CPU pinning of the calling thread (Linux).

Both are best effort: without the privilege (``CAP_SYS_NICE`` or an ``RLIMIT_RTPRIO``), the call
reports why and the loop runs at normal priority.  Open zenoh *before* raising the loop thread:
zenoh's threads inherit the policy of the thread that opens the session.
"""

from __future__ import annotations

import os

__all__ = ["pin_to_cpu", "set_realtime"]


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
        return "not pinned"
    if not hasattr(os, "sched_setaffinity"):
        return "CPU pinning not available on this OS"
    try:
        os.sched_setaffinity(0, {cpu})
    except (OSError, ValueError) as exc:
        return f"cannot pin to CPU {cpu} ({exc}); not pinned"
    return f"pinned to CPU {cpu}"
