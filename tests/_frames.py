"""Checks on output frames received over the wire, and strategies for hostile input frames."""

from __future__ import annotations

from typing import Any

import numpy as np
from hypothesis import strategies as st

from motcomp.core.axes import AXES

ints = st.integers(-(2**63), 2**64 - 1)  # what msgpack can carry
scalars = st.none() | st.booleans() | ints | st.floats() | st.text(max_size=8) \
    | st.binary(max_size=8)
anything = st.recursive(
    scalars, lambda c: st.lists(c, max_size=4) | st.dictionaries(scalars, c, max_size=4),
    max_leaves=12)
"""Any msgpack-able object."""
seqs = st.integers(0, 3000) | ints
frame_like = st.fixed_dictionaries(
    {}, optional={"seq": anything | seqs, "t": anything | st.floats(),
                  "pos": anything | st.dictionaries(st.sampled_from([*AXES, "rails_z"]),
                                                    anything | st.floats(), max_size=4),
                  "other": anything})
"""Maps shaped like input frames, with anything in their fields."""


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
