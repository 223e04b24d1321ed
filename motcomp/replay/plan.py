"""What the service did, tick by tick: the :class:`TickPlan` a replay follows.

A plan has one row per compensator step: its instant ``now_ns`` (the loop's own clock), the
input frame the tick read (if any), whether it emitted an output (a tick) or was a catch-up
step after a stall (computed by the following tick: :func:`motcomp.core.tick.step` with
``skipped``), and the bypass changes and the parking request between steps.  It is rebuilt
from a recording in one of three ways (docs/REPLAY.md):

``outputs+clock``
    Recorded outputs and a status frame carrying the loop's ``clock``: each output's ``t`` is
    mapped back to the exact tick instant (``tick_ns = grid0_ns + m * period_ns``), the input
    frame each tick used last is the one whose ``seq`` is the output's ``src_seq`` (a change of
    ``src_seq`` marks a consumed frame; the tick read every recorded frame since the previous
    consumed one: :func:`consumed_ranges`), stalls show as gaps of whole periods and become
    catch-up rows, bypass changes and parking come from the output flags.  The replay then
    computes with the very numbers the service computed with.
``outputs``
    The same without the clock (older service, or no status recorded): tick instants are output
    ``t`` snapped to the period relative to the first tick; the absolute instant is unknown,
    which changes floating-point rounding in the reference reconstruction (see docs/REPLAY.md).
``inputs``
    No outputs: ticks at the config's rate from the first input's arrival, each reading the
    frames that arrived since the previous tick (recorder receive times), valid or not, as the
    service's input does.

A plan does not judge frames: the replay's tick reads the recorded bytes and accepts or rejects
them itself (:func:`motcomp.core.tick.parse_input` and the sequence rule).  The one use of
:func:`~motcomp.core.tick.parse_input` here is the start of a warm plan: the first frame the
replay's tick accepts, since the replay starts at rest at its position.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from motcomp.config import ResolvedAxes, ServiceConfig, tick_params
from motcomp.core.axes import AXES
from motcomp.core.fpmode import FLUSHED
from motcomp.core.tick import MAX_CATCH_UP, TickParams, parse_input
from motcomp.errors import DataError
from motcomp.record.frames import FLAG_BITS
from motcomp.record.session import InputStream, Session

__all__ = ["TickPlan", "build_plan", "consumed_ranges", "first_position", "recorded_flushed"]

WARM_AFTER_TICKS = 5000
"""A recording whose first output is a later tick than this, and already used an input,
starts *warm* (mid-run)."""
_PARK = FLAG_BITS["parking"]


@dataclass
class TickPlan:
    """See the module docstring.  Row arrays all have one entry per compensator step."""

    now_ns: np.ndarray
    frame: np.ndarray
    """Index of the newest input frame the step's tick reads, or -1 (none)."""
    output: np.ndarray
    """Index of the recorded output of this step, or -1 (catch-up step, or not recorded)."""
    emit: np.ndarray
    """The step was a tick (it sent an output), not a catch-up."""
    bypass0: np.ndarray | None
    """Bypass mask at the first row (None: the config's): ``2 x len(AXES)`` booleans, the PID's
    bypass (flags ``bypass:<axis>``) then the prediction turned off (``nopredict:<axis>``)."""
    bypass_events: list[tuple[int, np.ndarray]]
    """``(row, mask)``: bypass set to ``mask`` (as :attr:`bypass0`) before the row's step."""
    park: tuple[int, int] | None
    """``(row, now_ns)``: parking requested at ``now_ns``, before that row."""
    warm: bool
    """Starts mid-run: at rest at the first frame (:func:`first_position`), without the
    start-up blend."""
    method: str
    period_ns: int
    missing_frames: int = 0
    notes: list[str] = field(default_factory=list)
    seq_holes: int = 0
    """Sequence numbers missing from the recorded input between the first and the last frame
    the service used: frames the recorder may have lost while the service read them (a sender
    counting its frames, as ``motcomp source`` does, leaves none); with any, the replay reads
    a shorter history and is not bit-identical."""
    bypass_axes: np.ndarray | None = None
    """Axes whose recorded bypass state is known (driven by the recorded service; the output
    flags say nothing of the others).  None: all."""
    frame_lo: np.ndarray | None = None
    """Index of the oldest input frame the step's tick reads (it reads ``frame_lo`` to
    ``frame``); None: :func:`consumed_ranges` of :attr:`frame`."""
    rx_ns: np.ndarray | None = None
    """Per row, how long after its instant the tick took its input frames (the outputs'
    ``rx``; 0: at the instant).  None: 0 everywhere."""
    flushed: bool = True
    """The recorded service's loop computed with subnormals flushed to zero (its status'
    ``realtime`` says so; a recording of a version before, or of a CPU without the mode, did
    not).  Without a status: as the service does now."""
    superseded: int | None = None
    """The rise of the service's status' ``frames.superseded`` over the run: ``seq`` numbers it
    never took -- the sender skipped them, a link dropped them, or the service rejected the
    frame --; None without two status frames in the run."""
    absent: tuple[int, ...] = ()
    """Recorded input frames (indices into the recording's inputs) found to have never reached
    the service: the ticks leave them out (:func:`motcomp.replay.offline.find_absent`)."""

    def __post_init__(self) -> None:
        if self.frame_lo is None:
            self.frame_lo = consumed_ranges(self.frame)

    @property
    def rows(self) -> int:
        return int(self.now_ns.size)

    @property
    def t_s(self) -> np.ndarray:
        """Row instants relative to the first row (s)."""
        return np.asarray((self.now_ns - self.now_ns[0]) / 1e9)


def consumed_ranges(frame: np.ndarray) -> np.ndarray:
    """The oldest frame each row reads, given the newest (``frame``): a tick reads every frame
    that arrived since the previous tick, i.e. those after the frame the previous reading row
    ended with; the first reading row reads its newest frame only (the tick's rule until a
    frame is accepted: :mod:`motcomp.core.tick`), as does a row whose frame is not after the
    previous one (a restarted sender)."""
    lo = np.full(frame.size, -1, dtype=np.int64)
    prev = -1
    for r in np.flatnonzero(frame >= 0).tolist():
        f = int(frame[r])
        lo[r] = prev + 1 if 0 <= prev < f else f
        prev = f
    return lo


def first_position(inp: InputStream, frame: int, params: TickParams
                   ) -> dict[int, float] | None:
    """``{axis index: value}`` of input frame ``frame`` if the tick accepts it (alone, as a
    first frame), else None."""
    sp = params.shaper
    try:
        return parse_input(inp.payload(frame), sp.reach_lo, sp.reach_hi,
                           params.max_frame_bytes)[2]
    except Exception:  # FrameError; anything else the tick rejects too ("internal")
        return None


def _warm_start(inp: InputStream, frame: np.ndarray, params: TickParams, name: str) -> int:
    """The row of a warm plan's first tick: the first whose frame the tick accepts."""
    for r in np.flatnonzero(frame >= 0).tolist():
        if first_position(inp, int(frame[r]), params) is not None:
            return int(r)
    raise DataError(f"{name}: no usable input frame in the recording")


def _runs(seq: np.ndarray) -> list[np.ndarray]:
    """Split recorded outputs into service runs (``seq`` restarts)."""
    cuts = np.flatnonzero(np.diff(seq) <= 0) + 1
    return np.split(np.arange(seq.size), cuts)


def _clock_for(session: Session, t_first: float, t_last: float) -> dict[str, Any] | None:
    """The loop clock of the service run whose outputs span ``[t_first, t_last]``."""
    best = None
    for _, st in session.status:
        c = st.get("clock")
        if not isinstance(c, dict) or not all(isinstance(c.get(k), int | float) for k in
                                               ("wall0", "mono0_ns", "period_ns")):
            continue
        if c["wall0"] <= t_first + 1e-3 and (best is None or c["wall0"] > best["wall0"]):
            best = c
    if best is not None and best["wall0"] > t_last:
        return None
    return best


def build_plan(session: Session, cfg: ServiceConfig, axes: ResolvedAxes, run: int = 0,
               use_outputs: bool = True) -> TickPlan:
    """The tick plan of a recording (see the module docstring).

    Raises
    ------
    DataError
        If the session has no input frames, or ``run`` does not exist.
    """
    inp = session.inputs
    if inp is None or not len(inp):
        raise DataError(f"{session.name}: no input frames on {session.keys['input']!r}")
    params = tick_params(cfg, axes)
    out = session.outputs
    if use_outputs and out is not None and out.valid.any():
        return _from_outputs(session, cfg, params, run)
    return _from_inputs(session, cfg, params)


def _frame_lookup(session: Session) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    inp = session.inputs
    assert inp is not None
    order = np.lexsort((inp.log_ns, inp.seq))
    return order, inp.seq[order], inp.log_ns[order]


def _from_outputs(session: Session, cfg: ServiceConfig, params: TickParams, run: int
                  ) -> TickPlan:
    out = session.outputs
    inp = session.inputs
    assert out is not None and inp is not None
    valid = np.flatnonzero(out.valid)
    runs = _runs(out.seq[valid])
    notes = []
    if len(runs) > 1:
        notes.append(f"the recording holds {len(runs)} service runs (output seq restarts); "
                     f"replaying run {run}")
    if not 0 <= run < len(runs):
        raise DataError(f"{session.name}: no service run {run} (runs: {len(runs)})")
    idx = valid[runs[run]]
    seq, t, src = out.seq[idx], out.t[idx], out.src_seq[idx]
    flags, log_ns = out.flags[idx], out.log_ns[idx]
    clock = _clock_for(session, float(t[0]), float(t[-1]))
    period = int(clock["period_ns"]) if clock else round(1e9 / cfg.loop.rate_hz)
    if clock is not None:
        est = clock["mono0_ns"] + np.round((t - clock["wall0"]) * 1e9).astype(np.int64)
        grid0 = clock.get("grid0_ns")
        if isinstance(grid0, int):
            tick = grid0 + np.round((est - grid0) / period).astype(np.int64) * period
            method = "outputs+clock"
        else:
            tick = est
            method = "outputs+clock (input-synchronous ticks: instants to ~0.2 us)"
    else:
        rel = np.round((t - t[0]) / (period / 1e9)).astype(np.int64)
        tick = rel * period + 10**12  # an arbitrary origin 1000 s after an imaginary boot
        method = "outputs"
        notes.append("no loop clock in the recorded status: tick instants rebuilt from output "
                     "t (relative grid only)")
    # ticks before the first recorded one: if the service had used no input yet (src_seq -1)
    # it was at rest at neutral, exactly the state the replay starts from; otherwise a few
    # seconds of ticks are rebuilt on the grid (frames by arrival), or the replay starts warm
    warm = bool(seq[0] > WARM_AFTER_TICKS and src[0] >= 0)
    if not warm and seq[0] > 0 and src[0] >= 0:
        lead = np.arange(int(seq[0]), 0, -1)
        tick = np.concatenate([tick[0] - lead * period, tick])
        seq = np.concatenate([seq[0] - lead, seq])
        src = np.concatenate([np.full(lead.size, -2), src])
        flags = np.concatenate([np.full(lead.size, flags[0]), flags])
        log_ns = np.concatenate([np.full(lead.size, -1), log_ns])
        idx = np.concatenate([np.full(lead.size, -1), idx])
        notes.append(f"the first {lead.size} ticks were not recorded: rebuilt on the grid")
    # rows: recorded ticks, missing ticks (seq gaps) and catch-up steps (time gaps)
    rows_now: list[np.ndarray] = []
    rows_out: list[np.ndarray] = []
    rows_emit: list[np.ndarray] = []
    rows_src: list[np.ndarray] = []
    gaps = np.diff(tick) // period - 1 if tick.size > 1 else np.zeros(0, np.int64)
    seq_gap = np.diff(seq) - 1 if seq.size > 1 else np.zeros(0, np.int64)
    irregular = np.flatnonzero((gaps != 0) | (seq_gap != 0)) + 1
    start = 0
    for j in [*irregular.tolist(), tick.size]:
        rows_now.append(tick[start:j])
        rows_out.append(idx[start:j])
        rows_emit.append(np.ones(j - start, bool))
        rows_src.append(src[start:j])
        if j == tick.size:
            break
        missing = int(max(seq_gap[j - 1], 0))
        skipped = int(max(gaps[j - 1] - missing, 0))
        t_prev = int(tick[j - 1])
        if missing:  # ticks the recorder lost: on the grid after the previous one
            rows_now.append(t_prev + period * np.arange(1, missing + 1, dtype=np.int64))
            rows_out.append(np.full(missing, -1))
            rows_emit.append(np.ones(missing, bool))
            rows_src.append(np.full(missing, -3))
        n_cu = min(skipped, MAX_CATCH_UP)
        if n_cu:
            rows_now.append(int(tick[j]) - period * np.arange(n_cu, 0, -1, dtype=np.int64))
            rows_out.append(np.full(n_cu, -1))
            rows_emit.append(np.zeros(n_cu, bool))
            rows_src.append(np.full(n_cu, -4))
        start = j
    now_ns = np.concatenate(rows_now)
    output = np.concatenate(rows_out)
    emit = np.concatenate(rows_emit)
    row_src = np.concatenate(rows_src)
    lost_ticks = np.flatnonzero(row_src == -3)
    if lost_ticks.size:
        first = (int(now_ns[lost_ticks[0]]) - int(now_ns[0])) / 1e9
        notes.append(f"{lost_ticks.size} output frames are not in the recording (the recorder "
                     f"lost them; the first {first:.3f} s into the run): the replay cannot know "
                     "when those ticks took their input frames nor which of the deadlines around "
                     "them the service missed, so from there on it may differ from the recorded "
                     "outputs at the rounding of a floating-point number, growing with the "
                     "compensator's dynamics (see 'max |replay-rec|'); " + _RECORD_BETTER)
    # frames: a change of src_seq between recorded ticks marks the frame consumed there
    frame = np.full(now_ns.size, -1, dtype=np.int64)
    rec = np.flatnonzero(row_src >= -1)
    prev = np.concatenate([[-1 if not warm else -5], row_src[rec][:-1]])
    changed = rec[(row_src[rec] != prev) & (row_src[rec] >= 0)]
    want = row_src[changed]
    if np.all(inp.seq[1:] > inp.seq[:-1]):  # the usual case: one sender, no restart
        order, sseq = np.arange(len(inp)), inp.seq
        lo = np.minimum(np.searchsorted(sseq, want, "left"), sseq.size - 1)
        found = sseq[lo] == want
        hi, pick = lo + 1, lo
        dup = np.zeros(0, dtype=np.int64)
    else:
        order, sseq, slog = _frame_lookup(session)
        lo = np.searchsorted(sseq, want, "left")
        hi = np.searchsorted(sseq, want, "right")
        found = hi > lo
        pick = np.where(found, hi - 1, 0)
        dup = np.flatnonzero(found & (hi - lo > 1))
    out_log = np.where(output[changed] >= 0, out.log_ns[np.maximum(output[changed], 0)], 0)
    for k in dup:  # several frames with that seq (a restarted sender): the latest before
        cand = np.arange(lo[k], hi[k])
        before = cand[slog[cand] <= out_log[k] + 10**9]
        pick[k] = before[-1] if before.size else cand[0]
    if dup.size or not np.all(inp.seq[1:] > inp.seq[:-1]):
        _arrived_in_order(found, pick, lo, hi, slog, out_log)
    frame[changed[found]] = order[pick[found]]
    at = np.where(found, order[pick], -1)
    if warm and want.size and not found[0]:
        # the frame in force when the recording began, taken before it: not the recorder's loss
        want, at, found = want[1:], at[1:], found[1:]
    missing_frames = int((~found).sum())
    if missing_frames:
        notes.append(f"{missing_frames} input frames the service used are not in the "
                     "recording (the recorder lost them): their ticks see no new input here, so "
                     "the replay departs from the recorded outputs after them; " + _RECORD_BETTER)
    holes = _seq_holes(inp.seq, want, at)
    superseded = _superseded(session, log_ns)
    if holes:
        notes.append(_holes_note(holes, superseded))
    # frames consumed in ticks the recorder lost: by arrival time (mapped to the tick clock),
    # newer than the frame in use before the gap and older than the one in use after it
    lost = np.flatnonzero((row_src == -2) | (row_src == -3))
    if lost.size:
        rec_rows = np.flatnonzero(output >= 0)
        delta = int(np.median(now_ns[rec_rows] - out.log_ns[output[rec_rows]]))
        known = np.flatnonzero(row_src >= -1)
        pos = np.searchsorted(known, lost)
        before = np.where(pos > 0, row_src[known[np.maximum(pos - 1, 0)]], -1)
        after = np.where(pos < known.size, row_src[known[np.minimum(pos, known.size - 1)]],
                         np.iinfo(np.int64).max)
        _assign_by_arrival(frame, now_ns, lost, inp.log_ns + delta, inp.seq, before, after)
    # bypass changes and parking, from the flags of the recorded ticks
    rec_rows = np.flatnonzero(output >= 0)
    flags_rows = out.flags[output[rec_rows]]
    bits = (flags_rows >> 8 & 0xFF) | ((flags_rows >> 32 & 0xFF) << 8)

    def mask_of(k: int) -> np.ndarray:
        return ((int(bits[k]) >> np.arange(2 * len(AXES))) & 1).astype(bool)

    bypass0 = mask_of(0)
    events = [(int(rec_rows[k]), mask_of(int(k)))
              for k in np.flatnonzero(bits[1:] != bits[:-1]) + 1]
    park = None
    parked = np.flatnonzero(flags_rows & _PARK)
    if parked.size and parked[0] > 0:
        prev_tick = int(rec_rows[parked[0] - 1])
        park = (prev_tick + 1, int(now_ns[prev_tick]))
    if warm:
        shift = _warm_start(inp, frame, params, session.name)
        keep = slice(shift, None)
        now_ns, frame, output, emit = now_ns[keep], frame[keep], output[keep], emit[keep]
        events = [(r - shift, m) for r, m in events if r > shift]
        bypass0 = mask_of(int(np.searchsorted(rec_rows, shift))) if rec_rows.size else bypass0
        park = (park[0] - shift, park[1]) if park and park[0] > shift else None
        notes.append(f"the recording starts mid-run (first tick seq {int(out.seq[idx[0]])}): "
                     "warm start at rest at the first input")
    missed = int(np.count_nonzero(~emit))
    if missed:
        notes.append(f"the service missed {missed} of {emit.size} deadlines "
                     f"({100 * missed / emit.size:.1f} %) over the replayed run: its live figures "
                     "(the recorded 'on' delay, the status) carry those stalls, which the replay "
                     "computes as the service did")
    rec_driven = [st["driven"] for _, st in session.status if isinstance(st.get("driven"), list)]
    by_axes = np.array([a in rec_driven[-1] for a in AXES]) if rec_driven else None
    rx = np.where(output >= 0, out.rx[np.maximum(output, 0)], 0) if out.rx.size else None
    return TickPlan(now_ns, frame, output, emit, bypass0, events, park, warm, method, period,
                    missing_frames, notes, holes, by_axes, rx_ns=rx,
                    flushed=recorded_flushed(st for _, st in session.status),
                    superseded=superseded)


def recorded_flushed(status: Iterable[dict[str, Any]]) -> bool:
    """Whether the service whose status frames these are computed its ticks with subnormals
    flushed to zero: its last ``realtime`` says so (True without one: as the service does)."""
    modes = [st["realtime"] for st in status if isinstance(st.get("realtime"), str)]
    return FLUSHED in modes[-1] if modes else True


_RECORD_BETTER = ("to record every frame, run `motcomp record` where it gets its CPU (not "
                  "beside a busy service on two cores) and check its summary's 'dropped (queue "
                  "full)'; frames lost before they reached it show in `motcomp info` (lost)")


def _superseded(session: Session, log_ns: np.ndarray) -> int | None:
    """Input frames the service never received over the replayed run (the rise of its
    status' ``frames.superseded``: ``seq`` steps between the frames it accepted), or None
    without two status frames in the run."""
    rec = log_ns[log_ns >= 0]  # the run's recorded outputs (receive times)
    counts = [int(st["frames"]["superseded"]) for ns, st in session.status
              if rec.size and rec[0] <= ns <= rec[-1] + 2 * 10**9
              and isinstance(st.get("frames"), dict)
              and isinstance(st["frames"].get("superseded"), int)]
    return counts[-1] - counts[0] if len(counts) > 1 else None


def _holes_note(holes: int, superseded: int | None) -> str:
    """What ``holes`` sequence numbers missing from the recorded input mean, and what to do."""
    head = (f"{holes} sequence numbers between the first and the last input frame the service "
            "used are not in the recording")
    if superseded is not None and superseded == holes:
        return (f"{head}; the service did not receive them either (its status counted "
                f"{superseded} frames superseded: the sender skipped those numbers, or they "
                "were lost before both): nothing it used is missing, the replay reads what it "
                "read")
    if superseded is not None and superseded > holes:
        return (f"{head}, but the service's status counted {superseded} input frames it never "
                "received (superseded): "
                f"{superseded - holes} frames the recorder received never reached the service "
                "(dropped on its link, under load) or were rejected by it: where the replay can "
                "be held to the recorded outputs, it looks for them (docs/REPLAY.md)")
    if superseded is not None:
        return (f"{head}, and the service received {holes - superseded} of them (its status "
                f"counted {superseded} superseded): the recorder lost those, so the replay "
                "reads a shorter input history near them and may differ from the recorded "
                "outputs there (docs/REPLAY.md); " + _RECORD_BETTER)
    return (f"{head}: either the sender skipped them (harmless) or the recorder lost frames "
            "the service used (the replay then differs from the recorded outputs near them); "
            "the recording has no service status to tell which: record the status key too")


def _arrived_in_order(found: np.ndarray, pick: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                      slog: np.ndarray, out_log: np.ndarray) -> None:
    """Hold the frames picked for the used numbers of a sender that restarted (its numbers
    repeat) to the order and the time the service took them in: none arrived before the one
    used before it, nor later than its output plus 1 s.  A pick that did not (another run's
    frame of a number the recorder lost) is replaced by the latest candidate that did, or
    marked not found (in place), and moves nothing on.  ``lo:hi`` are each number's
    candidates, ``slog`` their log times, ``out_log`` each output's (0: not recorded)."""
    last = -1

    def fits(c: int, k: int) -> bool:
        return bool(slog[c] >= last and (out_log[k] == 0 or slog[c] <= out_log[k] + 10**9))

    for k in np.flatnonzero(found).tolist():
        if not fits(int(pick[k]), k):
            ok = [c for c in range(int(lo[k]), int(hi[k])) if fits(c, k)]
            if not ok:
                found[k] = False
                continue
            pick[k] = ok[-1]
        last = int(slog[pick[k]])


def _seq_holes(seq: np.ndarray, used: np.ndarray, at: np.ndarray) -> int:
    """Sequence numbers that no recorded frame carries within the span of each sender run's
    used ones.  ``used``, in tick order, splits into runs where it regresses (a restarted
    sender starts its ``seq`` over); ``at`` is the index in ``seq`` of each used frame (-1: not
    recorded), and a run's recorded frames those of the recorded runs (``seq`` split likewise,
    in the recording's order) that hold its found ones."""
    holes = 0
    cuts = np.flatnonzero(np.diff(used) < 0) + 1
    rec_run = np.concatenate([[0], np.cumsum(np.diff(seq) < 0)]) if seq.size else seq
    for run, idx in zip(np.split(used, cuts), np.split(at, cuts), strict=True):
        if not run.size:
            continue
        lo, hi = int(run.min()), int(run.max())
        found = idx[idx >= 0]
        mine = seq[np.isin(rec_run, rec_run[found])] if found.size else seq[:0]
        holes += hi - lo + 1 - np.unique(mine[(mine >= lo) & (mine <= hi)]).size
    return holes


def _assign_by_arrival(frame: np.ndarray, now_ns: np.ndarray, rows: np.ndarray,
                       arrival_ns: np.ndarray, seq: np.ndarray, seq_lo: np.ndarray,
                       seq_hi: np.ndarray) -> None:
    """Give each of ``rows`` (ticks whose consumption was not recorded) the newest frame that
    arrived since the previous row with ``seq_lo < seq < seq_hi``."""
    last = -1
    for k, r in enumerate(rows.tolist()):
        t_lo = now_ns[r - 1] if r > 0 else now_ns[r] - 10**6
        cand = np.flatnonzero((arrival_ns > t_lo) & (arrival_ns <= now_ns[r]) &
                              (seq > max(int(seq_lo[k]), last)) & (seq < seq_hi[k]))
        if cand.size:
            frame[r] = cand[-1]
            last = int(seq[cand[-1]])


def _from_inputs(session: Session, cfg: ServiceConfig, params: TickParams) -> TickPlan:
    inp = session.inputs
    assert inp is not None
    period = round(1e9 / cfg.loop.rate_hz)
    arrival = inp.log_ns - int(inp.log_ns[0])
    n_rows = int(arrival[-1] // period) + 2
    now_ns = np.arange(n_rows, dtype=np.int64) * period + 10**12
    # the tick after each arrival reads every frame that arrived since the previous one
    tick_of = np.ceil(arrival / period).astype(np.int64)
    last = np.flatnonzero(np.diff(tick_of, append=tick_of[-1] + 1) != 0)
    first = np.flatnonzero(np.diff(tick_of, prepend=tick_of[0] - 1) != 0)
    frame = np.full(n_rows, -1, dtype=np.int64)
    frame_lo = np.full(n_rows, -1, dtype=np.int64)
    frame[tick_of[last]] = last
    frame_lo[tick_of[first]] = first
    start = _warm_start(inp, frame, params, session.name)
    frame_lo[start] = frame[start]  # the first reading row: its newest frame only
    keep = slice(start, None)
    return TickPlan(now_ns[keep], frame[keep], np.full(n_rows, -1)[keep],
                    np.ones(n_rows, bool)[keep], None, [], None, True, "inputs", period,
                    0, ["no outputs recorded: ticks at the config's rate from the input arrival "
                        "times, warm start at the first input"], frame_lo=frame_lo[keep])
