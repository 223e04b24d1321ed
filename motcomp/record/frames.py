"""Vectorised decoding of recorded msgpack frames into numpy columns.

Decoding a frame with ``msgpack.unpackb`` costs a few microseconds (one Python object per map,
key and number); an hour at 1 kHz holds about ten million frames.  But the frames of one
producer are nearly always byte-for-byte the same *layout* -- same keys in the same order, same
type markers -- and differ only in their values.  So frames are grouped by length, the first
frame of a group is parsed once into a :class:`Layout` (its structural bytes, and the offset and
type of every value), and the whole group is checked and decoded with numpy:

1. gather the group's rows into an ``(n, W)`` byte array (``W`` = length rounded up to 8);
2. keep the rows whose structural bytes equal the template's (compared as 64-bit words under a
   mask) and whose single-byte values are of the template's kind (fixints, booleans);
3. read each value column with a big-endian dtype view (``>f8``, ``>u4``...), strings through
   ``np.unique``.

Rows of another layout are tried against a new template from their own first row (a few times),
and whatever is left -- odd layouts, payloads that are not msgpack -- is decoded one by one
with ``msgpack``, with exactly the same result.  Nothing is guessed: a row is decoded from a
template only if every structural byte matches.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from motcomp.core.axes import AXES, AXIS_INDEX

__all__ = [
    "FLAG_BITS",
    "MODE_BITS",
    "FeedbackColumns",
    "InputColumns",
    "Layout",
    "Leaf",
    "OutputColumns",
    "decode_rows",
    "layout_of",
]

# leaf kinds
F64, F32, UINT, INT, FIXPOS, FIXNEG, STR, BOOL, NIL = range(9)
NUMERIC = frozenset({F64, F32, UINT, INT, FIXPOS, FIXNEG})
INTEGER = frozenset({UINT, INT, FIXPOS, FIXNEG})
MAX_TEMPLATE_BYTES = 2048
"""Longer frames (status maps) are decoded one by one: they are rare."""
_TEMPLATES_PER_LENGTH = 6
_BLOCK_ROWS = 1 << 13


@dataclass(frozen=True)
class Leaf:
    """A value in a layout: where it is and how to read it."""

    path: tuple[Any, ...]
    kind: int
    off: int
    size: int
    dtype: str = ""


@dataclass
class Layout:
    """The structure of one frame: which bytes must match and where the values are."""

    length: int
    template: np.ndarray
    mask: np.ndarray
    leaves: list[Leaf]
    maps: dict[tuple[Any, ...], list[str]]
    """Keys of every map, by path (``()`` is the top level)."""
    lists: dict[tuple[Any, ...], int]
    """Length of every array, by path."""
    cache: dict[Any, Any] = field(default_factory=dict)


class _UnsupportedError(Exception):
    pass


_INT_FMT = {0xCC: (1, ">u1", UINT), 0xCD: (2, ">u2", UINT), 0xCE: (4, ">u4", UINT),
            0xCF: (8, ">u8", UINT), 0xD0: (1, ">i1", INT), 0xD1: (2, ">i2", INT),
            0xD2: (4, ">i4", INT), 0xD3: (8, ">i8", INT)}


class _Walker:
    def __init__(self, data: bytes) -> None:
        self.b = data
        self.mask = np.full(len(data), 0xFF, dtype=np.uint8)
        self.leaves: list[Leaf] = []
        self.maps: dict[tuple[Any, ...], list[str]] = {}
        self.lists: dict[tuple[Any, ...], int] = {}

    def value_bytes(self, o: int, n: int) -> None:
        self.mask[o:o + n] = 0

    def string(self, o: int) -> tuple[int, int]:
        """``(content offset, content length)`` of a string at ``o``."""
        b = self.b[o]
        if 0xA0 <= b <= 0xBF:
            return o + 1, b & 0x1F
        if b == 0xD9:
            return o + 2, self.b[o + 1]
        if b == 0xDA:
            return o + 3, struct.unpack_from(">H", self.b, o + 1)[0]
        if b == 0xDB:
            return o + 5, struct.unpack_from(">I", self.b, o + 1)[0]
        raise _UnsupportedError

    def walk(self, o: int, path: tuple[Any, ...]) -> int:
        b = self.b[o]
        if b <= 0x7F:
            self.value_bytes(o, 1)
            self.leaves.append(Leaf(path, FIXPOS, o, 1))
            return o + 1
        if b >= 0xE0:
            self.value_bytes(o, 1)
            self.leaves.append(Leaf(path, FIXNEG, o, 1))
            return o + 1
        if 0x80 <= b <= 0x8F or b in (0xDE, 0xDF):
            n, o = ((b & 0x0F, o + 1) if b <= 0x8F else
                    (struct.unpack_from(">H", self.b, o + 1)[0], o + 3) if b == 0xDE else
                    (struct.unpack_from(">I", self.b, o + 1)[0], o + 5))
            keys = []
            for _ in range(n):
                start, size = self.string(o)
                key = self.b[start:start + size].decode("utf-8")
                keys.append(key)
                o = self.walk(start + size, (*path, key))
            self.maps[path] = keys
            return o
        if 0x90 <= b <= 0x9F or b in (0xDC, 0xDD):
            n, o = ((b & 0x0F, o + 1) if b <= 0x9F else
                    (struct.unpack_from(">H", self.b, o + 1)[0], o + 3) if b == 0xDC else
                    (struct.unpack_from(">I", self.b, o + 1)[0], o + 5))
            for i in range(n):
                o = self.walk(o, (*path, i))
            self.lists[path] = n
            return o
        if 0xA0 <= b <= 0xBF or b in (0xD9, 0xDA, 0xDB):
            start, size = self.string(o)
            self.value_bytes(start, size)
            self.leaves.append(Leaf(path, STR, start, size))
            return start + size
        if b == 0xC0:
            self.leaves.append(Leaf(path, NIL, o, 0))
            return o + 1
        if b in (0xC2, 0xC3):
            self.value_bytes(o, 1)
            self.leaves.append(Leaf(path, BOOL, o, 1))
            return o + 1
        if b == 0xCB:
            self.value_bytes(o + 1, 8)
            self.leaves.append(Leaf(path, F64, o + 1, 8, ">f8"))
            return o + 9
        if b == 0xCA:
            self.value_bytes(o + 1, 4)
            self.leaves.append(Leaf(path, F32, o + 1, 4, ">f4"))
            return o + 5
        if b in _INT_FMT:
            size, dtype, kind = _INT_FMT[b]
            self.value_bytes(o + 1, size)
            self.leaves.append(Leaf(path, kind, o + 1, size, dtype))
            return o + 1 + size
        raise _UnsupportedError  # bin, ext, reserved


def layout_of(payload: bytes) -> Layout | None:
    """The :class:`Layout` of one frame, or None if it is not a single msgpack object of the
    supported kinds (maps with string keys, arrays, numbers, strings, booleans, nil)."""
    w = _Walker(payload)
    try:
        end = w.walk(0, ())
    except (_UnsupportedError, IndexError, struct.error, UnicodeDecodeError):
        return None
    if end != len(payload):
        return None
    return Layout(len(payload), np.frombuffer(payload, dtype=np.uint8).copy(), w.mask, w.leaves,
                  w.maps, w.lists)


def _leaf_view(g: np.ndarray, leaf: Leaf, dtype: str) -> np.ndarray:
    """A leaf's values in each row of the C-contiguous ``g``, as a strided view (no copy)."""
    return np.ndarray((g.shape[0],), dtype=dtype, buffer=g, offset=leaf.off,
                      strides=(g.strides[0],))


def _column(g: np.ndarray, leaf: Leaf) -> np.ndarray:
    """The values of a numeric leaf in each row of ``g``, as float64 (ints exactly below 2^53)."""
    if leaf.kind == FIXPOS:
        return g[:, leaf.off].astype(np.float64)
    if leaf.kind == FIXNEG:
        return g[:, leaf.off].view(np.int8).astype(np.float64)
    return _leaf_view(g, leaf, leaf.dtype).astype(np.float64)


def _int_column(g: np.ndarray, leaf: Leaf) -> np.ndarray:
    if leaf.kind == FIXPOS:
        return g[:, leaf.off].astype(np.int64)
    if leaf.kind == FIXNEG:
        return g[:, leaf.off].view(np.int8).astype(np.int64)
    return _leaf_view(g, leaf, leaf.dtype).astype(np.int64)


def _map_block(g: np.ndarray, leaves: dict[tuple[Any, ...], Leaf], name: str,
               keys: list[str]) -> np.ndarray:
    """The axis values of the map ``name`` in each row, as an ``(n, 8)`` block (NaN where a
    row's map lacks the axis)."""
    block = np.full((g.shape[0], len(AXES)), np.nan)
    for a in keys:
        block[:, AXIS_INDEX[a]] = _column(g, leaves[(name, a)])
    return block


def _str_column(g: np.ndarray, leaf: Leaf) -> tuple[np.ndarray, list[str]]:
    """``(inverse, uniques)``: row ``i`` holds ``uniques[inverse[i]]``."""
    raw = np.ascontiguousarray(g[:, leaf.off:leaf.off + leaf.size])
    if leaf.size == 0:
        return np.zeros(g.shape[0], dtype=np.int64), [""]
    u, inv = np.unique(raw.view(f"S{leaf.size}")[:, 0], return_inverse=True)
    return inv.ravel(), [bytes(x).ljust(leaf.size, b"\0").decode("utf-8", "replace") for x in u]


class Extractor:
    """Receives decoded rows of one channel: a block from a layout, or a single object."""

    def __init__(self, n: int) -> None:
        self.n = n

    def from_layout(self, layout: Layout, g: np.ndarray, rows: np.ndarray,
                    same: dict[str, np.ndarray]) -> None:
        """Rows ``rows`` (of the extractor) are ``g`` (their bytes); ``same[name]`` tells which
        rows equal the template in the bytes of :meth:`value_masks` ``[name]``."""
        raise NotImplementedError

    def value_masks(self, layout: Layout) -> dict[str, np.ndarray]:
        """Value bytes worth comparing with the template in bulk (see :meth:`from_layout`)."""
        return {}

    def from_object(self, obj: Any, row: int) -> None:
        raise NotImplementedError

    def undecodable(self, row: int, message: str) -> None:
        raise NotImplementedError


def _words(layout: Layout, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The template and its structural mask as 64-bit words over ``width`` bytes (cached)."""
    key = ("words", width)
    cached = layout.cache.get(key)
    if cached is None:
        t = np.zeros(width, dtype=np.uint8)
        t[:layout.length] = layout.template
        m = np.zeros(width, dtype=np.uint8)
        m[:layout.length] = layout.mask
        cached = (t.view("<u8"), m.view("<u8"))
        layout.cache[key] = cached
    return cached


def _matches(g: np.ndarray, layout: Layout) -> tuple[np.ndarray, np.ndarray]:
    """``(ok, x)``: rows whose structure is the layout's, and each row XOR the template (as
    64-bit words, for value comparisons)."""
    t, m = _words(layout, g.shape[1])
    x = np.bitwise_xor(g.view("<u8"), t)
    ok = np.bitwise_or.reduce(x & m, axis=1) == 0
    for leaf in layout.leaves:
        if leaf.kind in (FIXPOS, FIXNEG, BOOL):
            col = g[:, leaf.off]
            if leaf.kind == FIXPOS:
                ok &= col <= 0x7F
            elif leaf.kind == FIXNEG:
                ok &= col >= 0xE0
            else:
                ok &= (col | 1) == 0xC3
    return ok, x


def _same(x: np.ndarray, layout: Layout, ex: Extractor) -> dict[str, np.ndarray]:
    """Per value mask the extractor asks for: rows whose bytes there equal the template's."""
    out = {}
    for name, mask in ex.value_masks(layout).items():
        key = ("vmask", name, x.shape[1])
        words = layout.cache.get(key)
        if words is None:
            m = np.zeros(x.shape[1] * 8, dtype=np.uint8)
            m[:mask.size] = mask
            mw = m.view("<u8")
            cols = np.flatnonzero(mw)
            words = (cols, mw[cols])
            layout.cache[key] = words
        cols, mw = words
        if cols.size:
            out[name] = np.bitwise_or.reduce(x[:, cols] & mw, axis=1) == 0
        else:
            out[name] = np.ones(x.shape[0], dtype=bool)
    return out


def decode_rows(buf: np.ndarray, offset: np.ndarray, length: np.ndarray, ex: Extractor,
                row0: int = 0) -> None:
    """Decode the payloads ``buf[offset[i]:offset[i]+length[i]]`` into ``ex`` (rows
    ``row0 + i``); see the module docstring."""
    if offset.size == 0:
        return
    order = np.argsort(length, kind="stable")
    ls = length[order]
    cuts = np.flatnonzero(np.diff(ls)) + 1
    for grp in np.split(order, cuts):
        size = int(length[grp[0]])
        remaining = grp
        if 0 < size <= MAX_TEMPLATE_BYTES and grp.size >= 4:
            width = (size + 7) // 8 * 8
            view = sliding_window_view(buf, width)
            for _ in range(_TEMPLATES_PER_LENGTH):
                o = int(offset[remaining[0]])
                layout = layout_of(bytes(buf[o:o + size]))
                if layout is None:
                    _one(buf, offset, length, remaining[0], ex, row0)
                    remaining = remaining[1:]
                else:
                    rest = []
                    for start in range(0, remaining.size, _BLOCK_ROWS):
                        block = remaining[start:start + _BLOCK_ROWS]
                        g = view[offset[block]]
                        ok, x = _matches(g, layout)
                        if ok.all():
                            ex.from_layout(layout, g, block + row0, _same(x, layout, ex))
                        else:
                            ex.from_layout(layout, g[ok], block[ok] + row0,
                                           _same(x[ok], layout, ex))
                            rest.append(block[~ok])
                    remaining = np.concatenate(rest) if rest else remaining[:0]
                if remaining.size < 4:
                    break
        for i in remaining:
            _one(buf, offset, length, int(i), ex, row0)


def _one(buf: np.ndarray, offset: np.ndarray, length: np.ndarray, i: int, ex: Extractor,
         row0: int) -> None:
    o = int(offset[i])
    data = bytes(buf[o:o + int(length[i])])
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        ex.undecodable(row0 + int(i), f"not a msgpack frame: {exc}")
        return
    ex.from_object(obj, row0 + int(i))


# --- input frames ---------------------------------------------------------------------------
def _is_number(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


class InputColumns(Extractor):
    """Input frames (``{"seq", "t", "pos"}``) as columns, for analysis (delays, plots, lookup
    of a frame by ``seq``).

    ``decoded[i]``: frame ``i`` is a msgpack map with an integer ``seq`` and a ``pos`` map;
    ``pos[i, a]`` is its value of axis ``a`` if that is a number (NaN otherwise, and where the
    frame does not carry the axis); ``t`` is NaN without a numeric ``t``.  Whether the service
    *accepts* a frame (schema, types, axes, range, sequence) is not decided here: only
    :func:`motcomp.core.tick.parse_input` decides, when the replay's tick reads the frame.
    """

    def __init__(self, n: int) -> None:
        super().__init__(n)
        self.seq = np.zeros(n, dtype=np.int64)
        self.t = np.full(n, np.nan)
        self.pos = np.full((n, len(AXES)), np.nan)
        self.decoded = np.zeros(n, dtype=bool)

    def undecodable(self, row: int, message: str) -> None:
        pass

    def from_layout(self, layout: Layout, g: np.ndarray, rows: np.ndarray,
                    same: dict[str, np.ndarray]) -> None:
        if rows.size == 0:
            return
        leaves = {leaf.path: leaf for leaf in layout.leaves}
        seq = leaves.get(("seq",))
        pos_keys = layout.maps.get(("pos",))
        if seq is None or seq.kind not in INTEGER or pos_keys is None or \
                layout.maps.get(()) is None:
            return
        if seq.dtype == ">u8":  # beyond int64: not decoded (as in from_object)
            small = _leaf_view(g, seq, ">u8") < 2**63
            if not small.all():
                rows, g = rows[small], g[small]
        self.seq[rows] = _int_column(g, seq)
        t_leaf = leaves.get(("t",))
        if t_leaf is not None and t_leaf.kind in NUMERIC:
            self.t[rows] = _column(g, t_leaf)
        keys = [a for a in pos_keys if a in AXIS_INDEX and leaves.get(("pos", a)) is not None
                and leaves[("pos", a)].kind in NUMERIC]
        if keys:
            self.pos[rows] = _map_block(g, leaves, "pos", keys)
        self.decoded[rows] = True

    def from_object(self, obj: Any, row: int) -> None:
        if obj.__class__ is not dict:
            return
        seq, pos = obj.get("seq"), obj.get("pos")
        if seq.__class__ is not int or not -2**63 <= seq < 2**63 or pos.__class__ is not dict:
            return
        self.seq[row] = seq
        t = obj.get("t")
        if isinstance(t, int | float) and not isinstance(t, bool):
            self.t[row] = float(t)
        for a, v in pos.items():
            if a.__class__ is str and a in AXIS_INDEX and _is_number(v):
                self.pos[row, AXIS_INDEX[a]] = float(v)
        self.decoded[row] = True


# --- output frames --------------------------------------------------------------------------
FLAG_BITS: dict[str, int] = {
    **{f"sat:{a}": 1 << i for i, a in enumerate(AXES)},
    **{f"bypass:{a}": 1 << (8 + i) for i, a in enumerate(AXES)},
    "stale": 1 << 16, "rejoin": 1 << 17, "parking": 1 << 18,
    **{f"fallback:{a}": 1 << (24 + i) for i, a in enumerate(AXES)},
    **{f"nopredict:{a}": 1 << (32 + i) for i, a in enumerate(AXES)},
    **{f"envelope:{a}": 1 << (40 + i) for i, a in enumerate(AXES)},
}
"""Bit of each output flag in :attr:`OutputColumns.flags`."""
MODE_BITS = FLAG_BITS["stale"] | FLAG_BITS["rejoin"] | FLAG_BITS["parking"]


def compensation_off(flags: np.ndarray, axis: str, predicts: bool) -> np.ndarray:
    """Per output (its :data:`FLAG_BITS`): whether ``axis`` went uncompensated -- its PID
    bypassed and, on an axis whose config predicts it (``predicts``), its prediction off too
    (``nopredict`` or ``fallback``): the reference reached the limiter as it came.  (A
    delay-dominated axis runs with its PID bypassed and its prediction on: compensated.)"""
    off = (flags & FLAG_BITS[f"bypass:{axis}"]) != 0
    if predicts:
        off &= (flags & (FLAG_BITS[f"nopredict:{axis}"] | FLAG_BITS[f"fallback:{axis}"])) != 0
    return np.asarray(off)


class _FramesBase(Extractor):
    fields: tuple[str, ...] = ()
    maps: tuple[str, ...] = ()

    def __init__(self, n: int) -> None:
        super().__init__(n)
        self.valid = np.zeros(n, dtype=bool)
        for f in self.fields:
            setattr(self, f, np.full(n, np.nan))
        for m in self.maps:
            setattr(self, m, np.full((n, len(AXES)), np.nan))
        self.bad = 0

    def undecodable(self, row: int, message: str) -> None:
        self.bad += 1

    def _extra(self, layout: Layout, g: np.ndarray, rows: np.ndarray,
               leaves: dict[tuple[Any, ...], Leaf], same: dict[str, np.ndarray]) -> None:
        pass

    def _extra_obj(self, obj: dict[str, Any], row: int) -> None:
        pass

    def from_layout(self, layout: Layout, g: np.ndarray, rows: np.ndarray,
                    same: dict[str, np.ndarray]) -> None:
        if rows.size == 0:
            return
        leaves = {leaf.path: leaf for leaf in layout.leaves}
        top = layout.maps.get(())
        if top is None or any(
                (f,) not in leaves or leaves[(f,)].kind not in NUMERIC for f in self.fields):
            self.bad += rows.size
            return
        for f in self.fields:
            getattr(self, f)[rows] = _column(g, leaves[(f,)])
        for m in self.maps:
            keys = [a for a in layout.maps.get((m,), []) if a in AXIS_INDEX and
                    leaves.get((m, a)) is not None and leaves[(m, a)].kind in NUMERIC]
            if keys:
                getattr(self, m)[rows] = _map_block(g, leaves, m, keys)
        self._extra(layout, g, rows, leaves, same)
        self.valid[rows] = True

    def from_object(self, obj: Any, row: int) -> None:
        if not isinstance(obj, dict) or not all(_is_number(obj.get(f)) for f in self.fields):
            self.bad += 1
            return
        for f in self.fields:
            getattr(self, f)[row] = float(obj[f])
        for m in self.maps:
            d = obj.get(m)
            if isinstance(d, dict):
                for a, v in d.items():
                    if a in AXIS_INDEX and _is_number(v):
                        getattr(self, m)[row, AXIS_INDEX[a]] = float(v)
        self._extra_obj(obj, row)
        self.valid[row] = True


class OutputColumns(_FramesBase):
    """Output frames (``{"seq", "t", "src_seq", "pos", "flags", "rx"?}``) as columns; ``flags``
    as a bit field (:data:`FLAG_BITS`), ``rx`` (ns; 0 where absent) as an integer column."""

    fields = ("seq", "t", "src_seq")
    maps = ("pos",)
    seq: np.ndarray
    t: np.ndarray
    src_seq: np.ndarray
    pos: np.ndarray

    def __init__(self, n: int) -> None:
        super().__init__(n)
        self.flags = np.zeros(n, dtype=np.int64)
        self.rx = np.zeros(n, dtype=np.int64)

    def value_masks(self, layout: Layout) -> dict[str, np.ndarray]:
        mask = np.zeros(layout.length, dtype=np.uint8)
        for leaf in layout.leaves:
            if leaf.path[:1] == ("flags",) and leaf.kind == STR:
                mask[leaf.off:leaf.off + leaf.size] = 0xFF
        return {"flags": mask}

    def _extra(self, layout: Layout, g: np.ndarray, rows: np.ndarray,
               leaves: dict[tuple[Any, ...], Leaf], same: dict[str, np.ndarray]) -> None:
        rx = leaves.get(("rx",))
        if rx is not None and rx.kind in INTEGER and rx.dtype != ">u8":
            self.rx[rows] = _int_column(g, rx)
        strs = [leaves[("flags", i)] for i in range(layout.lists.get(("flags",), 0))
                if leaves.get(("flags", i)) is not None and leaves[("flags", i)].kind == STR]
        if not strs:
            return
        # rows carrying the template's flags (nearly all): its bits; the others flag by flag
        mine = 0
        for leaf in strs:
            text = bytes(layout.template[leaf.off:leaf.off + leaf.size]).decode("utf-8",
                                                                             "replace")
            mine |= FLAG_BITS.get(text, 0)
        eq = same["flags"]
        bits = np.where(eq, mine, 0).astype(np.int64)
        other = np.flatnonzero(~eq)
        if other.size:
            sub = g[other]
            for leaf in strs:
                inv, uniq = _str_column(sub, leaf)
                table = np.array([FLAG_BITS.get(u, 0) for u in uniq], dtype=np.int64)
                bits[other] |= table[inv]
        self.flags[rows] |= bits

    def _extra_obj(self, obj: dict[str, Any], row: int) -> None:
        rx = obj.get("rx")
        if rx.__class__ is int and 0 <= rx < 2**63:
            self.rx[row] = rx
        flags = obj.get("flags")
        if isinstance(flags, list):
            bits = 0
            for s in flags:
                bits |= FLAG_BITS.get(s, 0) if isinstance(s, str) else 0
            self.flags[row] = bits


class FeedbackColumns(_FramesBase):
    """Feedback frames (``{"t", "pos", "acc"}``) as columns (``acc`` left NaN unless
    asked for)."""

    fields = ("t",)
    maps: tuple[str, ...] = ("pos", "acc")
    t: np.ndarray
    pos: np.ndarray
    acc: np.ndarray

    def __init__(self, n: int, acc: bool = True) -> None:
        super().__init__(n)
        if not acc:
            self.maps = ("pos",)


def seconds_to_ns(t: float) -> int | None:
    """A frame's ``t`` (s) as integer ns, or None if it is not a usable time."""
    if not _is_number(t) or not math.isfinite(t) or t < 0 or t > 1e10:
        return None
    return round(t * 1e9)


def frame_time_and_seq(payload: bytes) -> tuple[int | None, int | None]:
    """``(t in ns, seq)`` of a frame, each None when absent or not usable (recorder side)."""
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception:  # not msgpack: recorded as is
        return None, None
    if not isinstance(obj, dict):
        return None, None
    t = obj.get("t")
    seq = obj.get("seq")
    return (seconds_to_ns(t) if t is not None else None,
            seq if isinstance(seq, int) and not isinstance(seq, bool) else None)


Decoder = Callable[[int], Extractor]
