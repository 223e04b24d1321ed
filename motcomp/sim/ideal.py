"""The floor of motion quality: a config's tick fed a perfectly timed input stream, offline.

Every sample of the trajectory arrives exactly at its own instant, stamped with it, and the
ticks run exactly on their deadlines (:func:`motcomp.core.tick.step`, what the service runs):
whatever irregularity a live run shows beyond this one comes from the input stream or the
machine, not from the tuning.  Used by the motion-quality benchmark and the demo.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from motcomp.config import ServiceConfig, new_tick, resolve_axes
from motcomp.core.axes import AXES, AXIS_INDEX
from motcomp.core.tick import set_bypass, step
from motcomp.errors import ConfigError
from motcomp.io.wire import encode_input

__all__ = ["IdealRun", "ideal_run"]


@dataclass
class IdealRun:
    """Per axis at each tick (loop rate): reference, command, and whether the limiter acted."""

    rate_hz: float
    t: np.ndarray
    ref: dict[str, np.ndarray]
    u: dict[str, np.ndarray]
    acted: dict[str, np.ndarray]


def ideal_run(cfg: ServiceConfig, pos: Mapping[str, np.ndarray], rate_hz: float,
              bypass: bool | None = None, settle_s: float = 2.0, gap_s: float = 0.0
              ) -> IdealRun:
    """Run ``cfg``'s tick on the trajectory ``pos`` (axis -> samples at ``rate_hz``).

    The first sample is held for ``settle_s`` before the motion starts, sent at ``rate_hz``
    (the start-up blend and the input's period settle), and the returned traces start with the
    motion.  ``gap_s`` > 0 then sends nothing for that long before the motion: the input goes
    stale and its reference is held, and the motion's first sample rejoins it -- the start of a
    session that follows another (rejoin blend, the prediction's calm time and fade-in), as a
    live service meets it.  ``bypass`` True/False forces compensation off/on on every driven
    axis; None keeps the config's.

    Raises
    ------
    ConfigError
        For an unknown axis, an empty trajectory or a non-positive rate.
    """
    if not rate_hz > 0:
        raise ConfigError(f"trajectory rate must be > 0 Hz, got {rate_hz!r}")
    for a in pos:
        if a not in AXIS_INDEX:
            raise ConfigError(f"unknown axis {a!r}; axes: {', '.join(AXES)}")
    cols = {a: np.asarray(v, dtype=float) for a, v in pos.items()}
    n_src = min((v.size for v in cols.values()), default=0)
    if n_src == 0:
        raise ConfigError("empty trajectory")
    axes = resolve_axes(cfg)
    params, state = new_tick(cfg, axes)
    if bypass is not None:
        set_bypass(state, [bypass and d for d in axes.driven])
    loop_hz = cfg.loop.rate_hz
    period_ns = params.period_ns
    settle_ticks = round(settle_s * loop_hz)
    n_ticks = int(n_src / rate_hz * loop_hz)
    src_ns = 1e9 / rate_hz
    first = {a: float(v[0]) for a, v in cols.items()}
    t_out = np.arange(n_ticks) / loop_hz
    idx = [AXIS_INDEX[a] for a in cols]
    ref = {a: np.empty(n_ticks) for a in cols}
    u = {a: np.empty(n_ticks) for a in cols}
    acted = {a: np.zeros(n_ticks, dtype=bool) for a in cols}
    seq = 0
    n_settle = int(settle_ticks * period_ns / src_ns)  # at the trajectory's own rate
    j = -n_settle  # next settling sample (negative instants, before the motion)
    payload: bytes | None
    gap_ticks = round(gap_s * loop_hz)
    for k in range(settle_ticks):
        payload = None
        while j < 0 and (j + n_settle) * src_ns <= k * period_ns + 1e-3:
            payload = encode_input(seq, j / rate_hz - gap_ticks / loop_hz, first)
            seq += 1
            j += 1
        step(state, params, k * period_ns, payload)
    for k in range(settle_ticks, settle_ticks + gap_ticks):  # nothing arrives: stale, held
        step(state, params, k * period_ns, None)
    t0_ns = (settle_ticks + gap_ticks) * period_ns
    j = 0  # next source sample
    for k in range(n_ticks):
        now_ns = t0_ns + k * period_ns
        payload = None
        while j < n_src and j * src_ns <= k * period_ns + 1e-3:
            payload = encode_input(seq, j / rate_hz,
                                   {a: float(v[j]) for a, v in cols.items()})
            seq += 1
            j += 1
        before = list(state.acted)
        out = step(state, params, now_ns, payload)
        for a, i in zip(cols, idx, strict=True):
            ref[a][k] = state.shaper.ref[i]
            u[a][k] = out.u[i]
            acted[a][k] = state.acted[i] != before[i]
    return IdealRun(loop_hz, t_out, ref, u, acted)
