"""Checks on output frames received over the wire."""

from __future__ import annotations

from typing import Any

import numpy as np


def assert_frames_within_limits(frames: list[dict[str, Any]], axis: str, v_max: float,
                                a_max: float, rate_hz: float = 1000.0, min_checked: int = 1000
                                ) -> None:
    """Velocity between any two received frames (over their own sample times: a frame after a
    stall covers the periods caught up) and acceleration over consecutive regular samples."""
    seq = np.array([f["seq"] for f in frames])
    t = np.array([f["t"] for f in frames])
    y = np.array([f["pos"][axis] for f in frames])
    h = 1.0 / rate_hz
    dt = np.diff(t)  # wall-clock floats: ~0.2 us resolution, fine for velocities over gaps
    assert np.max(np.abs(np.diff(y) / dt)) <= v_max * (1 + 1e-3)
    regular = (np.diff(seq) == 1) & (np.abs(dt - h) < 1e-2 * h)
    ok = regular[1:] & regular[:-1]
    assert ok.sum() >= min_checked
    v = np.diff(y) / h  # exact on regular samples
    assert np.max(np.abs(np.diff(v)[ok] / h)) <= a_max * (1 + 1e-6) + 1e-6
