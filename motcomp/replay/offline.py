"""Offline replay: a recording, one or two configs, the engine, the report.

::

    read_session -> for each config: build_plan -> run_fast (or run_ticks) -> analyse

The config is the one recorded with the session (attachment ``config.json``) unless another is
given; a config whose loop rate differs from the recording's cannot follow the recorded ticks,
and is replayed on ticks rebuilt from the input arrivals instead.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from motcomp.config import ResolvedAxes, ServiceConfig, config_hash, load_config, resolve_axes
from motcomp.errors import ConfigError
from motcomp.record.session import Session
from motcomp.replay.analysis import ReplayReport, analyse
from motcomp.replay.engine import EngineResult, run_fast, run_ticks
from motcomp.replay.plan import TickPlan, build_plan

__all__ = ["ReplayRun", "config_for", "replay_offline"]


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
    hashes = {st["config"].get("hash") for _, st in session.status
              if isinstance(st.get("config"), dict)} - {None}
    if len(hashes) > 1:
        plan.notes.append(f"the service's config changed during the recording (hashes "
                          f"{', '.join(sorted(map(str, hashes)))}): replayed with one config "
                          "throughout")
    return plan


def replay_offline(session: Session, configs: list[tuple[ServiceConfig, str, bool]],
                   engine: str = "fast", run: int = 0, bypass: str = "recorded",
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
        res = (run_fast(plan, session.inputs, cfg, axes, sub) if engine == "fast"
               else run_ticks(plan, session.inputs, cfg, sub))
        t2 = time.perf_counter()
        rep = analyse(session, plan, res, cfg, axes, label, recorded)
        t3 = time.perf_counter()
        if progress is not None:
            progress((i + 1) * share)
        timings: dict[str, Any] = {"plan_s": t1 - t0, "engine_s": t2 - t1, "analysis_s": t3 - t2,
                                   **res.timings}
        runs.append(ReplayRun(label, cfg, axes, plan, res, rep, recorded, timings))
    return runs
