"""The delay / over-amplification trade-off: optimised designs for a list of peak-gain bounds,
with and without setpoint weights, and the classical rules placed on the same axes.

Each optimised point is :func:`motcomp.design.optimal.optimise` with ``peak_db`` set to the
bound and every other bound as given; each rule point is the rule's gains evaluated by
:func:`motcomp.design.frequency.evaluate`.  A rule may violate the other bounds (in-band gain
error, command amplification): the table says so.  matplotlib is imported only by
:func:`pareto_figure` and :func:`prediction_figure`.

With prediction (:func:`prediction_frontier`), the same peak bounds are swept for a few bounds on
the command gain above ``hf_from_hz``, each point twice: the optimised PID alone, and the chain
with the predictive prefilter (:func:`motcomp.design.predictor.design_predictor`; after the PID,
or alone where the optimiser recommends bypass), under the same bounds.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from motcomp.core.models import P1D, ProcessModel
from motcomp.core.pid import PIDGains
from motcomp.core.tuning import RULE_NAMES, RULES, tune
from motcomp.design.frequency import Evaluation, evaluate
from motcomp.design.optimal import MS_HAIR, Constraints, command_excess_db, optimise
from motcomp.design.predictor import PredictionOptions, PredictorBounds, design_predictor
from motcomp.errors import ConfigError

__all__ = ["ParetoPoint", "ParetoResult", "PredictionPoint", "pareto", "pareto_figure",
           "pareto_json", "pareto_markdown", "prediction_figure", "prediction_frontier",
           "prediction_markdown"]


@dataclass
class ParetoPoint:
    """One design on the trade-off plane (ms, dB)."""

    label: str
    kind: str  # "optimal", "optimal-plain" or "rule"
    peak_bound_db: float | None
    max_residual_delay_ms: float
    peak_gain_db: float
    peak_gain_hz: float
    gain_error_db: float
    command_excess_db: float
    peak_command_gain: float
    ms: float
    feasible: bool
    gains: PIDGains

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["gains"] = self.gains.to_config()
        return d


@dataclass
class ParetoResult:
    """All points, with what they were computed for."""

    model: P1D
    plant: ProcessModel
    rate_hz: float
    constraints: Constraints
    points: list[ParetoPoint]
    elapsed_s: float


def _point(label: str, kind: str, bound: float | None, gains: PIDGains, ev: Evaluation,
           excess: float, c: Constraints, feasible: bool | None = None) -> ParetoPoint:
    if feasible is None:
        feasible = (ev.stable and ev.gain_error_db <= c.gain_error_db + 0.02
                    and excess <= c.command_excess_db + 0.02
                    and ev.peak_command_gain <= c.max_command_gain * 1.002)
    # the sensitivity as the design report judges it, the optimiser's points included
    feasible = feasible and ev.ms <= c.max_sensitivity + MS_HAIR
    return ParetoPoint(label=label, kind=kind, peak_bound_db=bound,
                       max_residual_delay_ms=ev.max_residual_delay_ms,
                       peak_gain_db=ev.peak_gain_db, peak_gain_hz=ev.peak_gain_hz,
                       gain_error_db=ev.gain_error_db, command_excess_db=excess,
                       peak_command_gain=ev.peak_command_gain, ms=ev.ms, feasible=feasible,
                       gains=gains)


def pareto(plant: ProcessModel, model: P1D | None = None, rate_hz: float = 1000.0,
           bounds: Sequence[float] = (1.0, 3.0, 6.0, 8.0, 10.0),
           constraints: Constraints | None = None, plain: bool = True,
           progress: Callable[[int, int, str], None] | None = None) -> ParetoResult:
    """Optimised designs for each peak bound (setpoint weights, and plain PID if ``plain``) and
    the rules' designs, all on ``plant`` at ``rate_hz``."""
    import time

    t0 = time.perf_counter()
    if not bounds:
        raise ConfigError("pareto needs at least one peak-gain bound")
    c = constraints or Constraints()
    internal = model or plant.to_p1d()
    variants = [("optimal", True)] + ([("optimal-plain", False)] if plain else [])
    total = len(bounds) * len(variants)
    points: list[ParetoPoint] = []
    done = 0
    for bound in sorted(bounds):
        for kind, weights in variants:
            d = optimise(plant, internal, rate_hz, replace(c, peak_db=float(bound)),
                         setpoint_weights=weights)
            label = f"optimal{'' if weights else ', plain PID'}, peak <= {bound:g} dB"
            points.append(_point(label, kind, float(bound), d.gains, d.evaluation,
                                 d.command_excess_db, c, d.feasible))
            done += 1
            if progress is not None:
                progress(done, total, label)
    for rule in RULES:
        try:
            g = tune(rule, internal).gains
        except ConfigError:
            continue
        ev = evaluate(g, internal, plant, rate_hz=rate_hz, band_hz=c.band_hz)
        excess = command_excess_db(g, internal, rate_hz, c.band_hz)
        points.append(_point(RULE_NAMES[rule], "rule", None, g, ev, excess, c))
    return ParetoResult(model=internal, plant=plant, rate_hz=rate_hz, constraints=c,
                        points=points, elapsed_s=time.perf_counter() - t0)


def pareto_json(result: ParetoResult) -> dict[str, Any]:
    return {
        "model": {"kind": result.model.kind, **result.model.params()},
        "plant_spec": result.plant.spec(),
        "rate_hz": result.rate_hz,
        "constraints": result.constraints.as_dict(),
        "points": [p.as_dict() for p in result.points],
        "elapsed_s": result.elapsed_s,
    }


def pareto_markdown(result: ParetoResult) -> str:
    """The table of every point."""
    c = result.constraints
    lo, hi = c.band_hz
    lines = [
        f"# Residual delay vs peak gain: {result.plant.spec()} at {result.rate_hz:g} Hz", "",
        f"Optimised designs: in-band gain error <= {c.gain_error_db:g} dB, command <= "
        f"{c.command_excess_db:+g} dB over the exact inverse in band, max|F| <= "
        f"{c.max_command_gain:g}, Ms <= {c.max_sensitivity:g}, discrete loop stable. Rules: "
        "their own gains, checked against the same bounds.", "",
        f"| design | max residual delay {lo:g}-{hi:g} Hz (ms) | peak gain (dB) | at (Hz) | "
        "in-band gain error (dB) | command over inverse (dB) | max abs(F) | Ms | meets bounds |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for p in result.points:
        lines.append(
            f"| {p.label} | {p.max_residual_delay_ms:.2f} | {p.peak_gain_db:+.2f} | "
            f"{p.peak_gain_hz:.1f} | {p.gain_error_db:.2f} | {p.command_excess_db:+.2f} | "
            f"{p.peak_command_gain:.1f} | {p.ms:.2f} | {'yes' if p.feasible else 'no'} |")
    return "\n".join(lines) + "\n"


def pareto_figure(result: ParetoResult, path: Path) -> Path:
    """Residual delay against peak gain, frontiers and rules, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    styles = {"optimal": ("C1", "o-", "optimised, setpoint weights b, c"),
              "optimal-plain": ("C0", "s--", "optimised, plain PID")}
    for kind, (color, fmt, label) in styles.items():
        pts = [p for p in result.points if p.kind == kind]
        if pts:
            ax.plot([p.peak_gain_db for p in pts], [p.max_residual_delay_ms for p in pts], fmt,
                    color=color, label=label)
            for p in pts:
                ax.annotate(f"<= {p.peak_bound_db:g} dB", (p.peak_gain_db, p.max_residual_delay_ms),
                            textcoords="offset points", xytext=(4, 4), fontsize=7, color=color)
    rules = [p for p in result.points if p.kind == "rule"]
    for i, p in enumerate(rules):
        ax.plot(p.peak_gain_db, p.max_residual_delay_ms, "kx" if p.feasible else "rx", ms=8)
        ax.annotate(p.label, (p.peak_gain_db, p.max_residual_delay_ms),
                    textcoords="offset points", xytext=(5, -12 if i % 2 == 0 else 6), fontsize=8)
    for feasible, mark, text in ((True, "kx", "rule, meets the other bounds"),
                                 (False, "rx", "rule, violates a bound")):
        if any(p.feasible == feasible for p in rules):
            ax.plot([], [], mark, ms=8, label=text)
    top = max(p.max_residual_delay_ms for p in result.points)
    ax.set_ylim(0.0, 1.1 * top)
    lo, hi = result.constraints.band_hz
    ax.set_xlabel("peak gain of the delivered response (dB)")
    ax.set_ylabel(f"max residual phase delay {lo:g}-{hi:g} Hz (ms)")
    ax.set_title(f"{result.plant.spec()} at {result.rate_hz:g} Hz")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


@dataclass
class PredictionPoint:
    """One point of the frontier with and without prediction (ms, dB)."""

    peak_bound_db: float
    hf_bound: float
    kind: str  # "pid" (the optimised PID alone, or bypass) or "prediction"
    series: str  # "pid" or "bypass"
    worst_delay_ms: float
    peak_gain_db: float
    gain_error_db: float
    hf_command_gain: float
    feasible: bool

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def prediction_frontier(plant: ProcessModel, model: P1D | None, rate_hz: float,
                        peak_bounds: Sequence[float], hf_bounds: Sequence[float],
                        constraints: Constraints | None = None,
                        options: PredictionOptions | None = None,
                        progress: Callable[[int, int, str], None] | None = None
                        ) -> list[PredictionPoint]:
    """Worst in-band delay against the peak bound, for each HF command-gain bound, without and
    with the predictive prefilter (see the module docstring)."""
    if not peak_bounds or not hf_bounds:
        raise ConfigError("the prediction frontier needs peak-gain and HF-gain bounds")
    c = constraints or Constraints()
    o = options or PredictionOptions(mode="on")
    internal = model or plant.to_p1d()
    out: list[PredictionPoint] = []
    total = len(peak_bounds) * len(hf_bounds)
    for hf in sorted(hf_bounds):
        for peak in sorted(peak_bounds):
            ci = replace(c, peak_db=float(peak), hf_command_gain=float(hf))
            d = optimise(plant, internal, rate_hz, ci)
            ev = d.evaluation
            bypass = d.recommend_bypass
            series = "bypass" if bypass else "pid"
            if bypass:  # the platform alone
                ev = evaluate(None, None, plant, rate_hz=rate_hz, band_hz=c.band_hz,
                              hf_from_hz=c.hf_from_hz)
            out.append(PredictionPoint(
                peak_bound_db=float(peak), hf_bound=float(hf), kind="pid", series=series,
                worst_delay_ms=ev.max_residual_delay_ms, peak_gain_db=ev.peak_gain_db,
                gain_error_db=ev.gain_error_db, hf_command_gain=ev.hf_command_gain,
                feasible=bypass or d.feasible))
            try:
                pd = design_predictor(plant, rate_hz,
                                      series=None if bypass else (d.gains, internal),
                                      constraints=PredictorBounds.from_constraints(ci),
                                      order=o.order, pole_hz=o.pole_hz,
                                      step_rise_s=o.step_rise_s, overshoot=o.overshoot)
                k = pd.check
                out.append(PredictionPoint(
                    peak_bound_db=float(peak), hf_bound=float(hf), kind="prediction",
                    series=series, worst_delay_ms=k.max_delay_ms, peak_gain_db=k.peak_gain_db,
                    gain_error_db=k.gain_error_db, hf_command_gain=k.hf_command_gain,
                    feasible=True))
            except ConfigError:
                pass
            if progress is not None:
                progress(len({(p.peak_bound_db, p.hf_bound) for p in out}), total,
                         f"peak {peak:g} dB, HF {hf:g}x")
    return out


def prediction_markdown(points: Sequence[PredictionPoint], band_hz: tuple[float, float]
                        ) -> str:
    """The frontier with and without prediction as a table."""
    lo, hi = band_hz
    lines = ["", "## With and without the predictive prefilter", "",
             f"| HF bound | peak bound (dB) | worst delay {lo:g}-{hi:g} Hz without (ms) | with "
             "(ms) | peak with (dB) | HF gain with | series |", "|---|---|---|---|---|---|---|"]
    pid = {(p.hf_bound, p.peak_bound_db): p for p in points if p.kind == "pid"}
    pred = {(p.hf_bound, p.peak_bound_db): p for p in points if p.kind == "prediction"}
    for key, a in pid.items():
        b = pred.get(key)
        with_ = ("infeasible", "-", "-") if b is None else (
            f"{b.worst_delay_ms:.2f}", f"{b.peak_gain_db:+.2f}", f"{b.hf_command_gain:.2f}")
        lines.append(f"| {key[0]:g} | {key[1]:g} | {a.worst_delay_ms:.2f} | "
                     + " | ".join(with_) + f" | {a.series} |")
    return "\n".join(lines) + "\n"


def prediction_figure(points: Sequence[PredictionPoint], title: str, path: Path) -> Path:
    """Worst delay against the peak bound, one colour per HF bound: dashed without prediction,
    solid with it (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    for i, hf in enumerate(sorted({p.hf_bound for p in points})):
        for kind, fmt, what in (("pid", "s--", "without"), ("prediction", "o-", "with")):
            pts = sorted((p for p in points if p.hf_bound == hf and p.kind == kind),
                         key=lambda p: p.peak_bound_db)
            if pts:
                ax.plot([p.peak_bound_db for p in pts], [p.worst_delay_ms for p in pts], fmt,
                        color=f"C{i}", label=f"{what} prediction, command <= {hf:g}x above "
                                             "the band")
    ax.set_yscale("log")
    ax.set_ylim(bottom=0.01)  # the delay bisection resolves 0.02 ms
    ax.set_xlabel("bound on the peak gain of the delivered response (dB)")
    ax.set_ylabel("worst phase delay in the band (ms; resolved to 0.02)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
