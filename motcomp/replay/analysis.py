"""What a replay shows: apparent delays, saturation, differences from the recorded outputs.

Apparent delay (:func:`~motcomp.design.timedomain.estimate_delay`, cross-correlation with
sub-sample refinement) of a response behind the motion-cueing reference, per axis, on windows
of :data:`WINDOW_S` (at least :data:`MIN_WINDOW_S`) where the reference moves (peak to peak
above :data:`MIN_MOTION`) and the compensation state does not change, at most
:data:`MAX_WINDOWS` of them spread over the session; the median over windows is reported.

* *simulated*: the config's platform model (``plants``, the full models, not the compensator's
  P1D) driven by the replayed commands (``on``, windows where the replay compensated the axis)
  and by the reference through the limiter alone (``off``: no compensation);
* *recorded*: the recorded feedback position behind the recorded input (each on its own
  timestamps), on windows where the service had compensation on, resp. off (from the bypass
  flags of the recorded outputs).

Saturation follows the service's rule (a position or velocity limit acted, or the command left
its target by more than ``status.saturation_tolerance``), counted in samples and in events
(runs of saturated samples).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from motcomp.config import ResolvedAxes, ServiceConfig
from motcomp.core.axes import AXES
from motcomp.errors import ConfigError
from motcomp.record.frames import FLAG_BITS
from motcomp.record.session import Session
from motcomp.replay.engine import EngineResult, saturated
from motcomp.replay.plan import TickPlan

__all__ = ["MAX_WINDOWS", "MIN_MOTION", "WINDOW_S", "AxisReport", "analyse", "held_commands"]

WINDOW_S = 30.0
MIN_WINDOW_S = 3.0
MAX_WINDOWS = 12
MIN_MOTION = 1e-3
"""Least peak-to-peak motion (m or rad) of a window used for delays."""
SETTLE_S = 5.0
"""After a warm start, the first seconds are left out of the comparison with the recording."""


@dataclass
class AxisReport:
    axis: str
    compensated: bool
    """The replay compensated the axis at least part of the time."""
    delay_off_ms: float = math.nan
    delay_on_ms: float = math.nan
    delay_windows: int = 0
    recorded_off_ms: float = math.nan
    recorded_on_ms: float = math.nan
    saturated_samples: int = 0
    saturation_events: int = 0
    recorded_saturated: int = -1
    max_diff: float = math.nan
    rms_diff: float = math.nan

    @property
    def reduction_ms(self) -> float:
        return self.delay_off_ms - self.delay_on_ms

    @property
    def recorded_reduction_ms(self) -> float:
        return self.recorded_off_ms - self.recorded_on_ms


@dataclass
class ReplayReport:
    label: str
    axes: list[AxisReport]
    ticks: int
    rows: int
    duration_s: float
    compared_ticks: int
    extra: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        for a, rep in zip(out["axes"], self.axes, strict=True):
            a["reduction_ms"] = rep.reduction_ms
            a["recorded_reduction_ms"] = rep.recorded_reduction_ms
        return _finite(out)


def _finite(obj: Any) -> Any:
    """NaN -> None, for strict JSON."""
    if isinstance(obj, float):
        return None if not math.isfinite(obj) else obj
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj


def held_commands(plan: TickPlan, u: np.ndarray) -> np.ndarray:
    """The command the platform holds at each row: the last *emitted* one (catch-up steps send
    nothing)."""
    last = np.maximum.accumulate(np.where(plan.emit, np.arange(plan.rows), 0))
    return u[last]


def _windows(mask: np.ndarray, rate_hz: float) -> list[slice]:
    """Windows of at most WINDOW_S (at least MIN_WINDOW_S) inside the runs where ``mask``
    holds; at most MAX_WINDOWS of them, spread evenly."""
    n = int(WINDOW_S * rate_hz)
    n_min = int(MIN_WINDOW_S * rate_hz)
    m = np.concatenate([[False], mask, [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    out = []
    for lo, hi in zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True):
        for s in range(lo, hi, n):
            e = min(s + n, hi)
            if e - s >= n_min:
                out.append(slice(s, e))
    if len(out) > MAX_WINDOWS:
        pick = np.linspace(0, len(out) - 1, MAX_WINDOWS).round().astype(int)
        out = [out[i] for i in pick]
    return out


def _delay(ref: np.ndarray, resp: np.ndarray, mask: np.ndarray, rate_hz: float
           ) -> tuple[float, int]:
    """Median delay (s) over the windows inside ``mask`` where ``ref`` moves."""
    from motcomp.design.timedomain import estimate_delay

    out = []
    for w in _windows(mask, rate_hz):
        r, y = ref[w], resp[w]
        if not np.all(np.isfinite(r)) or not np.all(np.isfinite(y)) or np.ptp(r) < MIN_MOTION:
            continue
        try:
            out.append(estimate_delay(r, y, rate_hz, max_lag_s=1.0))
        except ConfigError:
            continue
    return (float(np.median(out)) if out else math.nan), len(out)


def _events(mask: np.ndarray) -> int:
    if not mask.size:
        return 0
    return int(np.count_nonzero(mask[1:] & ~mask[:-1]) + int(mask[0]))


def _grid(plan: TickPlan, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows onto a uniform grid at the plan's period (a value held until the next row)."""
    t = (plan.now_ns - plan.now_ns[0]) / 1e9
    h = plan.period_ns / 1e9
    g = np.arange(0.0, t[-1] + h / 2, h)
    k = np.searchsorted(t, g + h * 1e-6, side="right") - 1
    return g, cols[np.maximum(k, 0)]


def analyse(session: Session, plan: TickPlan, res: EngineResult, cfg: ServiceConfig,
            axes: ResolvedAxes, label: str, recorded_config: bool = True) -> ReplayReport:
    """The report of one replay (see the module docstring)."""
    from motcomp.sim.platform import simulate_axis

    rate = 1e9 / plan.period_ns
    sat = saturated(res, cfg.status.saturation_tolerance)
    emit = plan.emit
    u_held = held_commands(plan, res.u)
    # the command without compensation: the reference through the limiter alone
    off = _bypass_only(plan, res, cfg, axes)
    g, ref_g = _grid(plan, res.ref)
    _, on_g = _grid(plan, u_held)
    _, off_g = _grid(plan, off)
    _, byp_g = _grid(plan, res.bypass)
    rec_rows = np.flatnonzero(plan.output >= 0)
    out = session.outputs
    compared = rec_rows
    if plan.warm and rec_rows.size:
        compared = rec_rows[plan.now_ns[rec_rows] - plan.now_ns[0] >= SETTLE_S * 1e9]
    reports = []
    for a, name in enumerate(AXES):
        if not axes.driven[a]:
            continue
        rep = AxisReport(name, compensated=bool((~res.bypass[:, a]).any()))
        rep.saturated_samples = int(np.count_nonzero(sat[emit, a]))
        rep.saturation_events = _events(sat[emit, a])
        if np.ptp(ref_g[:, a]) >= MIN_MOTION:
            y_on = simulate_axis(axes.plants[a], on_g[:, a], rate)
            y_off = simulate_axis(axes.plants[a], off_g[:, a], rate)
            mask = ~byp_g[:, a] if rep.compensated else np.ones(g.size, bool)
            d_on, n_on = _delay(ref_g[:, a], y_on, mask, rate)
            d_off, _ = _delay(ref_g[:, a], y_off, mask, rate)
            rep.delay_on_ms, rep.delay_off_ms, rep.delay_windows = d_on * 1e3, d_off * 1e3, n_on
        if out is not None and rec_rows.size:
            rep.recorded_saturated = int(np.count_nonzero(
                out.flags[plan.output[rec_rows]] & FLAG_BITS[f"sat:{name}"]))
            if compared.size:
                d = res.u[compared, a] - out.pos[plan.output[compared], a]
                d = d[np.isfinite(d)]
                if d.size:
                    rep.max_diff = float(np.max(np.abs(d)))
                    rep.rms_diff = float(np.sqrt(np.mean(d * d)))
        reports.append(rep)
    _recorded_delays(session, reports, rate)
    return ReplayReport(label, reports, int(np.count_nonzero(emit)), plan.rows,
                        float(plan.t_s[-1]) if plan.rows else 0.0, int(compared.size),
                        {"recorded_config": recorded_config})


def _bypass_only(plan: TickPlan, res: EngineResult, cfg: ServiceConfig, axes: ResolvedAxes
                 ) -> np.ndarray:
    """Commands with compensation off on every driven axis (the reference through the
    limiter), held like the service's outputs."""
    from motcomp.replay.engine import _limit, _params, _State

    prms = _params(cfg, axes)
    out = np.empty_like(res.ref)
    for a in range(len(AXES)):
        lo, hi = float(axes.limits.p_min[a]), float(axes.limits.p_max[a])
        st = _State(min(max(float(res.ref[0, a]), lo), hi), prms[a])
        out[:, a], _ = _limit(res.ref[:, a], st, prms[a].lim)
    return held_commands(plan, out)


def _recorded_delays(session: Session, reports: list[AxisReport], rate: float) -> None:
    """Input -> feedback delays on the recorded timestamps, split by the recorded bypass."""
    inp, fb, out = session.inputs, session.feedback, session.outputs
    if inp is None or fb is None or not len(fb) or not len(inp):
        return
    t_in = np.where(np.isnan(inp.t), inp.log_ns / 1e9, inp.t)
    ok_in = inp.reason == 0
    t_fb = fb.t[fb.valid]
    if not t_fb.size or not ok_in.any():
        return
    t0, t1 = max(t_in[ok_in][0], t_fb[0]), min(t_in[ok_in][-1], t_fb[-1])
    if t1 - t0 < 1.0:
        return
    g = np.arange(t0, t1, 1.0 / rate)
    for rep in reports:
        a = AXES.index(rep.axis)
        sel = ok_in & np.isfinite(inp.pos[:, a])
        fsel = fb.valid & np.isfinite(fb.pos[:, a])
        if sel.sum() < 100 or fsel.sum() < 100:
            continue
        ti, vi = t_in[sel], inp.pos[sel, a]
        order = np.argsort(ti, kind="stable")
        r = np.interp(g, ti[order], vi[order])
        tf, vf = fb.t[fsel], fb.pos[fsel, a]
        order = np.argsort(tf, kind="stable")
        y = np.interp(g, tf[order], vf[order])
        if out is not None and len(out) and out.valid.any():
            to = out.t[out.valid]
            byp = (out.flags[out.valid] & FLAG_BITS[f"bypass:{rep.axis}"]) != 0
            k = np.clip(np.searchsorted(to, g, side="right") - 1, 0, to.size - 1)
            bypassed = byp[k]
        else:
            bypassed = np.ones(g.size, bool)
        d_on, _ = _delay(r, y, ~bypassed, rate)
        d_off, _ = _delay(r, y, bypassed, rate)
        rep.recorded_on_ms, rep.recorded_off_ms = d_on * 1e3, d_off * 1e3


def report_text(reps: list[ReplayReport], extra_lines: list[str]) -> str:
    """The table printed by ``motcomp replay``."""
    lines = list(extra_lines)

    def f(x: float, nd: int = 1) -> str:
        return f"{x:.{nd}f}" if math.isfinite(x) else "-"

    for rep in reps:
        lines += ["", f"{rep.label}: {rep.ticks} ticks ({rep.duration_s:.1f} s)", "",
                  f"{'axis':<10} {'delay off':>10} {'on':>8} {'gained':>8} | {'recorded off':>12}"
                  f" {'on':>8} | {'saturated':>9} {'events':>6} | {'max |replay-rec|':>16}",
                  "-" * 100]
        for a in rep.axes:
            note = "" if a.compensated else "  (bypass)"
            lines.append(
                f"{a.axis:<10} {f(a.delay_off_ms):>8}ms {f(a.delay_on_ms):>6}ms "
                f"{f(a.reduction_ms):>6}ms | {f(a.recorded_off_ms):>10}ms "
                f"{f(a.recorded_on_ms):>6}ms | {a.saturated_samples:>9} {a.saturation_events:>6} | "
                f"{(f'{a.max_diff:.2e}' if math.isfinite(a.max_diff) else '-'):>16}{note}")
    return "\n".join(lines)
