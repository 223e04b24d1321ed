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
    A session recording of the stack (``motcomp record``), read with
    :func:`motcomp.record.read_session` (rotated parts; a file cut short up to its last complete
    chunk, with a warning).  What the platform received against what it did: at each
    ``platform/feedback`` sample, the command is the service's output in force
    (``platform/setpoint``, :meth:`~motcomp.record.Session.identification_columns`) and the
    measurement the feedback's acceleration; each sample also says whether the axis was
    bypassed (``bypass:<axis>``) and whether the limiter acted (``sat:<axis>``).  Time stamps
    are the frames' own ``t`` (``clock="frame"``: the service's tick time and the platform's
    measurement time) or the recorder's receive times (``clock="log"``).

Window (:func:`select_window`)
------------------------------
Time is counted from the recording's start.  A window given as ``(start_s, end_s)`` is used as
is, with a warning if the axis was compensated or limited in it.  Otherwise a recording with
bypass and limiter flags (MCAP) is identified on the longest stretch where the axis is
bypassed and not limited (at least :data:`MIN_WINDOW_S`), searched inside ``within`` if given
(an identification run's excitation); a recording without them (CSV) whole, or ``within``.

Gaps
----
An interval longer than twice the median period is a gap.  Up to ``max_gap_s`` it is bridged
and counted (:class:`Gaps`): the measurement by the linear interpolation of the resampling, the
command by its known values at the missing samples when the loader knows them
(:attr:`RawRecording.cmd_at`: the outputs in force), else linearly too.  A longer gap ends a
stretch (automatic window) or is an error naming it.

Checks (each a :class:`~motcomp.errors.DataError` naming the place and the value)
---------------------------------------------------------------------------------
missing or misnamed columns; a value that is not a number, NaN or infinite (line and column);
time going backwards or repeated (line); a gap longer than ``max_gap_s`` in the window; fewer
than :data:`MIN_SAMPLES` samples; a constant command (nothing excited); a measurement sitting
at its extreme value for several samples in a row (sensor saturated or clipped).

Resampling
----------
A recording whose periods vary by more than 0.1 % (or has gaps) is resampled onto the uniform
grid ``t0 + k / rate`` (``rate`` = the mean sample rate outside the gaps, rounded to whole
hertz when within 0.1 %, unless given) by linear interpolation of both columns.  Linear
interpolation suits both: the command's samples are points of the setpoint sequence that the
platform holds, and holding a sequence of points lags it by half a period *whatever the grid*,
a lag the fit's zero-order-hold model adds back.

The accelerometer's bias is not removed here: the fit estimates it as a free constant (see
:mod:`motcomp.ident.fit`).
"""

from __future__ import annotations

import contextlib
import csv
import itertools
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from motcomp.core.axes import AXIS_INDEX
from motcomp.core.lti import FloatArray
from motcomp.errors import DataError
from motcomp.runtime.clock import DEGRADED_MISSED_SHARE

if TYPE_CHECKING:
    from motcomp.record.session import Session

__all__ = [
    "DEFAULT_MAX_GAP_S",
    "FEEDBACK_KEY",
    "LOADERS",
    "MIN_SAMPLES",
    "MIN_WINDOW_S",
    "OUTPUT_KEY",
    "SETPOINT_KEY",
    "Gaps",
    "RawRecording",
    "Recording",
    "Window",
    "check_and_resample",
    "list_axes",
    "load_recording",
    "register_loader",
    "select_window",
    "spectrum_tops",
    "write_recording_csv",
]

MIN_SAMPLES = 1000
"""Fewest samples accepted (1 s at 1 kHz): the fit needs many periods of the slowest dynamics."""
MIN_WINDOW_S = 5.0
"""Shortest stretch (s) the automatic window accepts."""
DEFAULT_MAX_GAP_S = 0.05
"""Longest gap (s) bridged by interpolation unless told otherwise."""

SETPOINT_KEY = "sim/motion/setpoint"
OUTPUT_KEY = "platform/setpoint"
FEEDBACK_KEY = "platform/feedback"


@dataclass(frozen=True)
class RawRecording:
    """A recording as read: its own time stamps (s from the recording's start), possibly
    irregular.

    ``t_cmd`` may differ from ``t_acc`` (two streams, e.g. setpoints and feedback); the places
    name each sample's origin (a line number, a message index) for messages.  ``bypassed`` and
    ``limited`` (per ``t_acc`` sample, or None when the format does not say) tell whether the
    axis was in bypass and whether the limiter acted; ``warnings`` are the reader's.  Without
    ``cmd_at``, the command is interpolated linearly between its samples.
    """

    source: str
    t_acc: FloatArray
    acc: FloatArray
    t_cmd: FloatArray
    cmd: FloatArray
    axis: str | None = None
    acc_place: Callable[[int], str] = field(default=lambda i: f"sample {i}")
    cmd_place: Callable[[int], str] = field(default=lambda i: f"sample {i}")
    bypassed: np.ndarray | None = None
    limited: np.ndarray | None = None
    warnings: tuple[str, ...] = ()
    cmd_at: Callable[[FloatArray], tuple[FloatArray, np.ndarray]] | None = None
    """The command at any times (the output in force) and whether it is known there: fills
    the measurement's gaps, where the command is known (when the samples share one time
    array), instead of interpolating it across them."""
    band_hz: float | None = None
    """The top of the excitation's band, from the reference the platform was asked to follow
    (a recording's input stream), if the format holds it."""
    within_hint: tuple[float, float] | None = None
    """Where the excitation lies (s from the recording's start), if the recording says so
    (``identify --live`` writes it): the automatic window's bounds unless ``within`` is given."""
    conditions_at: Callable[[float, float], dict[str, Any]] | None = None
    """The run's conditions over a window (s from the recording's start), if the recording
    holds them: :func:`run_conditions`."""


@dataclass(frozen=True)
class Window:
    """The stretch of a recording identified: ``[start_s, end_s]`` from its start."""

    start_s: float
    end_s: float
    samples: int
    """Recorded samples (of the measurement) in it."""
    how: str
    """``"given"``, ``"whole recording"`` or ``"longest stretch bypassed and not limited"``
    (followed by ``" inside START-END s"`` when searched inside bounds)."""


@dataclass(frozen=True)
class Gaps:
    """Gaps bridged by interpolation: intervals longer than twice the median period and not
    longer than ``max_gap_s``."""

    max_gap_s: float = DEFAULT_MAX_GAP_S
    count: int = 0
    longest_s: float = 0.0
    total_s: float = 0.0
    """Time without data, summed over the gaps."""
    first: tuple[tuple[float, float], ...] = ()
    """``(start_s, length_s)`` of the first few, from the recording's start."""

    def to_json(self) -> dict[str, Any]:
        return {"count": self.count, "longest_ms": self.longest_s * 1e3,
                "total_ms": self.total_s * 1e3, "max_gap_s": self.max_gap_s,
                "first": [{"start_s": a, "length_ms": b * 1e3} for a, b in self.first]}


@dataclass(frozen=True)
class Recording:
    """One axis on a uniform grid: ``t[k] = k / rate_hz`` (starting at 0, which is
    ``start_s`` in the recording)."""

    t: FloatArray
    cmd: FloatArray
    acc: FloatArray
    rate_hz: float
    axis: str | None
    source: str
    resampled: bool = False
    period_jitter_s: float = 0.0
    """Standard deviation of the recorded periods outside gaps (0 for a regular record)."""
    start_s: float = 0.0
    window: Window | None = None
    gaps: Gaps = field(default_factory=Gaps)
    warnings: tuple[str, ...] = ()
    """The reader's and the window's (a file cut short, compensation in a given window...)."""
    band_hz: float | None = None
    """See :attr:`RawRecording.band_hz`; it sets the fit's prefilter (:func:`prepare`)."""
    conditions: dict[str, Any] = field(default_factory=dict)
    """How the run went over the window (:func:`run_conditions`; empty if unknown)."""

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
                   clock: str = "frame", window: tuple[float, float] | None = None,
                   max_gap_s: float = DEFAULT_MAX_GAP_S,
                   within: tuple[float, float] | None = None) -> Recording:
    """Read, check, window and (if irregular) resample a recording.

    ``window`` is ``(start_s, end_s)`` from the recording's start (default: see the module
    notes), ``within`` the bounds the automatic window is searched in; ``max_gap_s`` the
    longest gap bridged by interpolation.

    Raises
    ------
    DataError
        For an unreadable file, an unknown suffix, no usable window or any failed check (see
        the module notes).
    """
    p = Path(path)
    loader = LOADERS.get(p.suffix.lower())
    if loader is None:
        raise DataError(f"{p}: unknown data format {p.suffix or '(no suffix)'!r}; readable: "
                        f"{', '.join(sorted(LOADERS))}")
    if not p.is_file() and p.suffix.lower() not in AXIS_LISTERS:  # rotated parts of a session
        raise DataError(f"{p}: no such file")
    if axis is not None and axis not in AXIS_INDEX:
        raise DataError(f"unknown axis {axis!r}; axes are {', '.join(AXIS_INDEX)}")
    raw = loader(p, axis, clock)
    return check_and_resample(raw, rate_hz, max_gap_s=max_gap_s, window=window, within=within)


# --- checks, window and resampling --------------------------------------------------------------

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


def _gap_threshold(t: FloatArray) -> float:
    """Intervals longer than this are gaps: twice the median period."""
    return 2.0 * float(np.median(np.diff(t))) if t.size > 1 else math.inf


def _long_gap_error(t: FloatArray, i: int, place: Callable[[int], str], src: str,
                    max_gap_s: float) -> DataError:
    """The gap between samples ``i`` and ``i + 1``, longer than ``max_gap_s``."""
    d = float(t[i + 1] - t[i])
    med = float(np.median(np.diff(t)))
    return DataError(f"{src}: {place(i + 1)}: column t: gap of {d:.4g} s without data at "
                     f"{t[i]:.6g} s (median period {med:.3g} s; longer than --max-gap "
                     f"{max_gap_s:g} s)")


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


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[start, end)`` of every run of True."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(),
                    strict=True))


def select_window(raw: RawRecording, window: tuple[float, float] | None = None,
                  max_gap_s: float = DEFAULT_MAX_GAP_S,
                  within: tuple[float, float] | None = None
                  ) -> tuple[int, int, Window, list[str]]:
    """The samples ``[i0, i1)`` of ``raw.t_acc`` to identify, the :class:`Window` and warnings
    (see the module notes; ``window`` and ``within`` exclude each other).

    Raises
    ------
    DataError
        For a window outside the recording, a gap longer than ``max_gap_s`` in a given window
        or a recording without flags, or (automatic window) no stretch of :data:`MIN_WINDOW_S`
        with the axis bypassed and not limited: the message says what the recording shows.
    """
    src, t, place = raw.source, raw.t_acc, raw.acc_place
    n = t.size
    if n < 2:
        raise DataError(f"{src}: only {n} samples; at least {MIN_SAMPLES} are needed")
    long_gap = np.diff(t) > max(_gap_threshold(t), max_gap_s)  # after sample i
    axis = raw.axis or "the axis"
    flagged = raw.bypassed is not None and raw.limited is not None
    if window is not None and within is not None:
        raise DataError("a given window and bounds to search one in exclude each other")
    if within is not None and not flagged:
        window = within
    if window is not None:
        start, end = (float(x) for x in window)
        if not (math.isfinite(start) and math.isfinite(end) and start < end):
            raise DataError(f"--window: START must be below END, got {start:g} {end:g}")
        i0 = int(np.searchsorted(t, start, side="left"))
        i1 = int(np.searchsorted(t, end, side="right"))
        if i1 - i0 < 2:
            raise DataError(f"{src}: window {start:g}-{end:g} s holds no data; the recording "
                            f"spans {t[0]:.3f}-{t[-1]:.3f} s")
        bad = np.flatnonzero(long_gap[i0:i1 - 1])
        if bad.size:
            raise _long_gap_error(t, i0 + int(bad[0]), place, src, max_gap_s)
        warnings = []
        if flagged:
            assert raw.bypassed is not None and raw.limited is not None
            comp = np.flatnonzero(~raw.bypassed[i0:i1])
            lim = np.flatnonzero(raw.limited[i0:i1])
            where = f"the window {t[i0]:.2f}-{t[i1 - 1]:.2f} s"
            if comp.size:
                warnings.append(
                    f"{axis} was compensated (no bypass:{axis} flag in the outputs) on "
                    f"{comp.size} of {i1 - i0} samples of {where} (first at "
                    f"{t[i0 + int(comp[0])]:.2f} s): the command is still what the platform "
                    "received, but no longer the excitation as played")
            if lim.size:
                warnings.append(
                    f"{axis} was limited (sat:{axis}) on {lim.size} samples of {where} (first "
                    f"at {t[i0 + int(lim[0])]:.2f} s): the limiter changed the command there")
        return i0, i1, Window(float(t[i0]), float(t[i1 - 1]), i1 - i0, "given"), warnings
    if not flagged:
        bad = np.flatnonzero(long_gap)
        if bad.size:
            raise _long_gap_error(t, int(bad[0]), place, src, max_gap_s)
        return 0, n, Window(float(t[0]), float(t[-1]), n, "whole recording"), []
    assert raw.bypassed is not None and raw.limited is not None
    good = raw.bypassed & ~raw.limited
    inside = ""
    if within is not None:
        lo, hi = (float(x) for x in within)
        good = good & (t >= lo) & (t <= hi)
        inside = f" inside {lo:.2f}-{hi:.2f} s"
    stretches = []
    for a, b in _runs(good):
        cuts = [a, *(np.flatnonzero(long_gap[a:b - 1]) + a + 1).tolist(), b]
        stretches += [(c0, c1) for c0, c1 in itertools.pairwise(cuts) if c1 > c0]
    best = max(stretches, key=lambda r: t[r[1] - 1] - t[r[0]], default=None)
    length = float(t[best[1] - 1] - t[best[0]]) if best else 0.0
    if best is None or length < MIN_WINDOW_S:
        period = float(np.median(np.diff(t)))
        found = []
        n_comp = int(np.count_nonzero(~raw.bypassed))
        if n_comp:
            found.append(f"compensated (no bypass:{axis} flag in the outputs) during "
                         f"{n_comp * period:.1f} s of {t[-1] - t[0]:.1f} s")
        n_lim = int(np.count_nonzero(raw.limited))
        if n_lim:
            found.append(f"limited (sat:{axis}) on {n_lim} samples")
        gaps = int(np.count_nonzero(long_gap))
        if gaps:
            found.append(f"{gaps} gaps longer than --max-gap {max_gap_s:g} s")
        found.append(f"the longest stretch bypassed and not limited is {length:.2f} s "
                     f"({t[best[0]]:.2f}-{t[best[1] - 1]:.2f} s)" if best else
                     "no sample with the axis bypassed and not limited")
        raise DataError(f"{src}: {axis}: no stretch of {MIN_WINDOW_S:g} s or more with the axis "
                        f"bypassed and not limited{inside}: {'; '.join(found)}; record the "
                        "excitation "
                        f"with the axis bypassed (motcomp bypass on --axes {axis}) or choose a "
                        "window with --window START END")
    i0, i1 = best
    return i0, i1, Window(float(t[i0]), float(t[i1 - 1]), i1 - i0,
                          "longest stretch bypassed and not limited" + inside), []


def _bridged(t: FloatArray, max_gap_s: float) -> tuple[Gaps, np.ndarray]:
    """The gaps of ``t`` (none longer than ``max_gap_s`` by now) and the mask of the intervals
    that are not gaps."""
    d = np.diff(t)
    is_gap = d > _gap_threshold(t)
    idx = np.flatnonzero(is_gap)
    gaps = Gaps(max_gap_s=max_gap_s, count=int(idx.size),
                longest_s=float(d[idx].max()) if idx.size else 0.0,
                total_s=float(d[idx].sum()) if idx.size else 0.0,
                first=tuple((float(t[i]), float(d[i])) for i in idx[:5].tolist()))
    return gaps, ~is_gap


def _merge(a: Gaps, b: Gaps) -> Gaps:
    return Gaps(max_gap_s=a.max_gap_s, count=a.count + b.count,
                longest_s=max(a.longest_s, b.longest_s), total_s=a.total_s + b.total_s,
                first=tuple(sorted(a.first + b.first))[:5])


def check_and_resample(raw: RawRecording, rate_hz: float | None = None,
                       max_gap_s: float = DEFAULT_MAX_GAP_S,
                       window: tuple[float, float] | None = None,
                       within: tuple[float, float] | None = None) -> Recording:
    """Check a raw recording, choose its window (:func:`select_window`) and put it on a
    uniform grid.

    Raises
    ------
    DataError
        Naming the problem, the place (line or message) and the value.
    """
    src = raw.source
    if not (math.isfinite(max_gap_s) and max_gap_s > 0):
        raise DataError(f"--max-gap must be a positive number of seconds, got {max_gap_s!r}")
    for x, col, place in ((raw.t_acc, "t", raw.acc_place), (raw.acc, "acc", raw.acc_place),
                          (raw.t_cmd, "t", raw.cmd_place), (raw.cmd, "cmd", raw.cmd_place)):
        _check_finite(x, col, place, src)
    n = min(raw.t_acc.size, raw.t_cmd.size)
    if n < MIN_SAMPLES:
        raise DataError(f"{src}: only {n} samples; at least {MIN_SAMPLES} are needed")
    _check_time(raw.t_acc, raw.acc_place, src, "sample")
    same = raw.t_cmd is raw.t_acc
    if not same:
        _check_time(raw.t_cmd, raw.cmd_place, src, "setpoint")
    if within is None:
        within = raw.within_hint
    i0, i1, win, warnings = select_window(raw, window, max_gap_s, within)
    conditions = raw.conditions_at(win.start_s, win.end_s) if raw.conditions_at else {}
    warnings = [*warnings, *conditions.pop("warnings", [])]
    t_acc, acc = raw.t_acc[i0:i1], raw.acc[i0:i1]
    if same:
        t_cmd, cmd = t_acc, raw.cmd[i0:i1]
    else:  # the command samples covering the window, one either side for the interpolation
        j0 = max(int(np.searchsorted(raw.t_cmd, t_acc[0], side="right")) - 1, 0)
        j1 = min(int(np.searchsorted(raw.t_cmd, t_acc[-1], side="left")) + 1, raw.t_cmd.size)
        t_cmd, cmd = raw.t_cmd[j0:j1], raw.cmd[j0:j1]
        long_gap = np.flatnonzero(np.diff(t_cmd) > max(_gap_threshold(t_cmd), max_gap_s))
        if long_gap.size:
            raise _long_gap_error(raw.t_cmd, j0 + int(long_gap[0]), raw.cmd_place, src,
                                  max_gap_s)
    n = min(t_acc.size, t_cmd.size)
    if n < MIN_SAMPLES:
        raise DataError(f"{src}: only {n} samples in the window {win.start_s:.3f}-"
                        f"{win.end_s:.3f} s; at least {MIN_SAMPLES} are needed")
    span = float(np.ptp(cmd))
    scale = max(float(np.max(np.abs(cmd))), 1.0)
    if span <= 1e-12 * scale:
        raise DataError(f"{src}: column cmd: the command is constant ({cmd[0]:.6g} on every "
                        "sample): nothing was excited")
    _check_clipped(acc, "acc", lambda i: raw.acc_place(i0 + i), src)
    gaps, steady = _bridged(t_acc, max_gap_s)
    if not same:
        gaps = _merge(gaps, _bridged(t_cmd, max_gap_s)[0])

    d = np.diff(t_acc)
    med = float(np.median(d))
    jitter = float(np.std(d[steady]))
    if rate_hz is None:
        rate = float(np.count_nonzero(steady) / np.sum(d[steady]))  # the mean rate, gaps aside
        # 1000.07 Hz from jittered stamps is 1 kHz; a regular record keeps its own rate
        tol = 1e-6 if same and float(np.max(np.abs(d - med))) <= 1e-3 * med else 1e-3
        if abs(rate - round(rate)) <= tol * rate:
            rate = float(round(rate))
    else:
        rate = float(rate_hz)
    if not (math.isfinite(rate) and rate > 0):
        raise DataError(f"{src}: resampling rate must be a positive number, got {rate!r}")
    same_grid = same or (t_cmd.size == t_acc.size and bool(np.all(t_cmd == t_acc)))
    regular = same_grid and float(np.max(np.abs(d - med))) <= 1e-3 * med and (
        abs(rate * med - 1.0) < 1e-6)
    # (a regular record: every period within 0.1 % of the median, and the rate its own)
    common: dict[str, Any] = dict(rate_hz=rate, axis=raw.axis, source=src, window=win,
                                  gaps=gaps, warnings=(*raw.warnings, *warnings),
                                  period_jitter_s=jitter, band_hz=raw.band_hz,
                                  conditions=conditions)
    if regular:
        return Recording(t=t_acc - t_acc[0], cmd=cmd.copy(), acc=acc.copy(), resampled=False,
                         start_s=float(t_acc[0]), **common)
    t0 = max(float(t_acc[0]), float(t_cmd[0]))
    t1 = min(float(t_acc[-1]), float(t_cmd[-1]))
    n_new = math.floor((t1 - t0) * rate + 1e-9) + 1
    if n_new < MIN_SAMPLES:
        raise DataError(f"{src}: only {n_new} samples after resampling at {rate:.6g} Hz over the "
                        f"common span {t1 - t0:.6g} s; at least {MIN_SAMPLES} are needed")
    grid = t0 + np.arange(n_new) / rate
    if raw.cmd_at is not None and gaps.count:
        t_cmd, cmd = _fill_command(t_cmd, cmd, raw.cmd_at)
    return Recording(t=grid - t0, cmd=np.interp(grid, t_cmd, cmd),
                     acc=np.interp(grid, t_acc, acc), resampled=True, start_s=t0, **common)


def _fill_command(t: FloatArray, cmd: FloatArray,
                  cmd_at: Callable[[FloatArray], tuple[FloatArray, np.ndarray]]
                  ) -> tuple[FloatArray, FloatArray]:
    """The command with, in every gap, the samples that would have been there (evenly spaced at
    about the median period) where ``cmd_at`` knows it: a gap in the measurement is not one in
    the command."""
    d = np.diff(t)
    med = float(np.median(d))
    idx = np.flatnonzero(d > 2.0 * med)
    fill = [t[i] + np.arange(1, m) * (d[i] / m)
            for i, m in zip(idx.tolist(), np.rint(d[idx] / med).astype(int).tolist(),
                            strict=True)]
    times = np.concatenate(fill) if fill else np.zeros(0)
    values, known = cmd_at(times)
    t_all = np.concatenate([t, times[known]])
    order = np.argsort(t_all, kind="stable")
    return t_all[order], np.concatenate([cmd, values[known]])[order]


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

_SESSION_CACHE: dict[tuple[Any, ...], Session] = {}


def _session(path: Path) -> Session:
    """The recording (or its rotated parts), read once for several axes: the last one read is
    kept."""
    from motcomp.record.session import read_session, session_parts

    parts = session_parts(path)
    key = tuple((str(p.resolve()), p.stat().st_mtime_ns, p.stat().st_size) for p in parts)
    if key not in _SESSION_CACHE:
        session = read_session(parts, other_keys=False, publish=False)
        _SESSION_CACHE.clear()
        _SESSION_CACHE[key] = session
    return _SESSION_CACHE[key]


def _output_spans(session: Session) -> dict[str, float]:
    """Span of the output command of every axis."""
    out = session.outputs
    if out is None or not len(out):
        return {}
    spans = {}
    for a, i in AXIS_INDEX.items():
        x = out.pos[out.valid, i]
        x = x[np.isfinite(x)]
        if x.size:
            spans[a] = float(np.ptp(x))
    return spans


def _no_outputs(session: Session) -> DataError:
    key = session.keys.get("output", OUTPUT_KEY)
    return DataError(f"{session.name}: no messages on channel {key}: the command identified "
                     "against is the service's output in force (what the platform received), "
                     f"so the recording must hold {key} (motcomp record records it by default); "
                     "for other data, write a CSV t,cmd,acc")


AxisLister = Callable[[Path, str], list[str]]
AXIS_LISTERS: dict[str, AxisLister] = {}
"""Per suffix, ``func(path, clock) -> axes that move``, for formats holding several axes."""


def list_axes(path: str | Path, clock: str = "frame") -> list[str]:
    """The axes a recording moves (in the order of :data:`motcomp.core.axes.AXES`); a format
    holding one axis (CSV) gives ``[]``: the caller names it."""
    p = Path(path)
    lister = AXIS_LISTERS.get(p.suffix.lower())
    if lister is None:
        return []
    return lister(p, clock)


def _list_mcap(path: Path, clock: str) -> list[str]:
    session = _session(path)
    spans = _output_spans(session)
    if not spans:
        raise _no_outputs(session)
    return [a for a in AXIS_INDEX if spans.get(a, 0.0) > 0.0]


AXIS_LISTERS[".mcap"] = _list_mcap


@register_loader(".mcap")
def _load_mcap(path: Path, axis: str | None, clock: str) -> RawRecording:
    from motcomp.record.session import pairing_phase_ms

    session = _session(path)
    src = session.name
    spans = _output_spans(session)
    if not spans:
        raise _no_outputs(session)
    if axis is None:  # the one whose command moves most
        axis = max(spans, key=lambda a: spans[a])
    cols = session.identification_columns(axis, clock)
    fb_key = session.keys.get("feedback", FEEDBACK_KEY)
    if not cols.t.size:
        raise DataError(f"{src}: {fb_key}: no message carries acc.{axis} (with a time stamp) "
                        "after the first output")
    warnings = list(session.warnings)
    if cols.unknown:
        warnings.append(f"{cols.unknown} {fb_key} samples left out: the recording lost the "
                        "outputs in force then")
    index = cols.feedback_index
    t = cols.t - cols.start_s

    def place(i: int) -> str:
        return f"{fb_key} message {int(index[i]) if 0 <= i < index.size else i}"

    def cmd_at(times: FloatArray) -> tuple[FloatArray, np.ndarray]:
        return session.command_in_force(axis, times + cols.start_s, clock)

    def conditions_at(a: float, b: float) -> dict[str, Any]:
        out = run_conditions(session, a + cols.start_s, b + cols.start_s)
        inside = (t >= a) & (t <= b)
        if clock == "frame" and inside.any():  # the log clock's times are receipts
            out["pairing_phase_ms"] = pairing_phase_ms(cols.t[inside], cols.t_out[inside])
        return out
    hint = None
    span = str(session.metadata.get("excitation_window", "")).split()
    if len(span) == 2 and session.metadata.get("excitation_axis") == axis:
        with contextlib.suppress(ValueError):
            hint = (float(span[0]) - cols.start_s, float(span[1]) - cols.start_s)
    return RawRecording(source=src, t_acc=t, acc=cols.acc, t_cmd=t, cmd=cols.cmd, axis=axis,
                        acc_place=place, cmd_place=place, bypassed=cols.bypassed,
                        limited=cols.limited, warnings=tuple(warnings), cmd_at=cmd_at,
                        band_hz=_reference_band(session, axis, hint, cols.start_s),
                        within_hint=hint,
                        conditions_at=conditions_at)


def run_conditions(session: Session, t0: float, t1: float) -> dict[str, Any]:
    """How the run went between ``t0`` and ``t1`` (the recording's clock, s), from the service
    status frames it recorded (one before and one after the window at best): the deadlines the
    service's loop missed, and the platform's own figures (its setpoint age: the stack's delay,
    which an identified ``Td`` includes less the pairing's phase).  ``warnings`` name what
    makes the fit doubtful."""
    frames = [st for _, st in session.status
              if isinstance(st.get("t"), int | float) and isinstance(st.get("ticks"), int)
              and isinstance(st.get("missed_ticks"), int)]
    if not frames:
        return {}
    before = [st for st in frames if st["t"] <= t0 + 0.5]
    after = [st for st in frames if st["t"] >= t1 - 0.5]
    a = before[-1] if before else frames[0]
    b = after[0] if after else frames[-1]
    out: dict[str, Any] = {"from_t": a["t"], "to_t": b["t"]}
    ticks, missed = b["ticks"] - a["ticks"], b["missed_ticks"] - a["missed_ticks"]
    warnings = []
    if b["t"] > a["t"] and ticks >= 0 and missed >= 0 and ticks + missed > 0:
        share = missed / (ticks + missed)
        out.update(service_ticks=ticks, service_missed=missed, service_missed_share=share)
        if share > DEGRADED_MISSED_SHARE:  # the host's stalls are in the fit
            warnings.append(f"the service missed {missed} of {ticks + missed} deadlines "
                            f"({100 * share:.1f} %) while the data were recorded: the host "
                            "took the loop's time, and the fitted delay and dynamics carry "
                            "its stalls; identify again on a quiet host")
    plat = b.get("platform") if isinstance(b.get("platform"), dict) else None
    if plat:
        for k in ("setpoint_age_ms", "setpoint_age_mean_ms"):
            if isinstance(plat.get(k), int | float):
                out[f"platform_{k}"] = float(plat[k])
    out["warnings"] = warnings
    return out


def spectrum_tops(x: FloatArray, rate: float) -> tuple[float, float]:
    """``(f30, f10)``: the frequencies above which the spectrum of ``x`` stays 30 dB and 10 dB
    below its peak (Welch, 8 s segments); ``(0, 0)`` for a signal without content."""
    from scipy import signal

    nper = min(x.size, max(256, int(8.0 * rate)))
    f, px = signal.welch(x, fs=rate, nperseg=nper)
    peak = float(px[1:].max()) if px.size > 1 else 0.0
    if not peak > 0:
        return 0.0, 0.0
    return (float(f[np.nonzero(px >= 1e-3 * peak)[0][-1]]),
            float(f[np.nonzero(px >= 0.1 * peak)[0][-1]]))


def _reference_band(session: Session, axis: str, within: tuple[float, float] | None,
                    start_s: float) -> float | None:
    """The top of the band of the reference the service was asked to follow on ``axis`` (its
    input stream, inside ``within`` if given): where its acceleration spectrum falls 10 dB
    below its peak for good (:func:`spectrum_tops`; not 30 dB: the time
    stamps' own rounding -- 0.24 us on epoch seconds -- puts a white floor there); None without
    one."""
    inp = session.inputs
    if inp is None or len(inp) < MIN_SAMPLES:
        return None
    t, x = inp.t, inp.pos[:, AXIS_INDEX[axis]]
    keep = np.isfinite(t) & np.isfinite(x)
    if within is not None:
        keep &= (t >= within[0] + start_s) & (t <= within[1] + start_s)
    t, x = t[keep], x[keep]
    if t.size < MIN_SAMPLES or not np.all(np.diff(t) > 0) or np.ptp(x) == 0:
        return None
    rate = 1.0 / float(np.median(np.diff(t)))
    grid = np.arange(t[0], t[-1], 1.0 / rate)
    _, f10 = spectrum_tops(np.diff(np.interp(grid, t, x), 2) * rate * rate, rate)
    return f10 if 0 < f10 < rate / 4 else None
