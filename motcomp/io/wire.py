"""The wire contract: msgpack frames between the motion source, the service and the platform.

Axes: :data:`motcomp.core.axes.AXES`, SI units (m, rad).

Input (key ``sim/motion/setpoint``)
    ``{"seq": int, "t": float, "pos": {axis: float, ...}}``; a subset of axes is allowed (the
    others hold their last value).  Checked by :func:`motcomp.core.tick.parse_input`, the one
    validation of input frames (reasons in :data:`motcomp.core.tick.REJECT_REASONS`).
Output (key ``platform/setpoint``)
    ``{"seq": int, "t": float, "src_seq": int, "pos": {all 8 axes}, "flags": [str, ...]}``
    and ``"rx": int`` (ns after ``t`` the tick took its input frames) where not 0.
Feedback (key ``platform/feedback``)
    ``{"t": float, "pos": {axis: float}, "acc": {axis: float}}``.
Status (key ``motcomp/status``)
    a map described in docs/WIRE.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import msgpack

from motcomp.core.axes import AXES
from motcomp.errors import FrameError

__all__ = [
    "decode_feedback",
    "decode_output",
    "encode_feedback",
    "encode_input",
    "encode_output",
]

_pack = msgpack.Packer(use_bin_type=True).pack


def encode_input(seq: int, t: float | None, pos: dict[str, float]) -> bytes:
    """An input frame; without ``t`` when ``t`` is None (the service then times the sample by
    its arrival)."""
    if t is None:
        return _pack({"seq": seq, "pos": pos})
    return _pack({"seq": seq, "t": t, "pos": pos})


def encode_output(seq: int, t: float, src_seq: int, positions: Sequence[float],
                  flags: Sequence[str], rx_ns: int = 0) -> bytes:
    """An output frame; ``positions`` in :data:`AXES` order (packed as floats); ``rx`` (ns
    after ``t`` the tick took its input frames) only when not 0."""
    frame: dict[str, Any] = {"seq": seq, "t": float(t), "src_seq": src_seq,
                             "pos": dict(zip(AXES, map(float, positions), strict=True)),
                             "flags": list(flags)}
    if rx_ns:
        frame["rx"] = int(rx_ns)
    return _pack(frame)


def encode_feedback(t: float, pos: dict[str, float], acc: dict[str, float]) -> bytes:
    return _pack({"t": t, "pos": pos, "acc": acc})


def _unpack_map(payload: bytes) -> dict[Any, Any]:
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        raise FrameError("decode", f"not a msgpack frame: {str(exc)[:80]}") from None
    if not isinstance(obj, dict):
        raise FrameError("decode", f"frame is a {type(obj).__name__}, not a map")
    return obj


def decode_output(payload: bytes) -> dict[str, Any]:
    """An output frame as a dict (for clients and tests)."""
    obj = _unpack_map(payload)
    missing = {"seq", "t", "src_seq", "pos", "flags"} - set(obj)
    if missing:
        raise FrameError("schema", f"output frame lacks {sorted(missing)}")
    return obj


def decode_feedback(payload: bytes) -> dict[str, Any]:
    obj = _unpack_map(payload)
    missing = {"t", "pos", "acc"} - set(obj)
    if missing:
        raise FrameError("schema", f"feedback frame lacks {sorted(missing)}")
    return obj
