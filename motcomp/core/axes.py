"""The platform's axes: fixed names, order and SI units.

ULTIMATE-style platforms have X-Y rails carrying a hexapod: eight degrees of freedom.  Arrays of
per-axis values in motcomp are always in the order of :data:`AXES`.
"""

from __future__ import annotations

from typing import Final

AXES: Final[tuple[str, ...]] = (
    "rails_x",
    "rails_y",
    "hex_x",
    "hex_y",
    "hex_z",
    "hex_roll",
    "hex_pitch",
    "hex_yaw",
)
"""Axis names, in the order of every per-axis array."""

N_AXES: Final[int] = len(AXES)

AXIS_INDEX: Final[dict[str, int]] = {name: i for i, name in enumerate(AXES)}

ROTATIONAL: Final[frozenset[str]] = frozenset({"hex_roll", "hex_pitch", "hex_yaw"})


def unit(axis: str) -> str:
    """Position unit of ``axis``: ``"rad"`` for rotations, ``"m"`` otherwise."""
    if axis not in AXIS_INDEX:
        raise KeyError(f"unknown axis {axis!r}; axes are {', '.join(AXES)}")
    return "rad" if axis in ROTATIONAL else "m"
