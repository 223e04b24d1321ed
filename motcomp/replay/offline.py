"""Offline replay: recordings, one or more configs, the tick, the report.

::

    read_session -> for each config: build_plan -> run_ticks -> analyse

The config is the one recorded with the session (attachment ``config.json``) unless another is
given; a config whose loop rate differs from the recording's cannot follow the recorded ticks,
and is replayed on ticks rebuilt from the input arrivals instead.

:func:`replay_files` replays several recordings, each with several configs; with ``jobs > 1``
every (recording, config) pair runs in its own worker process (it reads the recording itself),
and the results are the same, bit for bit, as with ``jobs=1``: the same functions on the same
bytes, in the same order within a pair.
"""

from __future__ import annotations

import multiprocessing
import time
import weakref
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from motcomp.config import ResolvedAxes, ServiceConfig, config_hash, load_config, resolve_axes
from motcomp.core.axes import AXES
from motcomp.errors import ConfigError
from motcomp.record.session import Session, read_session
from motcomp.replay.analysis import ReplayReport, analyse, flush_subnormal
from motcomp.replay.engine import EngineResult, recorded_bypass_axes, run_ticks
from motcomp.replay.plan import TickPlan, build_plan

__all__ = ["FEEDBACK_WINDOWS", "Absent", "FileReplay", "ReplayRun", "bypass_overridden",
           "comparable", "config_for", "departure_note", "find_absent", "plan_for",
           "read_for_replay", "replay_files", "replay_offline"]

FEEDBACK_WINDOWS = (12, 40.0)
"""Feedback is read in this many windows of this length (s) on long recordings: the recorded
delays are estimated on windows anyway (:mod:`motcomp.replay.analysis`)."""


@dataclass
class ReplayRun:
    label: str
    cfg: ServiceConfig
    axes: ResolvedAxes
    plan: TickPlan
    result: EngineResult
    report: ReplayReport
    recorded_config: bool
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class FileReplay:
    """The replays of one recording."""

    path: Path
    name: str
    warnings: list[str]
    runs: list[ReplayRun]
    read_s: float
    """Reading the recording (the longest of the workers' reads with ``jobs > 1``)."""
    wall_s: float
    """From the start of the work on this file to its last replay."""
    session: Session | None = None
    """The recording as read (None when the replays ran in worker processes)."""


def config_for(session: Session, path: str | Path | None) -> tuple[ServiceConfig, str, bool]:
    """``(config, label, is the recorded one)``: ``path`` if given, else the recorded config.

    Raises
    ------
    ConfigError
        If no config is given and none was recorded, or a config is invalid.
    """
    recorded_hash = session.metadata.get("config_hash")
    if path is not None:
        cfg = load_config(path)
        return cfg, str(path), recorded_hash is not None and config_hash(cfg) == recorded_hash
    cfg = session.config()
    if cfg is None:
        raise ConfigError(f"{session.name}: no config recorded with the session (the service "
                          "did not answer the recorder's status query); give --config FILE")
    return cfg, f"recorded config {config_hash(cfg)}", True


ABSENT_MAX = 16
"""Most input frames :func:`find_absent` leaves out of a replay."""
ABSENT_LOOKBACK_S = 0.25
"""How far before a departure from the recorded outputs the frame that explains it is looked
for (the reference plays a frame some ms after it is taken: ``input.playback_lag_s``)."""
ABSENT_TRIAL_ROWS = 2000
"""A trial replay runs from the start to this many rows past the departure it tries to
explain."""
ABSENT_BUDGET = 8
"""The trials of a search run at most this many times the plan's rows in all."""


@dataclass(frozen=True)
class Absent:
    """What :func:`find_absent` found: the frames, its note, and why it stopped with the replay
    still departing (None if it does not)."""

    frames: tuple[int, ...] = ()
    note: str | None = None
    stopped: str | None = None


_ABSENT: dict[int, dict[int, Absent]] = {}
""":func:`find_absent`'s answers by ``id`` of the session (dropped with it) and run."""


def find_absent(session: Session, run: int = 0) -> Absent:
    """The recorded input frames that never reached the service, found where the replay of the
    recorded config departs from the recorded outputs, bit for bit.

    A frame the recorder got but the service did not (a link that dropped it) shows in no
    output: the next frame's ``src_seq`` covers it, and the service counts it superseded.  So
    when the service's status counts any (:attr:`TickPlan.superseded`), each departure is
    explained, if it can be, by the frame whose absence from one of the ticks that took several
    frames just before it moves the departure furthest on (trial replays); at most as many as
    the status counted.  The frames found are left out of the replay of every config at the
    recording's rate (:func:`plan_for`).  Cached per session and run; nothing found where the
    status counted none or the recording cannot be held to (:func:`comparable`).
    """
    cache = _ABSENT.get(id(session))
    if cache is None:
        cache = _ABSENT[id(session)] = {}
        weakref.finalize(session, _ABSENT.pop, id(session), None)
    if run in cache:
        return cache[run]
    found = Absent()
    cfg = session.config()
    if cfg is not None:
        axes = resolve_axes(cfg)
        plan = plan_for(session, cfg, axes, run, absent=False)
        if plan.superseded and comparable(session, plan):
            found = _search_absent(session, plan, cfg, axes)
    cache[run] = found
    return found


def comparable(session: Session, plan: TickPlan) -> bool:
    """The plan's commands can be held to the recorded ones bit for bit: the loop's clock on
    its grid, every output and every input frame the service used recorded, one config, no
    warm start."""
    return (session.outputs is not None and session.inputs is not None
            and plan.method == "outputs+clock" and not plan.warm and plan.missing_frames == 0
            and not bool(np.any(plan.emit & (plan.output < 0)))
            and len(session.config_hashes()) <= 1)


def _departure(session: Session, plan: TickPlan, axes: ResolvedAxes, res: EngineResult
               ) -> tuple[int, float] | None:
    """The first row whose command differs from the recorded one (bit for bit, the driven
    axes), and the largest difference from there; None where none does."""
    assert session.outputs is not None
    rows = np.flatnonzero(plan.output >= 0)
    driven = np.asarray(axes.driven, dtype=bool)
    u = res.u[rows][:, driven]
    d = np.abs(u - session.outputs.pos[plan.output[rows]][:, driven])
    bad = np.flatnonzero(np.isfinite(u).all(axis=1) & (d > 0).any(axis=1))
    if not bad.size:
        return None
    return int(rows[bad[0]]), flush_subnormal(float(np.nanmax(d[bad[0]:])))


def departure_note(session: Session, plan: TickPlan, axes: ResolvedAxes, res: EngineResult,
                   run: int = 0) -> str | None:
    """Where the replay of the recorded config (``res``, with the recorded bypass) departs from
    the recorded outputs, in words; None where it does not, or cannot be held to them (other
    notes say why)."""
    if not comparable(session, plan):
        return None
    dep = _departure(session, plan, axes, res)
    if dep is None:
        return None
    assert session.outputs is not None
    row, worst = dep
    seq = int(session.outputs.seq[plan.output[row]])
    t = (int(plan.now_ns[row]) - int(plan.now_ns[0])) / 1e9
    if plan.superseded is None:
        why = ("and the recording cannot tell why (fewer than two status frames in the run: no "
               "count of the input frames the service never took)")
    elif plan.superseded == 0:
        why = ("and nothing in the recording says why (the service's status counted no input "
               "frame superseded)")
    else:
        stopped = find_absent(session, run).stopped or "no recorded config to search with"
        why = (f"which the search for input frames the service never received did not explain "
               f"({stopped}; its status counted {plan.superseded} superseded)")
    return (f"the replay departs from the recorded outputs from output seq {seq} ({t:.3f} s "
            f"into the run; by up to {worst:.3g} in axis units), {why}")


def _search_absent(session: Session, plan: TickPlan, cfg: ServiceConfig, axes: ResolvedAxes
                   ) -> Absent:
    assert session.inputs is not None and plan.frame_lo is not None
    assert plan.superseded is not None
    inp, lo = session.inputs, plan.frame_lo
    dep = _departure(session, plan, axes, run_ticks(plan, inp, cfg))
    took = np.flatnonzero(plan.emit & (plan.frame > lo) & (lo >= 0))
    lookback = round(ABSENT_LOOKBACK_S * 1e9 / plan.period_ns)
    absent: list[int] = []
    budget = ABSENT_BUDGET * plan.rows
    most = min(plan.superseded, ABSENT_MAX)
    stopped: str | None = None
    while dep is not None:
        if len(absent) >= most:
            stopped = (f"it stops at {most} frame{'s' if most > 1 else ''}"
                       if most == ABSENT_MAX else
                       "as many frames found as the status counted")
            break
        first = dep[0]
        best: tuple[float, int] | None = None
        spent = False
        for r in took[(took <= first) & (took >= first - lookback)][::-1]:
            for k in range(int(lo[r]), int(plan.frame[r])):  # not the last: the output names it
                until = first + ABSENT_TRIAL_ROWS
                if budget < until:
                    spent = True
                    break
                if k in absent:
                    continue
                budget -= until
                trial = replace(plan, absent=tuple(sorted([*absent, k])))
                d = _departure(session, trial, axes, run_ticks(trial, inp, cfg, until_row=until))
                reach = np.inf if d is None else float(d[0])
                if reach > first and (best is None or reach > best[0]):
                    best = (reach, k)
        if best is None:
            stopped = ("its trial budget was spent" if spent else
                       "no frame of the ticks before it explains it")
            break
        absent.append(best[1])
        plan = replace(plan, absent=tuple(sorted(absent)))
        dep = _departure(session, plan, axes, run_ticks(plan, inp, cfg))
    note = None
    if absent:
        seqs = ", ".join(str(int(inp.seq[k])) for k in sorted(absent))
        n = len(absent)
        note = (f"{n} input frame{'s' if n > 1 else ''} the recorder holds never reached the "
                f"service (seq {seqs}; its status counted {plan.superseded} superseded): the "
                f"replay goes without {'them' if n > 1 else 'it'}, as the service did")
    return Absent(tuple(sorted(absent)), note, stopped)


def plan_for(session: Session, cfg: ServiceConfig, axes: ResolvedAxes, run: int = 0,
             bypass: str = "recorded", absent: bool = True) -> TickPlan:
    """The plan of ``session`` for ``cfg`` (recorded ticks when the rates agree); with
    ``absent``, the input frames that never reached the service left out
    (:func:`find_absent`)."""
    plan = build_plan(session, cfg, axes, run)
    if plan.method.startswith("outputs") and round(1e9 / cfg.loop.rate_hz) != plan.period_ns:
        plan = build_plan(session, cfg, axes, run, use_outputs=False)
        plan.notes.append(f"loop rate {cfg.loop.rate_hz:g} Hz differs from the recording's: "
                          "ticks rebuilt from the input arrivals")
    if bypass == "config":
        plan.bypass0, plan.bypass_events = None, []
    hashes = session.config_hashes()
    if len(hashes) > 1:
        plan.notes.append(f"the service's config changed during the recording (hashes "
                          f"{', '.join(hashes)}): replayed with one config throughout")
    if absent and plan.superseded and plan.method.startswith("outputs"):
        found = find_absent(session, run)
        plan.absent = found.frames
        if found.note is not None:
            plan.notes.append(found.note)
    return plan


def replay_offline(session: Session, configs: list[tuple[ServiceConfig, str, bool]],
                   run: int = 0, bypass: str = "recorded",
                   progress: Callable[[float], None] | None = None) -> list[ReplayRun]:
    """Replay ``session`` once per config (see the module docstring)."""
    runs = []
    for i, (cfg, label, recorded) in enumerate(configs):
        share = 1.0 / len(configs)

        def sub(x: float, i: int = i, share: float = share) -> None:
            if progress is not None:
                progress((i + 0.9 * x) * share)

        t0 = time.perf_counter()
        axes = resolve_axes(cfg)
        plan = plan_for(session, cfg, axes, run, bypass)
        t1 = time.perf_counter()
        assert session.inputs is not None
        res = run_ticks(plan, session.inputs, cfg, sub)
        if recorded and bypass == "recorded":
            note = departure_note(session, plan, axes, res, run)
            if note is not None:
                plan.notes.append(note)
        elif bypass == "recorded" and (note := bypass_overridden(plan, axes)) is not None:
            plan.notes.append(note)
        t2 = time.perf_counter()
        rep = analyse(session, plan, res, cfg, axes, label, recorded)
        t3 = time.perf_counter()
        if progress is not None:
            progress((i + 1) * share)
        timings: dict[str, Any] = {"plan_s": t1 - t0, "engine_s": t2 - t1, "analysis_s": t3 - t2,
                                   "us_per_tick": res.timings.get("us_per_tick", 0.0)}
        runs.append(ReplayRun(label, cfg, axes, plan, res, rep, recorded, timings))
    return runs


def bypass_overridden(plan: TickPlan, axes: ResolvedAxes) -> str | None:
    """A note naming the axes whose ``bypass`` in the config the recording's bypass switches
    override at the replay's start (``--bypass recorded``), or None."""
    if plan.bypass0 is None:
        return None
    known = recorded_bypass_axes(plan, axes)
    pid = plan.bypass0[:len(AXES)]
    differ = [f"{a} ({'bypassed' if pid[i] else 'compensated'} in the recording, "
              f"{'bypassed' if axes.bypass[i] else 'compensated'} in this config)"
              for i, a in enumerate(AXES) if known[i] and bool(pid[i]) != axes.bypass[i]]
    if not differ:
        return None
    return (f"bypass of {', '.join(differ)}: the recording's bypass switches apply, as they "
            "did live; `--bypass config` replays this config's")


def read_for_replay(path: str | Path) -> Session:
    """A recording as the offline replay needs it: no publish times, no feedback
    accelerations, no other keys, the feedback in :data:`FEEDBACK_WINDOWS` on long files."""
    return read_session(path, other_keys=False, acc=False, publish=False,
                        feedback_windows=FEEDBACK_WINDOWS)


def _replay_pair(path: Path, config: Path | None, run: int, bypass: str
                 ) -> tuple[ReplayRun, str, list[str], float]:
    """One recording with one config, in a worker: ``(run, session name, warnings, read_s)``."""
    t0 = time.perf_counter()
    session = read_for_replay(path)
    read_s = time.perf_counter() - t0
    (rr,) = replay_offline(session, [config_for(session, config)], run, bypass)
    return rr, session.name, session.warnings, read_s


def replay_files(paths: Sequence[Path], configs: Sequence[Path | None], jobs: int = 1,
                 run: int = 0, bypass: str = "recorded",
                 progress: Callable[[float], None] | None = None) -> Iterator[FileReplay]:
    """Replay each recording with each config (``None``: the recorded one), in order.

    ``jobs == 1``: in this process, each recording read once.  ``jobs > 1``: every
    (recording, config) pair in a worker process of a pool of ``jobs`` (``spawn``ed, so the
    workers share no state with the caller), the same results; :attr:`FileReplay.session` is
    then None.

    Raises
    ------
    ConfigError, DataError
        As :func:`config_for`, :func:`~motcomp.record.session.read_session` and
        :func:`~motcomp.replay.plan.build_plan` raise them.
    """
    if not paths or not configs:
        return
    if jobs <= 1:
        for k, path in enumerate(paths):
            t0 = time.perf_counter()
            session = read_for_replay(path)
            read_s = time.perf_counter() - t0

            def sub(x: float, k: int = k) -> None:
                if progress is not None:
                    progress((k + x) / len(paths))

            runs = replay_offline(session, [config_for(session, c) for c in configs], run,
                                  bypass, sub)
            yield FileReplay(Path(path), session.name, session.warnings, runs, read_s,
                             time.perf_counter() - t0, session)
        return
    for c in configs:  # fail early, before any recording is read
        if c is not None:
            load_config(c)
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx) as pool:
        t0 = time.perf_counter()
        futures: list[list[Future[tuple[ReplayRun, str, list[str], float]]]] = [
            [pool.submit(_replay_pair, Path(p), c, run, bypass) for c in configs] for p in paths]
        total = len(paths) * len(configs)
        done = 0
        try:
            for path, fs in zip(paths, futures, strict=True):
                results = []
                for f in fs:
                    results.append(f.result())
                    done += 1
                    if progress is not None:
                        progress(done / total)
                _, name, warnings, _ = results[0]
                yield FileReplay(Path(path), name, warnings, [r[0] for r in results],
                                 max(r[3] for r in results), time.perf_counter() - t0)
        finally:
            for fs in futures:
                for f in fs:
                    f.cancel()
