"""The wire contract: msgpack frames between the motion source, the service and the platform.

Axes: :data:`motcomp.core.axes.AXES`, SI units (m, rad).

Input (key ``sim/motion/setpoint``)
    ``{"seq": int, "t": float, "pos": {axis: float, ...}}``; a subset of axes is allowed (the
    others hold their last value).
Output (key ``platform/setpoint``)
    ``{"seq": int, "t": float, "src_seq": int, "pos": {all 8 axes}, "flags": [str, ...]}``.
Feedback (key ``platform/feedback``)
    ``{"t": float, "pos": {axis: float}, "acc": {axis: float}}``.
Status (key ``motcomp/status``)
    a map described in docs/WIRE.md.

Validation of input frames (:class:`InputValidator`) rejects, counts and never forwards a frame
that is: not msgpack or not a map (``decode``); missing ``seq`` or ``pos``, with an unknown
top-level key or an empty ``pos`` (``schema``); of a wrong type -- ``seq`` not an int, ``t`` not
a number, a position not a number (``type``); naming an unknown axis (``axis``); carrying a
NaN or infinite position or ``t`` (``nonfinite``); putting an axis further outside its limits than
``reject_beyond_fraction`` of its range (``range``); or repeating or going back in ``seq``
(``duplicate``, ``old``).  After the input has been stale, any ``seq`` is accepted again (a
restarted sender starts from 0).  A rejected frame changes nothing.
"""

from __future__ import annotations

import math
import os
from array import array
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import msgpack

from motcomp.core.axes import AXES, AXIS_INDEX
from motcomp.errors import FrameError

__all__ = [
    "REJECT_REASONS",
    "InputValidator",
    "decode_feedback",
    "decode_input",
    "decode_output",
    "encode_feedback",
    "encode_input",
    "encode_output",
]

REJECT_REASONS: tuple[str, ...] = ("decode", "schema", "type", "axis", "nonfinite", "range",
                                   "duplicate", "old")
_INPUT_KEYS = frozenset({"seq", "t", "pos"})
_pack = msgpack.Packer(use_bin_type=True).pack

_cwire: Any = None
if os.environ.get("MOTCOMP_KERNEL", "").strip().lower() != "python":
    try:  # the compiled codec (motcomp/io/_cwire.c): the same bytes, the same verdicts
        from motcomp.io import _cwire
    except ImportError:  # pragma: no cover - exercised where no C compiler was available
        _cwire = None


def encode_input(seq: int, t: float, pos: dict[str, float]) -> bytes:
    """An input frame."""
    return _pack({"seq": seq, "t": t, "pos": pos})


def encode_output(seq: int, t: float, src_seq: int, positions: Sequence[float],
                  flags: Sequence[str]) -> bytes:
    """An output frame; ``positions`` in :data:`AXES` order (packed as floats)."""
    if _cwire is not None:
        return _cwire.pack_output(seq, t, src_seq, AXES, positions, flags)
    return _pack({"seq": seq, "t": float(t), "src_seq": src_seq,
                  "pos": dict(zip(AXES, map(float, positions), strict=True)),
                  "flags": list(flags)})


def encode_feedback(t: float, pos: dict[str, float], acc: dict[str, float]) -> bytes:
    return _pack({"t": t, "pos": pos, "acc": acc})


def _unpack_map(payload: bytes) -> dict[Any, Any]:
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        raise FrameError("decode", f"not a msgpack frame: {exc}") from None
    if not isinstance(obj, dict):
        raise FrameError("decode", f"frame is a {type(obj).__name__}, not a map")
    return obj


def _is_number(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def decode_input(payload: bytes) -> tuple[int, float | None, dict[str, float]]:
    """``(seq, t, pos)`` of an input frame, checked for structure, types, axes and finiteness
    (not for range or sequence: see :class:`InputValidator`).

    Raises
    ------
    FrameError
        With ``reason`` one of :data:`REJECT_REASONS` and a message naming the key and value.
    """
    obj = _unpack_map(payload)
    extra = set(obj) - _INPUT_KEYS
    if extra:
        raise FrameError("schema", f"unknown key(s) {sorted(map(str, extra))} in input frame")
    if "seq" not in obj or "pos" not in obj:
        raise FrameError("schema", f"input frame lacks {'seq' if 'seq' not in obj else 'pos'}")
    seq = obj["seq"]
    if not isinstance(seq, int) or isinstance(seq, bool):
        raise FrameError("type", f"seq must be an int, got {seq!r}")
    t = obj.get("t")
    if t is not None and not _is_number(t):
        raise FrameError("type", f"t must be a number, got {t!r}")
    if t is not None and not math.isfinite(t):
        raise FrameError("nonfinite", f"t is {t!r}")
    pos = obj["pos"]
    if not isinstance(pos, dict):
        raise FrameError("type", f"pos must be a map, got {type(pos).__name__}")
    if not pos:
        raise FrameError("schema", "pos is empty")
    for axis, value in pos.items():
        if axis not in AXIS_INDEX:
            raise FrameError("axis", f"unknown axis {axis!r} in pos")
        if not _is_number(value):
            raise FrameError("type", f"pos.{axis} must be a number, got {value!r}")
        if not math.isfinite(value):
            raise FrameError("nonfinite", f"pos.{axis} is {value!r}")
    return seq, (float(t) if t is not None else None), pos


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


@dataclass
class InputValidator:
    """Stateful acceptance of input frames (sequence numbers and ranges).

    ``p_min``/``p_max`` are the axis limits in :data:`AXES` order; a value is out of range if it
    lies further outside them than ``reject_beyond_fraction`` of the axis' range.
    """

    p_min: Sequence[float]
    p_max: Sequence[float]
    reject_beyond_fraction: float = 0.25
    last_seq: int | None = None
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REJECT_REASONS, 0))
    received: int = 0
    accepted: int = 0
    last_error: str = ""

    def __post_init__(self) -> None:
        self.set_limits(self.p_min, self.p_max)

    def set_limits(self, p_min: Sequence[float], p_max: Sequence[float]) -> None:
        f = self.reject_beyond_fraction
        self._bounds = {a: (lo - f * (hi - lo), hi + f * (hi - lo))
                        for a, lo, hi in zip(AXES, p_min, p_max, strict=True)}
        self._lo = array("d", [b[0] for b in self._bounds.values()])
        self._hi = array("d", [b[1] for b in self._bounds.values()])
        self.p_min, self.p_max = p_min, p_max

    def accept(self, payload: bytes, after_stale: bool = False
               ) -> tuple[int, float | None, dict[str, float]] | None:
        """``(seq, t, pos)`` of a valid frame, or None (counted under its reason).

        ``after_stale``: the input has been stale, so a ``seq`` that is not newer is accepted
        (the sender restarted).
        """
        self.received += 1
        try:
            seq, t, pos = self._decode(payload)
            last = self.last_seq
            if last is not None and not after_stale and seq <= last:
                raise FrameError("duplicate" if seq == last else "old",
                                 f"seq {seq} after {last}")
        except FrameError as exc:
            self.counts[exc.reason] += 1
            self.last_error = f"{exc.reason}: {exc}"
            return None
        self.last_seq = seq
        self.accepted += 1
        return seq, t, pos

    def _decode(self, payload: bytes) -> tuple[int, float | None, dict[str, float]]:
        """The common case in one pass: a map of the three keys whose ``pos`` values are floats
        within their bounds (one chained comparison also rejects NaN and infinities); anything
        else goes through :func:`decode_input`, which names the problem.  The compiled
        codec, when built, takes the common case first (motcomp/io/_cwire.c)."""
        if _cwire is not None:
            res = _cwire.parse_input(payload, AXIS_INDEX, self._lo, self._hi)
            if res is not None:
                return res
        try:
            obj = msgpack.unpackb(payload, raw=False)
        except Exception:  # msgpack raises several unrelated types
            obj = None
        if obj.__class__ is dict and "pos" in obj and "seq" in obj and len(obj) <= 3:
            seq, pos, t = obj["seq"], obj["pos"], obj.get("t")
            if (seq.__class__ is int and pos.__class__ is dict and pos
                    and (t is None or (t.__class__ is float and -math.inf < t < math.inf))
                    and (len(obj) == 2 or "t" in obj)):
                bounds = self._bounds
                for axis, value in pos.items():
                    b = bounds.get(axis)
                    if b is None or value.__class__ is not float or not b[0] <= value <= b[1]:
                        break
                else:
                    return seq, t, pos
        seq, t, pos = decode_input(payload)  # raises the precise FrameError
        for axis, value in pos.items():
            lo, hi = self._bounds[axis]
            if not lo <= value <= hi:
                raise FrameError("range", f"pos.{axis} = {value!r} is outside "
                                          f"[{lo:.6g}, {hi:.6g}]")
        return seq, t, pos

    @property
    def rejected(self) -> int:
        return sum(self.counts.values())
