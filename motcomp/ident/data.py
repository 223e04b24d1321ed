"""Identification data: one axis' command and measured acceleration on a uniform time grid.

Loaders
-------
A loader turns a file into a :class:`RawRecording` (time stamps, command, acceleration, as
recorded); it is chosen by the file's suffix from a registry, so a new recording format is one
function decorated with :func:`register_loader`:

``.csv``
    A header row with the columns ``t`` (s), ``cmd`` (commanded position, m or rad) and ``acc``
    (measured cabin acceleration, m/s^2 or rad/s^2); other columns are ignored.  Lines starting
    with ``#`` before the header are comments; ``# axis: NAME`` names the axis.
``.mcap``
    A session recording of the service: one channel per zenoh key, msgpack messages.  The
    command comes from ``sim/motion/setpoint`` frames ``{"seq", "t", "pos": {axis: value}}``, the
    acceleration from ``platform/feedback`` frames ``{"t", "pos": {...}, "acc": {...}}``.  Time
    stamps are the recorder's log times (one clock for both) unless ``clock="frame"`` asks for
    the frames' own ``t``.

Checks (each a :class:`~motcomp.errors.DataError` naming the place and the value)
---------------------------------------------------------------------------------
missing or misnamed columns; a value that is not a number, NaN or infinite (line and column);
time going backwards or repeated (line); a gap of more than 5 median periods; fewer than
:data:`MIN_SAMPLES` samples; a constant command (nothing excited); a measurement sitting at its
extreme value for several samples in a row (sensor saturated or clipped).

Resampling
----------
A recording whose periods vary by more than 0.1 % is resampled onto the uniform grid
``t0 + k / rate`` (``rate`` = the mean sample rate, rounded to whole hertz when within 0.1 %,
unless given) by linear interpolation of both columns.  Linear interpolation suits both: the
command's samples are points of the setpoint sequence that the platform holds, and holding a
sequence of points lags it by half a period *whatever the grid*, a lag the fit's
zero-order-hold model adds back.

The accelerometer's bias is not removed here: the fit estimates it as a free constant (see
:mod:`motcomp.ident.fit`).
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from motcomp.core.axes import AXIS_INDEX
from motcomp.core.lti import FloatArray
from motcomp.errors import DataError

__all__ = [
    "FEEDBACK_KEY",
    "LOADERS",
    "MIN_SAMPLES",
    "SETPOINT_KEY",
    "RawRecording",
    "Recording",
    "check_and_resample",
    "list_axes",
    "load_recording",
    "register_loader",
    "write_recording_csv",
]

MIN_SAMPLES = 1000
"""Fewest samples accepted (1 s at 1 kHz): the fit needs many periods of the slowest dynamics."""

SETPOINT_KEY = "sim/motion/setpoint"
FEEDBACK_KEY = "platform/feedback"


@dataclass(frozen=True)
class RawRecording:
    """A recording as read: its own time stamps, possibly irregular.

    ``t_cmd`` may differ from ``t_acc`` (two streams, e.g. setpoints and feedback); ``rows``
    maps each sample to the place it came from (a line number, a message index) for messages.
    """

    source: str
    t_acc: FloatArray
    acc: FloatArray
    t_cmd: FloatArray
    cmd: FloatArray
    axis: str | None = None
    acc_place: Callable[[int], str] = field(default=lambda i: f"sample {i}")
    cmd_place: Callable[[int], str] = field(default=lambda i: f"sample {i}")


@dataclass(frozen=True)
class Recording:
    """One axis on a uniform grid: ``t[k] = k / rate_hz`` (starting at 0)."""

    t: FloatArray
    cmd: FloatArray
    acc: FloatArray
    rate_hz: float
    axis: str | None
    source: str
    resampled: bool = False
    period_jitter_s: float = 0.0
    """Standard deviation of the recorded periods (0 for a regular record)."""

    @property
    def n(self) -> int:
        return int(self.t.size)

    @property
    def duration_s(self) -> float:
        return self.n / self.rate_hz


Loader = Callable[[Path, str | None, str], RawRecording]
LOADERS: dict[str, Loader] = {}


def register_loader(*suffixes: str) -> Callable[[Loader], Loader]:
    """Register ``func(path, axis, clock) -> RawRecording`` for file suffixes like ``.csv``."""
    def deco(func: Loader) -> Loader:
        for s in suffixes:
            LOADERS[s.lower()] = func
        return func
    return deco


def load_recording(path: str | Path, axis: str | None = None, rate_hz: float | None = None,
                   clock: str = "log") -> Recording:
    """Read, check and (if irregular) resample a recording.

    Raises
    ------
    DataError
        For an unreadable file, an unknown suffix or any failed check (see the module notes).
    """
    p = Path(path)
    loader = LOADERS.get(p.suffix.lower())
    if loader is None:
        raise DataError(f"{p}: unknown data format {p.suffix or '(no suffix)'!r}; readable: "
                        f"{', '.join(sorted(LOADERS))}")
    if not p.is_file():
        raise DataError(f"{p}: no such file")
    if axis is not None and axis not in AXIS_INDEX:
        raise DataError(f"unknown axis {axis!r}; axes are {', '.join(AXIS_INDEX)}")
    raw = loader(p, axis, clock)
    return check_and_resample(raw, rate_hz)


# --- checks and resampling ----------------------------------------------------------------------

def _check_time(t: FloatArray, place: Callable[[int], str], src: str, what: str) -> None:
    d = np.diff(t)
    bad = np.nonzero(d <= 0)[0]
    if bad.size:
        i = int(bad[0]) + 1
        if d[i - 1] == 0:
            raise DataError(f"{src}: {place(i)}: column t: repeated time {t[i]:.9g} s "
                            f"(same as the previous {what})")
        raise DataError(f"{src}: {place(i)}: column t: time goes backwards ({t[i]:.9g} s after "
                        f"{t[i - 1]:.9g} s)")
    if d.size:
        med = float(np.median(d))
        gaps = np.nonzero(d > 5.0 * med)[0]
        if gaps.size:
            i = int(gaps[0]) + 1
            raise DataError(f"{src}: {place(i)}: column t: gap of {d[i - 1]:.6g} s without data "
                            f"(median period {med:.6g} s)")


def _check_finite(x: FloatArray, col: str, place: Callable[[int], str], src: str) -> None:
    bad = np.nonzero(~np.isfinite(x))[0]
    if bad.size:
        i = int(bad[0])
        raise DataError(f"{src}: {place(i)}: column {col}: value {float(x[i])!r} is not a finite "
                        "number")


def _check_clipped(x: FloatArray, col: str, place: Callable[[int], str], src: str) -> None:
    """A sensor at its range end reads the same extreme value sample after sample."""
    for extreme, word in ((float(np.max(x)), "maximum"), (float(np.min(x)), "minimum")):
        at = x == extreme
        if at.sum() < 5:
            continue
        # longest run at the extreme
        edges = np.diff(np.concatenate([[0], at.astype(np.int8), [0]]))
        starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
        lengths = ends - starts
        j = int(np.argmax(lengths))
        if lengths[j] >= 5:
            raise DataError(
                f"{src}: {place(int(starts[j]))}: column {col}: measurement clipped or saturated: "
                f"{int(lengths[j])} samples in a row at its {word} {extreme:.6g} "
                f"({int(at.sum())} in all)")


def check_and_resample(raw: RawRecording, rate_hz: float | None = None) -> Recording:
    """Check a raw recording and put it on a uniform grid.

    Raises
    ------
    DataError
        Naming the problem, the place (line or message) and the value.
    """
    src = raw.source
    for x, col, place in ((raw.t_acc, "t", raw.acc_place), (raw.acc, "acc", raw.acc_place),
                          (raw.t_cmd, "t", raw.cmd_place), (raw.cmd, "cmd", raw.cmd_place)):
        _check_finite(x, col, place, src)
    n = min(raw.t_acc.size, raw.t_cmd.size)
    if n < MIN_SAMPLES:
        raise DataError(f"{src}: only {n} samples; at least {MIN_SAMPLES} are needed")
    _check_time(raw.t_acc, raw.acc_place, src, "sample")
    if raw.t_cmd is not raw.t_acc:
        _check_time(raw.t_cmd, raw.cmd_place, src, "setpoint")
    span = float(np.ptp(raw.cmd))
    scale = max(float(np.max(np.abs(raw.cmd))), 1.0)
    if span <= 1e-12 * scale:
        raise DataError(f"{src}: column cmd: the command is constant ({raw.cmd[0]:.6g} on every "
                        "sample): nothing was excited")
    _check_clipped(raw.acc, "acc", raw.acc_place, src)

    d = np.diff(raw.t_acc)
    med = float(np.median(d))
    jitter = float(np.std(d))
    if rate_hz is None:
        rate = (raw.t_acc.size - 1) / float(raw.t_acc[-1] - raw.t_acc[0])  # the mean rate
        # 1000.07 Hz from jittered stamps is 1 kHz; a regular record keeps its own rate
        same = raw.t_cmd is raw.t_acc
        tol = 1e-6 if same and float(np.max(np.abs(d - med))) <= 1e-3 * med else 1e-3
        if abs(rate - round(rate)) <= tol * rate:
            rate = float(round(rate))
    else:
        rate = float(rate_hz)
    if not (math.isfinite(rate) and rate > 0):
        raise DataError(f"{src}: resampling rate must be a positive number, got {rate!r}")
    same_grid = raw.t_cmd is raw.t_acc or (
        raw.t_cmd.size == raw.t_acc.size and bool(np.all(raw.t_cmd == raw.t_acc)))
    regular = same_grid and float(np.max(np.abs(d - med))) <= 1e-3 * med and (
        abs(rate * med - 1.0) < 1e-6)
    # (a regular record: every period within 0.1 % of the median, and the rate its own)
    if regular:
        t = raw.t_acc - raw.t_acc[0]
        return Recording(t=t, cmd=raw.cmd.copy(), acc=raw.acc.copy(), rate_hz=rate,
                         axis=raw.axis, source=src, resampled=False, period_jitter_s=jitter)
    t0 = max(float(raw.t_acc[0]), float(raw.t_cmd[0]))
    t1 = min(float(raw.t_acc[-1]), float(raw.t_cmd[-1]))
    n_new = math.floor((t1 - t0) * rate + 1e-9) + 1
    if n_new < MIN_SAMPLES:
        raise DataError(f"{src}: only {n_new} samples after resampling at {rate:.6g} Hz over the "
                        f"common span {t1 - t0:.6g} s; at least {MIN_SAMPLES} are needed")
    grid = t0 + np.arange(n_new) / rate
    cmd = np.interp(grid, raw.t_cmd, raw.cmd)
    acc = np.interp(grid, raw.t_acc, raw.acc)
    return Recording(t=grid - t0, cmd=cmd, acc=acc, rate_hz=rate, axis=raw.axis, source=src,
                     resampled=True, period_jitter_s=jitter)


# --- CSV ----------------------------------------------------------------------------------------

_AXIS_COMMENT = re.compile(r"^#\s*axis\s*[:=]\s*([A-Za-z_]+)\s*$")
REQUIRED = ("t", "cmd", "acc")


@register_loader(".csv")
def _load_csv(path: Path, axis: str | None, clock: str) -> RawRecording:
    src = str(path)
    file_axis: str | None = None
    try:
        fh = open(path, newline="")  # noqa: SIM115 - closed by the with below
    except OSError as exc:
        raise DataError(f"{src}: cannot read: {exc.strerror}") from None
    with fh:
        reader = csv.reader(fh)
        header: list[str] | None = None
        line = 0
        for row in reader:
            line = reader.line_num
            if not row or not "".join(row).strip():
                continue
            if row[0].lstrip().startswith("#"):
                m = _AXIS_COMMENT.match(",".join(row).strip())
                if m:
                    file_axis = m.group(1)
                continue
            header = [c.strip() for c in row]
            break
        if header is None:
            raise DataError(f"{src}: empty file: expected a header line 't,cmd,acc'")
        missing = [c for c in REQUIRED if c not in header]
        if missing:
            hints = []
            lowered = {h.lower(): h for h in header}
            for c in missing:
                near = lowered.get(c) or next((h for h in header if h.lower().startswith(c)),
                                              None)
                hints.append(f"{c!r}" + (f" (found {near!r})" if near else ""))
            raise DataError(f"{src}:{line}: missing column(s) {', '.join(hints)}; the header "
                            f"must name t, cmd and acc; found: {', '.join(header)}")
        dup = [c for c in REQUIRED if header.count(c) > 1]
        if dup:
            raise DataError(f"{src}:{line}: column {dup[0]!r} appears twice in the header")
        idx = [header.index(c) for c in REQUIRED]
        width = max(idx) + 1
        values: list[list[float]] = [[], [], []]
        lines: list[int] = []
        for row in reader:
            if not row or not "".join(row).strip():
                continue
            ln = reader.line_num
            if len(row) < width:
                raise DataError(f"{src}:{ln}: {len(row)} field(s); column "
                                f"{header[width - 1]!r} is missing on this line")
            for j, (col, i) in enumerate(zip(REQUIRED, idx, strict=True)):
                text = row[i].strip()
                try:
                    values[j].append(float(text))
                except ValueError:
                    raise DataError(f"{src}:{ln}: column {col}: {text!r} is not a number"
                                    ) from None
            lines.append(ln)
    if file_axis is not None and file_axis not in AXIS_INDEX:
        raise DataError(f"{src}: '# axis' comment names an unknown axis {file_axis!r}")
    t = np.asarray(values[0], dtype=float)
    line_arr = np.asarray(lines, dtype=np.int64)

    def place(i: int) -> str:
        return f"line {int(line_arr[i])}" if 0 <= i < line_arr.size else f"sample {i}"
    return RawRecording(source=src, t_acc=t, acc=np.asarray(values[2], dtype=float), t_cmd=t,
                        cmd=np.asarray(values[1], dtype=float), axis=axis or file_axis,
                        acc_place=place, cmd_place=place)


def write_recording_csv(path: str | Path, t: FloatArray, cmd: FloatArray, acc: FloatArray,
                        axis: str | None = None) -> None:
    """Write ``t,cmd,acc`` (with ``# axis: NAME`` first if given), full precision, through a
    temporary file (never half a file)."""
    from motcomp.ident.excitation import atomic_write

    def _w(fh: Any) -> None:
        if axis:
            fh.write(f"# axis: {axis}\n")
        fh.write("t,cmd,acc\n")
        for row in zip(t, cmd, acc, strict=True):
            fh.write(f"{row[0]:.9f},{row[1]:.12g},{row[2]:.12g}\n")
    atomic_write(Path(path), _w, "w")


# --- MCAP session recordings --------------------------------------------------------------------

Rows = list[tuple[float, dict[str, Any], int]]
_MCAP_CACHE: dict[tuple[str, int, str], tuple[Rows, Rows]] = {}


def _read_mcap(path: Path, clock: str) -> tuple[Rows, Rows]:
    """``(setpoints, feedback)`` as ``(time, frame, message index)``; the last file read is
    kept, so that several axes of one recording are read once."""
    import msgpack
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    src = str(path)
    if clock not in ("log", "frame"):
        raise DataError(f"clock must be 'log' or 'frame', got {clock!r}")
    key = (str(path.resolve()), path.stat().st_mtime_ns, clock)
    if key in _MCAP_CACHE:
        return _MCAP_CACHE[key]
    sp: Rows = []
    fb: Rows = []
    try:
        with open(path, "rb") as fh:
            reader = make_reader(fh)
            for _schema, channel, message in reader.iter_messages(
                    topics=[SETPOINT_KEY, FEEDBACK_KEY]):
                target = sp if channel.topic == SETPOINT_KEY else fb
                index = len(target)
                where = f"{channel.topic} message {index}"
                if channel.message_encoding != "msgpack":
                    raise DataError(f"{src}: channel {channel.topic}: message encoding "
                                    f"{channel.message_encoding!r}, expected 'msgpack'")
                try:
                    obj = msgpack.unpackb(message.data, raw=False)
                except (ValueError, msgpack.UnpackException) as exc:
                    raise DataError(f"{src}: {where}: not msgpack ({exc})") from None
                if not isinstance(obj, dict):
                    raise DataError(f"{src}: {where}: not a map")
                if clock == "log":
                    stamp = message.log_time * 1e-9
                else:
                    frame_t = obj.get("t")
                    if not isinstance(frame_t, int | float) or isinstance(frame_t, bool):
                        raise DataError(f"{src}: {where}: t is {frame_t!r}, not a number")
                    stamp = float(frame_t)
                target.append((float(stamp), obj, index))
    except (McapError, OSError, EOFError) as exc:
        raise DataError(f"{src}: not a readable MCAP file ({exc})") from None
    for name, got in ((SETPOINT_KEY, sp), (FEEDBACK_KEY, fb)):
        if not got:
            raise DataError(f"{src}: no messages on channel {name}")
    _MCAP_CACHE.clear()
    _MCAP_CACHE[key] = (sp, fb)
    return sp, fb


def _moving_axes(sp: Rows) -> dict[str, float]:
    """Span of the command of every known axis in the setpoint frames."""
    spans: dict[str, list[float]] = {}
    for _, obj, _ in sp:
        pos = obj.get("pos")
        if isinstance(pos, dict):
            for name, value in pos.items():
                if isinstance(value, int | float) and not isinstance(value, bool):
                    spans.setdefault(name, []).append(float(value))
    return {a: float(np.ptp(v)) for a, v in spans.items() if a in AXIS_INDEX}


AxisLister = Callable[[Path, str], list[str]]
AXIS_LISTERS: dict[str, AxisLister] = {}
"""Per suffix, ``func(path, clock) -> axes that move``, for formats holding several axes."""


def list_axes(path: str | Path, clock: str = "log") -> list[str]:
    """The axes a recording excites (in the order of :data:`motcomp.core.axes.AXES`); a format
    holding one axis (CSV) gives ``[]``: the caller names it."""
    p = Path(path)
    lister = AXIS_LISTERS.get(p.suffix.lower())
    if lister is None or not p.is_file():
        return []
    return lister(p, clock)


def _list_mcap(path: Path, clock: str) -> list[str]:
    sp, _ = _read_mcap(path, clock)
    moving = _moving_axes(sp)
    return [a for a in AXIS_INDEX if moving.get(a, 0.0) > 0.0]


AXIS_LISTERS[".mcap"] = _list_mcap


@register_loader(".mcap")
def _load_mcap(path: Path, axis: str | None, clock: str) -> RawRecording:
    src = str(path)
    sp, fb = _read_mcap(path, clock)
    # the axis: given, or the one whose command moves most
    if axis is None:
        moving = _moving_axes(sp)
        if not moving:
            raise DataError(f"{src}: {SETPOINT_KEY}: no frame has a pos map with a known axis")
        axis = max(moving, key=lambda a: moving[a])

    def column(rows: Rows, key: str, topic: str) -> tuple[FloatArray, FloatArray, list[int]]:
        ts, vs, idx = [], [], []
        for stamp, obj, index in rows:
            block = obj.get(key)
            if not isinstance(block, dict):
                raise DataError(f"{src}: {topic} message {index}: no {key!r} map")
            if axis not in block:
                continue  # a frame that does not command this axis
            value = block[axis]
            if not isinstance(value, int | float) or isinstance(value, bool):
                raise DataError(f"{src}: {topic} message {index}: {key}.{axis} is {value!r}")
            ts.append(stamp)
            vs.append(float(value))
            idx.append(index)
        if not ts:
            raise DataError(f"{src}: {topic}: no message carries {key}.{axis}")
        return np.asarray(ts), np.asarray(vs), idx

    t_cmd, cmd, i_cmd = column(sp, "pos", SETPOINT_KEY)
    t_acc, acc, i_acc = column(fb, "acc", FEEDBACK_KEY)
    t0 = min(float(t_cmd[0]), float(t_acc[0]))
    return RawRecording(
        source=src, t_acc=t_acc - t0, acc=acc, t_cmd=t_cmd - t0, cmd=cmd, axis=axis,
        acc_place=lambda i: f"{FEEDBACK_KEY} message {i_acc[i] if i < len(i_acc) else i}",
        cmd_place=lambda i: f"{SETPOINT_KEY} message {i_cmd[i] if i < len(i_cmd) else i}")
