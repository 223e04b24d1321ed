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
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from motcomp.config import ResolvedAxes, ServiceConfig, config_hash, load_config, resolve_axes
from motcomp.errors import ConfigError
from motcomp.record.session import Session, read_session
from motcomp.replay.analysis import ReplayReport, analyse
from motcomp.replay.engine import EngineResult, run_ticks
from motcomp.replay.plan import TickPlan, build_plan

__all__ = ["FEEDBACK_WINDOWS", "FileReplay", "ReplayRun", "config_for", "plan_for",
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


def plan_for(session: Session, cfg: ServiceConfig, axes: ResolvedAxes, run: int = 0,
             bypass: str = "recorded") -> TickPlan:
    """The plan of ``session`` for ``cfg`` (recorded ticks when the rates agree)."""
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
        t2 = time.perf_counter()
        rep = analyse(session, plan, res, cfg, axes, label, recorded)
        t3 = time.perf_counter()
        if progress is not None:
            progress((i + 1) * share)
        timings: dict[str, Any] = {"plan_s": t1 - t0, "engine_s": t2 - t1, "analysis_s": t3 - t2,
                                   "us_per_tick": res.timings.get("us_per_tick", 0.0)}
        runs.append(ReplayRun(label, cfg, axes, plan, res, rep, recorded, timings))
    return runs


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
