"""Design and evaluation reports: the JSON object, a markdown summary, the config fragment and
the figures.

:func:`design_report` is what ``motcomp design`` prints; :func:`config_fragment` the
``[axes.<name>]`` table it writes with ``--out``, in the service config's own keys;
:func:`evaluation_report` adds the time-domain runs (swept sine, slalom) that ``motcomp
evaluate`` writes with its figures.  matplotlib is imported only inside the plotting functions.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from motcomp.core.bandlimit import band_limit_params
from motcomp.core.models import P1D, ProcessModel, parse_model
from motcomp.core.pid import PIDGains
from motcomp.core.saturation import AxisLimits
from motcomp.core.tuning import RULE_NAMES, RULES, check_lag, tune
from motcomp.design import optimal as opt
from motcomp.design.frequency import (
    NOISE_RMS_M,
    Evaluation,
    default_grid,
    evaluate,
    loop_response,
    noise_figures,
)
from motcomp.design.predictor import (
    PredictionOptions,
    PredictorBounds,
    PredictorDesign,
    check_chain,
    design_predictor,
)
from motcomp.design.timedomain import (
    SimulationResult,
    simulate_compensated,
    slalom,
    swept_sine,
)
from motcomp.errors import ConfigError
from motcomp.progress import ProgressCallback, Stages

__all__ = ["DESIGN_RULES", "OPTIMAL", "config_fragment", "design_report", "evaluation_report",
           "fragment_markdown", "markdown", "write_figures"]


def _model_json(model: ProcessModel) -> dict[str, Any]:
    return {"kind": model.kind, **model.params()}


def _corrected_json(ev: Evaluation) -> dict[str, Any]:
    return {
        "phase_delay_ms": ev.phase_delay_ms,
        "max_residual_delay_ms": ev.max_residual_delay_ms,
        "max_residual_delay_hz": ev.max_residual_delay_hz,
        "gain_error_db": ev.gain_error_db,
        "peak_gain_db": ev.peak_gain_db,
        "peak_gain_hz": ev.peak_gain_hz,
        "peak_command_gain": ev.peak_command_gain,
        "peak_command_gain_hz": ev.peak_command_gain_hz,
        "hf_command_gain": ev.hf_command_gain,
        "hf_from_hz": ev.hf_from_hz,
        "ms": ev.ms,
        "stable": ev.stable,
        "max_pole_modulus": ev.max_pole_modulus,
    }


OPTIMAL = "optimal"
"""The rule name of the numerically optimised tuning (:mod:`motcomp.design.optimal`)."""
OPTIMAL_NAME = "numerically optimised"
DESIGN_RULES: tuple[str, ...] = (*RULES, OPTIMAL)
"""Every ``--rule`` that :func:`design_report` accepts."""


def with_input_lag(plant: ProcessModel, rate_hz: float, input_lag_s: float,
                   input_band_hz: float) -> tuple[ProcessModel, float]:
    """The plant as the compensator sees it -- the input reconstruction's lag and the band
    limit's delay (``input.band_hz``; 0: none) added to its dead time -- and that lag in all
    (s).

    Raises
    ------
    ConfigError
        If ``input_lag_s`` is not within 0-1 s.
    """
    if not (math.isfinite(input_lag_s) and 0.0 <= input_lag_s <= 1.0):
        raise ConfigError(f"input lag must be 0-1000 ms, got {input_lag_s * 1e3:g} ms")
    band_limit = band_limit_params(input_band_hz, rate_hz)
    if band_limit is not None:
        input_lag_s += band_limit.delay_s
    return (opt.perturb(plant, dead_time_s=input_lag_s) if input_lag_s > 0.0 else plant,
            input_lag_s)


def design_report(plant: ProcessModel, rule: str, rate_hz: float = 1000.0,
                  filter_n: float = 10.0, gains: PIDGains | None = None,
                  model: P1D | None = None, options: opt.OptimalOptions | None = None,
                  progress: ProgressCallback | None = None,
                  input_lag_s: float = 0.0,
                  prediction: PredictionOptions | None = None,
                  input_band_hz: float = 0.0) -> dict[str, Any]:
    """The ``motcomp design --json`` object.

    ``plant`` is the platform; the compensator's internal model is ``model`` or the plant's P1D
    approximation.  ``input_lag_s`` is what the input reconstruction adds before the compensator
    (``input.reconstruction = "smooth"``: about one input period; the status shows it): the
    delivered response is computed, and the delay cancelled, with it added to the platform's
    delay, the internal model staying the platform's.  ``gains`` overrides the rule's gains
    (``rule`` is then only a label).
    ``rule = "optimal"`` runs :func:`motcomp.design.optimal.optimise` with ``options`` (and
    ``progress``) and adds its block under ``"optimal"``; ``filter_n`` does not apply to it.
    ``recommendation`` is ``"bypass"`` or ``"compensate"``: the optimiser's verdict, and for the
    rules the same criteria (worse than uncompensated, a gain under ``min_gain_ms``, a
    delay-dominated model, a low-frequency lag above the plant's).
    ``prediction`` (``rule = "optimal"`` only; default off) adds the predictive prefilter
    (:func:`_predict`): its block under ``"prediction"``, and ``corrected`` then describes the
    whole chain the fragment deploys.
    ``input_band_hz`` is the service's reference band limit (``input.band_hz``,
    :mod:`motcomp.core.bandlimit`; 0: none): its delay is added to ``input_lag_s``, and
    ``"noise"`` gives what input noise does to the deployed command
    (:func:`motcomp.design.frequency.noise_figures`) with and without it.
    """
    internal = model or plant.to_p1d()
    playback_lag_s = input_lag_s
    platform = plant
    plant, input_lag_s = with_input_lag(plant, rate_hz, input_lag_s, input_band_hz)
    band_limit = band_limit_params(input_band_hz, rate_hz)
    warnings: list[str] = []
    std: dict[str, float] = {}
    design: opt.OptimalDesign | None = None
    band = opt.Constraints().band_hz
    pred: dict[str, Any] | None = None
    params = None
    if prediction is not None and prediction.mode != "off" and (gains is not None
                                                                or rule != OPTIMAL):
        if prediction.mode == "on":
            raise ConfigError("prediction is designed with --rule optimal only")
        prediction = None
    if gains is None and rule == OPTIMAL:
        o = options or opt.OptimalOptions()
        band = o.constraints.band_hz
        with_prediction = prediction is not None and prediction.mode != "off"
        stages = Stages(progress, [("optimising the PID", STAGE_PID)]
                        + ([("designing the prefilter", STAGE_PREFILTER)] if with_prediction
                           else []) + [("checking the design", STAGE_CHECK)])
        design = opt.optimise(plant, internal, rate_hz, o.constraints, o.uncertainty,
                              o.setpoint_weights, o.min_gain_ms,
                              stages.start("optimising the PID"))
        gains = design.gains
        warnings = list(design.warnings)
        std = gains.to_standard()
        if prediction is not None and prediction.mode != "off":
            pred, chosen = _predict(plant, internal, rate_hz, design, o, prediction, stages)
            if chosen is not None:
                pid, params = chosen
                if pid is not None and pid.gains != gains:  # a PID re-optimised for the chain
                    # the chain was designed for a compensated axis: it stays one
                    design = replace(pid, recommend_bypass=design.recommend_bypass)
                    gains = pid.gains
                    warnings = list(pid.warnings)
                    std = gains.to_standard()
        stages.start("checking the design")
    elif gains is None:
        tuning = tune(rule, internal, filter_n=filter_n)
        gains = tuning.gains
        warnings = list(tuning.warnings)
        std = tuning.standard
    ev = design.evaluation if design is not None else evaluate(gains, internal, plant,
                                                                rate_hz=rate_hz)
    ev_c = evaluate(gains, internal, plant, rate_hz=None, band_hz=band)
    if params is not None and design is not None:
        c = design.constraints
        # the deployed chain: the PID (none on a bypassed axis) after the prefilter
        series = None if design.recommend_bypass else gains
        ev = evaluate(series, internal, plant, rate_hz=rate_hz, band_hz=band,
                      hf_from_hz=c.hf_from_hz, predictor=params)
        ev_c = evaluate(series, internal, plant, rate_hz=None, band_hz=band,
                        hf_from_hz=c.hf_from_hz, predictor=params)
    warnings += ev.notes
    worse = ev.max_residual_delay_ms > ev.uncorrected_max_delay_ms
    if design is not None:
        bypass = design.recommend_bypass
    else:
        bypass = opt.bypass_recommended(
            ev.max_residual_delay_ms, ev.uncorrected_max_delay_ms, internal,
            (options or opt.OptimalOptions()).min_gain_ms, check_lag(gains, internal) is not None)
    if worse:
        warnings.append(
            f"WARNING: the corrected response lags MORE than the uncorrected one over the band "
            f"({ev.max_residual_delay_ms:.1f} ms vs {ev.uncorrected_max_delay_ms:.1f} ms): "
            "use bypass on this axis."
        )
    out: dict[str, Any] = {
        "model": _model_json(internal),
        "rate_hz": rate_hz,
        "rule": rule,
        "rule_name": RULE_NAMES.get(rule, OPTIMAL_NAME if rule == OPTIMAL else rule),
        "gains": gains.to_config(),
        "standard_form": {k: (v if math.isfinite(v) else None) for k, v in std.items()},
        "uncorrected": {
            "phase_delay_ms": ev.uncorrected_phase_delay_ms,
            "max_delay_ms": ev.uncorrected_max_delay_ms,
            "gain_error_db": ev.uncorrected_gain_error_db,
        },
        "corrected": _corrected_json(ev),
        "continuous": _corrected_json(ev_c),
        "warnings": warnings,
        "recommendation": "bypass" if bypass else "compensate",
    }
    if design is not None:
        out["optimal"] = design.summary()
    if pred is not None:
        out["prediction"] = pred
    if not isinstance(platform, P1D) or platform != internal:
        out["plant"] = _model_json(platform)
        out["plant_spec"] = platform.spec()
    out["model_spec"] = internal.spec()
    out["band_hz"] = list(band)
    out["chain"] = _chain_text(params is not None, bypass)
    out["ms_bound"] = (design.constraints if design is not None
                       else opt.Constraints()).max_sensitivity
    out["input_lag_ms"] = input_lag_s * 1e3
    out["input_playback_lag_ms"] = playback_lag_s * 1e3
    out["input_band_hz"] = input_band_hz
    out["input_band_delay_ms"] = 0.0 if band_limit is None else band_limit.delay_s * 1e3
    deployed = None if bypass else gains
    out["noise"] = {
        "input_rms_um": NOISE_RMS_M * 1e6,
        "with_band_limit": noise_figures(deployed, internal, rate_hz, band_limit, params),
        "without_band_limit": noise_figures(deployed, internal, rate_hz, None, params),
    }
    return out


def _chain_text(prefilter: bool, bypass: bool) -> str:
    """What ``corrected`` describes: the deployed chain, or the PID a bypass leaves unused."""
    if prefilter:
        return "the prefilter alone (PID bypassed)" if bypass else "the prefilter, then the PID"
    return "the PID (not deployed: bypass recommended)" if bypass else "the PID"


def _ms_text(ms: float, bound: float) -> str:
    """``Ms`` with its bound, flagged when at (to the shown digits) or beyond it."""
    if ms > bound + 0.005:
        return f"{ms:.2f} -- BEYOND its bound {bound:g}"
    if ms >= bound - 0.005:
        return f"{ms:.2f} -- AT its bound {bound:g} (the bound limits the design)"
    return f"{ms:.2f} (bound {bound:g})"


PID_HF_LADDER = (10.0, 4.0)
"""HF command-gain bounds the PID is re-optimised for when the prefilter goes in series with
it (``--prediction on`` on a compensated axis): the prefilter then supplies the lead."""


DEFAULT_CHECK_S = 6.0
"""Step simulations of the ``prediction_off`` column last this long (``check_chain``'s default)."""
STAGE_PID = 1.0
"""Estimated weight of one PID optimisation in the progress of a design (a prefilter's design
weighs :data:`STAGE_PREFILTER`, the final checks :data:`STAGE_CHECK`)."""
STAGE_PREFILTER = 1.5
STAGE_CHECK = 0.3


def _predict(plant: ProcessModel, internal: P1D, rate_hz: float, design: opt.OptimalDesign,
             o: opt.OptimalOptions, p: PredictionOptions, stages: Stages
             ) -> tuple[dict[str, Any], tuple[opt.OptimalDesign | None, Any] | None]:
    """The prefilter for an optimised design, and whether it is used.

    Bypassed axis (the optimiser's recommendation): the prefilter alone, least worst delay.
    Compensated axis, ``auto``: the prefilter in series with the optimal PID, least worst delay;
    ``on``: the PID re-optimised for each HF bound of :data:`PID_HF_LADDER` below the given one
    (and as optimised), each followed by the prefilter that holds the optimal PID's worst delay
    with the least total command gain above ``hf_from_hz``; the quietest chain is kept.  With
    ``p.chain_hf_gain``, each is followed instead by the prefilter of least worst delay with the
    chain's command gain above ``hf_from_hz`` within that bound (the prefilter alone on a
    bypassed axis), and the chain of least worst delay is kept; a chain that cannot beat the
    best so far is dropped after one LP (its search stops at the best worst delay).
    ``auto`` uses the prefilter where it gains ``o.min_gain_ms`` of worst delay.  Returns the
    report block and ``(the PID's design or None, PredictorParams)`` if used.
    """
    c = design.constraints
    bounds = PredictorBounds.from_constraints(c)
    chain_hf = p.chain_hf_gain
    if chain_hf is not None:
        bounds = replace(bounds, hf_command_gain=chain_hf)
    ev = design.evaluation
    bypass = design.recommend_bypass
    baseline = ev.uncorrected_max_delay_ms if bypass else ev.max_residual_delay_ms

    def run(series: tuple[PIDGains, P1D] | None, stage: str, max_delay_ms: float | None = None,
            limit_ms: float | None = None, hint_ms: float | None = None) -> PredictorDesign:
        return design_predictor(plant, rate_hz, series=series, constraints=bounds,
                                order=p.order, pole_hz=p.pole_hz, step_rise_s=p.step_rise_s,
                                overshoot=p.overshoot, max_delay_ms=max_delay_ms,
                                delay_limit_ms=limit_ms, delay_hint_ms=hint_ms,
                                progress=stages.start(stage))

    block: dict[str, Any] = {"mode": p.mode, "used": False, "series": "bypass" if bypass
                             else "pid", "baseline_delay_ms": baseline}
    candidates: list[tuple[opt.OptimalDesign | None, float | None, PredictorDesign]] = []
    try:
        if bypass:
            stages.plan([("designing the prefilter alone (axis bypassed)", STAGE_PREFILTER),
                         ("checking the design", STAGE_CHECK)])
            candidates.append((None, None, run(None, "designing the prefilter alone "
                                                     "(axis bypassed)")))
        elif p.mode == "auto":
            if baseline < o.min_gain_ms:
                block["note"] = (f"the optimal PID leaves {baseline:.2f} ms, less than the "
                                 f"{o.min_gain_ms:g} ms a prefilter must gain")
                return block, None
            stages.plan([("designing the prefilter after the PID", STAGE_PREFILTER),
                         ("checking the design", STAGE_CHECK)])
            candidates.append((design, None, run((design.gains, internal),
                                                 "designing the prefilter after the PID")))
        else:
            hfs: list[float | None] = [None] + [h for h in PID_HF_LADDER if h < c.hf_gain]
            plan: list[tuple[str, float]] = []
            for hf in hfs:
                which = "the optimal PID" if hf is None else f"the PID for HF <= {hf:g}"
                if hf is not None:
                    plan.append((f"optimising {which}", STAGE_PID))
                plan.append((f"designing the prefilter after {which}", STAGE_PREFILTER))
            stages.plan([*plan, ("checking the design", STAGE_CHECK)])
            best_ms: float | None = None
            for hf in hfs:
                which = "the optimal PID" if hf is None else f"the PID for HF <= {hf:g}"
                pid_design = design if hf is None else opt.optimise(
                    plant, internal, rate_hz, replace(c, hf_command_gain=hf), None,
                    o.setpoint_weights, o.min_gain_ms, stages.start(f"optimising {which}"))
                series = (pid_design.gains, internal)
                try:
                    if chain_hf is None:
                        d = run(series, f"designing the prefilter after {which}",
                                max_delay_ms=baseline)
                    else:
                        d = run(series, f"designing the prefilter after {which}",
                                limit_ms=best_ms,
                                hint_ms=pid_design.evaluation.max_residual_delay_ms)
                except ConfigError:
                    continue
                candidates.append((pid_design, hf, d))
                if chain_hf is not None:
                    best_ms = min(d.worst_delay_ms, best_ms if best_ms is not None else math.inf)
            if not candidates:
                raise ConfigError(
                    f"prediction: no prefilter in series with the PID holds {baseline:.2f} ms "
                    f"within the bounds" if chain_hf is None else
                    f"prediction: no prefilter in series with the PID keeps the chain's command "
                    f"gain within {chain_hf:g} above {c.hf_from_hz:g} Hz")
    except ConfigError as exc:
        if p.mode == "on":
            raise
        block["note"] = str(exc)
        return block, None
    if chain_hf is None:  # the quietest of the chains holding the PID's delay
        pid, hf, best = min(candidates, key=lambda t: (round(t[2].check.hf_command_gain, 6),
                                                       t[2].worst_delay_ms))
    else:  # the least delay within the chain's bound
        pid, hf, best = min(candidates, key=lambda t: (round(t[2].worst_delay_ms, 3),
                                                       t[2].check.hf_command_gain))
    gain_ms = baseline - best.worst_delay_ms
    used = p.mode == "on" or gain_ms >= o.min_gain_ms
    # what --prediction off deploys: the optimal PID alone (the platform alone if bypassed)
    off = best.without if hf is None else check_chain(
        plant, rate_hz, None if bypass else (design.gains, internal), None, bounds,
        p.step_rise_s, DEFAULT_CHECK_S)
    block.update({
        "used": used,
        "pid_hf_bound": hf,
        "chain_hf_bound": chain_hf,
        "gain_ms": gain_ms,
        "design": best.summary(),
        "without": best.without.as_dict(),  # the chain's own PID (or the platform) alone
        "with": best.check.as_dict(),
        "prediction_off": off.as_dict(),
    })
    if not used:
        block["note"] = (f"the prefilter gains {gain_ms:.2f} ms of worst delay, less than "
                         f"{o.min_gain_ms:g} ms: not used (--prediction on forces it)")
    return block, ((pid, best.params) if used else None)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)  # round-trips exactly
    return json.dumps(value)


def config_fragment(report: dict[str, Any], axis: str, source: str = "") -> str:
    """The ``[axes.<axis>]`` table of a design, in the service config's keys.

    ``model`` is the spec the service reduces (``to_p1d()``) to the internal model the gains
    were designed for: the platform's if it reduces to it, else the internal model; then
    ``bypass = false`` and ``gains`` (:meth:`PIDGains.to_config`, exact), or ``bypass = true``
    alone when the design recommends bypass.  Comments give the design and its metrics.  The
    fragment is meant to be included after the base config (``include = ["motcomp.toml",
    "design.toml"]``); ``motcomp config check`` then shows where each value comes from.

    Examples
    --------
    The rails preset with ZN gives (numbers abridged)::

        # motcomp design: zn, rails preset, 1000 Hz: residual 4.08 ms, peak +11.6 dB (generated)
        [axes.rails_y]
        model = "p1d:K=1,Td=0.0175,Tp1=0.1857683128"
        bypass = false
        gains = { kp = 12.7..., ki_per_s = 364..., kd_s = 0.111..., tf_s = ..., b = 1.0, c = 1.0 }
    """
    c = report["corrected"]
    rule = report["rule"]
    if rule == OPTIMAL and "robust" in report.get("optimal", {}):
        rule = "optimal (robust)"
    where = f", {source}" if source else ""
    lines = [f"# motcomp design: {rule}{where}, {report['rate_hz']:g} Hz: residual "
             f"{c['max_residual_delay_ms']:.2f} ms, peak {c['peak_gain_db']:+.1f} dB (generated)",
             f"# Gains for loop.rate_hz = {report['rate_hz']:g}.  Include this file after the base "
             "config;", "# `motcomp config check` shows which file each value comes from."]
    model_spec = report["model_spec"]
    plant_spec = report.get("plant_spec")
    if plant_spec is not None:
        try:
            reduced = parse_model(plant_spec).to_p1d().spec()
        except ConfigError:
            reduced = None
        if reduced == model_spec:
            model_spec = plant_spec
        else:
            lines.append(f"# Designed on the platform {plant_spec} with this internal model.")
    if report.get("input_lag_ms"):
        band = (f" (of which {report['input_band_delay_ms']:.3g} ms the band limit input.band_hz"
                f" = {report['input_band_hz']:g})" if report.get("input_band_delay_ms") else "")
        lines.append(f"# Designed for an input played back {report['input_lag_ms']:.3g} ms behind "
                     f"its newest sample{band}.")
    noise = report.get("noise")
    if noise is not None:
        n = noise["with_band_limit"]
        lines.append(f"# Input noise: {n['hf_gain']:.2g} um of command per um above "
                     f"{report['corrected']['hf_from_hz']:g} Hz; {noise['input_rms_um']:g} um RMS "
                     f"white -> jerk {n['jerk_rms_m_s3']:.2g} m/s^3 RMS.")
    bypass = report.get("recommendation") == "bypass"
    used = report.get("prediction", {}).get("used", False)
    if bypass:
        lines.append("# Recommendation: bypass (see the design's warnings); no gains"
                     + ("; the predictive prefilter alone." if used else "."))
    if used:
        w = report["prediction"]["with"]
        lines.append(f"# Prediction: worst delay {w['max_delay_ms']:.2f} ms over the band, "
                     f"peak {w['peak_gain_db']:+.1f} dB, command gain {w['hf_command_gain']:.1f}"
                     f" above {report['corrected']['hf_from_hz']:g} Hz.")
    lines += [f"[axes.{axis}]", f"model = {_toml_value(model_spec)}",
              f"bypass = {_toml_value(bypass)}"]
    if not bypass:
        gains = ", ".join(f"{k} = {_toml_value(float(v))}" for k, v in report["gains"].items())
        lines.append(f"gains = {{ {gains} }}")
    pred = report.get("prediction", {})
    if pred.get("used"):
        table = pred["design"]["params"]  # PredictorParams.to_config(), full precision

        def value(v: Any) -> str:
            if isinstance(v, list):
                return "[" + ", ".join(_toml_value(float(x)) for x in v) + "]"
            return _toml_value(float(v))

        body = ", ".join(f"{k} = {value(table[k])}"
                         for k in ("pole_hz", "rate_hz", "band_hz", "coeffs"))
        lines.append(f"prediction = {{ {body} }}")
    else:  # a prefilter an earlier file configures was designed with other gains
        lines.append("predict = false  # this design has no prefilter: an inherited one is unused")
    return "\n".join(lines) + "\n"


def fragment_markdown(fragment: str, written: str | None = None) -> str:
    """The fragment as a paste-able block for the end of the human output."""
    how = (f"Written to `{written}`: include it in the site config after the base config"
           if written else "Paste it into the site config, or write it with `--out FILE` and "
           "include that after the base config")
    return (f"\n## Config fragment\n\n{how} (docs/TUNING.md):\n\n```toml\n{fragment}```\n")


def _sweep_amplitude(limits: AxisLimits, f1_hz: float, requested: float | None) -> float:
    """Largest amplitude whose plain sweep stays within 80 % of every limit at ``f1_hz``."""
    w = 2 * math.pi * f1_hz
    bound = 0.8 * min(float(limits.p_max[0]), -float(limits.p_min[0]),
                      float(limits.v_max[0]) / w, float(limits.a_max[0]) / w**2)
    return bound if requested is None else min(requested, bound)


def evaluation_report(plant: ProcessModel, rule: str, limits: AxisLimits, rate_hz: float = 1000.0,
                      filter_n: float = 10.0, gains: PIDGains | None = None,
                      model: P1D | None = None, sweep_amplitude: float | None = None,
                      options: opt.OptimalOptions | None = None,
                      progress: ProgressCallback | None = None,
                      input_lag_s: float = 0.0, input_band_hz: float = 0.0,
                      ) -> tuple[dict[str, Any], dict[str, SimulationResult]]:
    """Design report plus time-domain runs on a 0.1-3 Hz swept sine and on the slalom (the
    platform delayed by the input's lag and band limit: :func:`design_report`)."""
    internal = model or plant.to_p1d()
    report = design_report(plant, rule, rate_hz, filter_n, gains, internal, options, progress,
                           input_lag_s, input_band_hz=input_band_hz)
    input_lag_s = report["input_lag_ms"] / 1e3
    if input_lag_s > 0.0:
        plant = opt.perturb(plant, dead_time_s=input_lag_s)
    g = PIDGains.from_config(report["gains"])
    amp = _sweep_amplitude(limits, 3.0, sweep_amplitude)
    _, r_sweep = swept_sine(rate_hz, 0.1, 3.0, 60.0, amp)
    _, r_slalom = slalom(rate_hz)
    scale = min(1.0, 0.8 * float(limits.p_max[0]) / 0.5)
    runs = {
        "sweep": simulate_compensated(r_sweep, g, internal, plant, limits, rate_hz),
        "slalom": simulate_compensated(r_slalom * scale, g, internal, plant, limits, rate_hz),
    }
    report["time_domain"] = {
        name: {
            "delay_uncorrected_ms": res.delay_off_s * 1e3,
            "delay_corrected_ms": res.delay_on_s * 1e3,
            "delay_reduction_ms": res.reduction_s * 1e3,
            "saturated_samples_corrected": res.saturated_samples_on,
            "saturated_samples_uncorrected": res.saturated_samples_off,
            "peak_command": float(np.max(np.abs(res.command_on))),
        }
        for name, res in runs.items()
    }
    report["time_domain"]["sweep"]["amplitude"] = amp
    report["limits"] = {"p_min": float(limits.p_min[0]), "p_max": float(limits.p_max[0]),
                        "v_max": float(limits.v_max[0]), "a_max": float(limits.a_max[0])}
    return report, runs


def markdown(report: dict[str, Any]) -> str:
    """A human-readable summary of a design/evaluation report."""
    lines = [f"# motcomp design: {report['rule_name']} at {report['rate_hz']:g} Hz", ""]
    lines.append(f"Internal model: `{report['model_spec']}`")
    if "plant_spec" in report:
        lines.append(f"Platform: `{report['plant_spec']}`")
    g = report["gains"]
    weights = f", b = {g['b']:.6g}, c = {g['c']:.6g}" if (g["b"], g["c"]) != (1.0, 1.0) else ""
    lines += ["", f"Gains (parallel): kp = {g['kp']:.6g}, ki_per_s = {g['ki_per_s']:.6g} 1/s, "
              f"kd_s = {g['kd_s']:.6g} s, tf_s = {g['tf_s']:.6g} s{weights}", ""]
    lo, hi = report.get("band_hz", [0.1, 2.0])
    chain = report.get("chain", "the PID")
    lag = report.get("input_lag_ms") or 0.0
    if lag:
        band_delay = report.get("input_band_delay_ms") or 0.0
        parts = [f"{report.get('input_playback_lag_ms', lag):.2f} ms of playback"]
        if band_delay:
            parts.append(f"{band_delay:.2f} ms of the {report['input_band_hz']:g} Hz band limit")
        lines += [f"Input: played back {lag:.2f} ms behind its newest sample "
                  f"({' + '.join(parts)}), a delay the design cancels with the platform's.", ""]
    lines += ["| phase delay (ms) | " + " | ".join(f"{k} Hz" for k in
                                                  report["uncorrected"]["phase_delay_ms"]) + " |",
              "|---|" + "---|" * len(report["uncorrected"]["phase_delay_ms"])]
    for label, key in (("uncorrected", "uncorrected"), (f"corrected: {chain}", "corrected")):
        block = report[key]
        lines.append(f"| {label} | " + " | ".join(f"{v:.1f}" for v in
                                                  block["phase_delay_ms"].values()) + " |")
    c = report["corrected"]
    what = "input lag, " if lag else ""
    what += {"the prefilter, then the PID": "prefilter, PID",
             "the prefilter alone (PID bypassed)": "prefilter"}.get(chain, "PID")
    lines += [
        "",
        f"## Corrected: {chain}",
        "",
        f"Everything from the reference to the platform's motion ({what}, platform model); "
        "the delays are phase delays, a lead counting as much as a lag.",
        "",
        "| metric | value |",
        "|---|---|",
        f"| worst residual phase delay {lo:g}-{hi:g} Hz ({what}, platform) | "
        f"{c['max_residual_delay_ms']:.2f} ms (at {c['max_residual_delay_hz']:.2f} Hz) |",
        f"| in-band gain error | {c['gain_error_db']:.2f} dB |",
        f"| peak gain | {c['peak_gain_db']:+.2f} dB at {c['peak_gain_hz']:.1f} Hz |",
        f"| peak command amplification abs(u/r) | {c['peak_command_gain']:.1f} at "
        f"{c['peak_command_gain_hz']:.1f} Hz |",
        f"| command amplification at and above {c['hf_from_hz']:g} Hz | "
        f"{c['hf_command_gain']:.1f} |",
        f"| Ms (internal loop) | {_ms_text(c['ms'], report.get('ms_bound', 4.0))} |",
        f"| discrete internal loop | {'stable' if c['stable'] else 'UNSTABLE'} "
        f"(max pole modulus {c['max_pole_modulus']:.4f}) |",
    ]
    if "noise" in report:
        lines += noise_markdown(report)
    if "optimal" in report:
        lines += optimal_markdown(report["optimal"])
    if "prediction" in report:
        lines += prediction_markdown(report["prediction"])
    if "time_domain" in report:
        lines += ["", "| run | delay uncorrected | delay corrected | reduction | "
                      "saturated samples (corr./uncorr.) |", "|---|---|---|---|---|"]
        for name, td in report["time_domain"].items():
            lines.append(f"| {name} | {td['delay_uncorrected_ms']:.1f} ms | "
                         f"{td['delay_corrected_ms']:.1f} ms | {td['delay_reduction_ms']:.1f} ms |"
                         f" {td['saturated_samples_corrected']} / "
                         f"{td['saturated_samples_uncorrected']} |")
    if report["warnings"]:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in report["warnings"]]
    return "\n".join(lines) + "\n"


def noise_markdown(report: dict[str, Any]) -> list[str]:
    """The input-noise table: the command's sensitivity, a designed figure (docs/WIRE.md)."""
    noise = report["noise"]
    w, wo = noise["with_band_limit"], noise["without_band_limit"]
    band = report.get("input_band_hz") or 0.0
    head = (f"band limit {band:g} Hz ({report['input_band_delay_ms']:.2f} ms, cancelled)"
            if band else "no band limit")
    hf = report["corrected"]["hf_from_hz"]
    return [
        "", f"## Input noise ({head})", "",
        f"White noise of {noise['input_rms_um']:g} um RMS on the input values, one value a tick "
        "(float32 rounding at 2.6 m is 0.07 um; epoch-second stamps at 1 m/s, 0.07 um), "
        "through the deployed chain:", "",
        "| figure | with the band limit | without |", "|---|---|---|",
        f"| um of command per um of input above {hf:g} Hz (max) | {w['hf_gain']:.3g} | "
        f"{wo['hf_gain']:.3g} |",
        f"| command noise RMS per input noise RMS | {w['rms_gain']:.3g} | {wo['rms_gain']:.3g} |",
        f"| command acceleration RMS above 5 Hz | {w['acc_hf_rms_m_s2']:.3g} m/s^2 | "
        f"{wo['acc_hf_rms_m_s2']:.3g} m/s^2 |",
        f"| command jerk RMS | {w['jerk_rms_m_s3']:.3g} m/s^3 | {wo['jerk_rms_m_s3']:.3g} m/s^3 |",
    ]


def prediction_markdown(block: dict[str, Any]) -> list[str]:
    """Lines comparing the chain with and without the predictive prefilter."""
    lines = ["", f"## Predictive prefilter (--prediction {block['mode']})", ""]
    if "with" not in block:
        return [*lines, f"Not designed: {block.get('note', '')}"]
    d = block["design"]
    p = d["params"]
    series = "after it, the PID" if block["series"] == "pid" else "alone (axis bypassed)"
    if block.get("pid_hf_bound") is not None:
        series += f" re-optimised for a command gain <= {block['pid_hf_bound']:g} above the band"
    if block.get("chain_hf_bound") is not None:
        series += (f"; least worst delay with the chain's command gain <= "
                   f"{block['chain_hf_bound']:g} above the band")
    alone = "the PID alone" if block["series"] == "pid" else "the platform alone"
    columns = [(alone, block["without"]), ("with the prefilter", block["with"])]
    if block.get("pid_hf_bound") is not None and "prediction_off" in block:
        columns.insert(0, ("the optimal PID alone (--prediction off)", block["prediction_off"]))
        columns[1] = (f"the chain's PID alone (<= {block['pid_hf_bound']:g} above the band)",
                      block["without"])
    lines += [f"{d['order']} Laguerre functions, pole {p['pole_hz']:g} Hz, {series}; "
              f"used: **{'yes' if block['used'] else 'no'}**.", "",
              "| metric | " + " | ".join(name for name, _ in columns) + " |",
              "|---|" + "---|" * len(columns)]
    rows = [("worst phase delay in band", "max_delay_ms", "{:.2f} ms"),
            ("in-band gain error", "gain_error_db", "{:.2f} dB"),
            ("peak gain", "peak_gain_db", "{:+.2f} dB"),
            ("command gain above the band (HF)", "hf_command_gain", "{:.2f}"),
            ("ideal step: overshoot", "ideal_step_overshoot", "{:.1%}")]
    if d["step_rise_s"] is not None:
        rows.append((f"{d['step_rise_s']:g} s min-jerk step: overshoot",
                     "design_step_overshoot", "{:.1%}"))
    for label, key, fmt in rows:
        lines.append(f"| {label} | " + " | ".join(
            "-" if values.get(key) is None else fmt.format(values[key])
            for _, values in columns) + " |")
    if block.get("note"):
        lines += ["", block["note"]]
    return lines


def optimal_markdown(block: dict[str, Any]) -> list[str]:
    """Lines describing the ``optimal`` block of a design report: bounds against values, the
    recommendation and, for a robust design, the member table.  The block describes the PID
    alone (before any prefilter), with the input's lag and the platform model."""
    c, v = block["constraints"], block["values"]
    lo, hi = c["band_hz"]
    kind = "setpoint weights b, c" if block["setpoint_weights"] else "plain PID"
    hf_bound = c.get("hf_command_gain")
    for_chain = ""
    if hf_bound is not None and hf_bound < c["max_command_gain"]:
        for_chain = f", command gain <= {hf_bound:g} from {c['hf_from_hz']:g} Hz"

    def status(value: float, bound: float, hair: float) -> str:
        return "AT the bound" if value >= bound - hair else ""

    lines = [
        "", f"## Optimised PID ({kind}{', robust' if 'robust' in block else ''}{for_chain})",
        "",
        "The PID alone, as the optimiser designed it: the input lag and the platform model "
        "included, no prefilter.", "",
        "| quantity | bound | value | note |", "|---|---|---|---|",
        f"| worst residual phase delay {lo:g}-{hi:g} Hz, the PID alone | minimised | "
        f"{v['max_residual_delay_ms']:.2f} ms | |",
        f"| peak gain of the delivered response | {c['peak_db']:g} dB | "
        f"{v['peak_gain_db']:+.2f} dB | {status(v['peak_gain_db'], c['peak_db'], 0.02)} |",
        f"| in-band gain error | {c['gain_error_db']:g} dB | {v['gain_error_db']:.2f} dB | "
        f"{status(v['gain_error_db'], c['gain_error_db'], 0.02)} |",
        f"| command over the exact inverse, in band | {c['command_excess_db']:+g} dB | "
        f"{v['command_excess_db']:+.2f} dB | "
        f"{status(v['command_excess_db'], c['command_excess_db'], 0.02)} |",
        f"| command amplification max abs(u/r) | {c['max_command_gain']:g} | "
        f"{v['peak_command_gain']:.1f} | "
        f"{status(v['peak_command_gain'], c['max_command_gain'], 0.1)} |",
    ]
    if for_chain:
        lines.append(f"| command amplification from {c['hf_from_hz']:g} Hz | {hf_bound:g} | "
                     f"{v['hf_command_gain']:.1f} | "
                     f"{status(v['hf_command_gain'], hf_bound or 0.0, 0.05)} |")
    ms_flag = ("BEYOND the bound" if v["ms"] > c["max_sensitivity"] + opt.MS_HAIR
               else status(v["ms"], c["max_sensitivity"], opt.MS_HAIR))
    lines += [
        f"| max sensitivity Ms | {c['max_sensitivity']:g} | {v['ms']:.2f} | {ms_flag} |",
        f"| largest pole modulus (discrete loop) | < 1 | {v['max_pole_modulus']:.5f} | |",
        "",
        f"Uncompensated: {block['uncompensated_delay_ms']:.1f} ms; "
        + ("the PID alone gains " if for_chain else "gain ")
        + f"{block['best_gain_ms']:.1f} ms"
        + (" (the chain's figures are above)" if for_chain else "")
        + f". Recommendation: **{block['recommendation']}**"
        + (" (delay-dominated plant)." if block["delay_dominated"] else "."),
    ]
    if "robust" in block:
        rob = block["robust"]
        lines += ["", "| member | floor (ms) | residual (ms) | excess (ms) | peak (dB) | "
                      "ZN residual (ms) | ZN peak (dB) |", "|---|---|---|---|---|---|---|"]
        for m in rob["members"]:
            zr = "-" if m["zn_residual_ms"] is None else f"{m['zn_residual_ms']:.1f}"
            zp = "-" if m["zn_peak_gain_db"] is None else f"{m['zn_peak_gain_db']:+.1f}"
            lines.append(f"| {m['label']} | {m['floor_ms']:.1f} | {m['residual_ms']:.1f} | "
                         f"{m['excess_ms']:+.2f} | {m['peak_gain_db']:+.2f} | {zr} | {zp} |")
        lines += ["", f"Worst member: peak {rob['worst_peak_gain_db']:+.2f} dB, residual delay "
                      f"{rob['worst_excess_ms']:+.2f} ms above its floor."]
    return lines


def write_figures(report: dict[str, Any], runs: dict[str, SimulationResult], plant: ProcessModel,
                  out_dir: Path) -> list[Path]:
    """Bode (uncorrected vs corrected), swept-sine traces and slalom traces as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    rate = float(report["rate_hz"])
    g = report["gains"]
    gains = PIDGains.from_config(g)
    model = P1D(**{k: report["model"][k] for k in ("K", "Td", "Tp1")})
    f = default_grid(rate)
    f = f[(f >= 0.05) & (f <= min(100.0, rate / 2 * 0.99))]
    resp = loop_response(gains, model, plant, np.concatenate([np.geomspace(1e-3, f[0], 200)[:-1],
                                                               f]), rate)
    sel = resp.f >= 0.05
    paths = []

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    ax1.semilogx(resp.f[sel], 20 * np.log10(np.abs(resp.plant[sel])), label="uncorrected P")
    ax1.semilogx(resp.f[sel], 20 * np.log10(np.abs(resp.delivered[sel])), label="corrected P F")
    ax1.semilogx(resp.f[sel], 20 * np.log10(np.abs(resp.command[sel])), ":",
                 label="command |F| = |C/(1+CM)|")
    ax1.axvspan(0.1, 2.0, color="0.9", zorder=0)
    ax1.set_ylabel("gain (dB)")
    ax1.legend(loc="lower left")
    ax1.grid(True, which="both", alpha=0.3)
    ax1.set_title(f"{report['rule_name']} at {rate:g} Hz: delivered response")
    ax2.semilogx(resp.f[sel], resp.phase_delay("plant")[sel] * 1e3, label="uncorrected")
    ax2.semilogx(resp.f[sel], resp.phase_delay("delivered")[sel] * 1e3, label="corrected")
    ax2.axvspan(0.1, 2.0, color="0.9", zorder=0)
    ax2.set_ylim(-100, 300)
    ax2.set_xlabel("frequency (Hz)")
    ax2.set_ylabel("phase delay (ms)")
    ax2.legend()
    ax2.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    paths.append(out_dir / "bode.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    if "sweep" in runs:
        res = runs["sweep"]
        fig = plt.figure(figsize=(10, 8))
        top = fig.add_subplot(3, 1, 1)
        top.plot(res.t, res.reference, "k", lw=0.8, label="setpoint")
        top.plot(res.t, res.response_on, "C1", lw=0.8, label="platform, corrected")
        top.set_title("0.1-3 Hz swept sine")
        top.set_ylabel("position (axis units)")
        top.legend(loc="upper right")
        n = res.t.size
        for col, (a, b, title) in enumerate(((int(0.08 * n), int(0.2 * n), "low frequencies"),
                                             (int(0.85 * n), int(0.9 * n), "high frequencies"))):
            ax = fig.add_subplot(3, 2, 3 + col)
            ax.plot(res.t[a:b], res.reference[a:b], "k", lw=1, label="setpoint")
            ax.plot(res.t[a:b], res.response_on[a:b], "C1", lw=1, label="corrected")
            ax.set_title(title)
            ax.set_xlabel("time (s)")
            if col == 0:
                ax.set_ylabel("position (axis units)")
        bottom = fig.add_subplot(3, 1, 3)
        bottom.plot(res.t, res.reference, "k", lw=0.8, label="setpoint")
        bottom.plot(res.t, res.response_off, "C0", lw=0.8, label="platform, uncorrected")
        bottom.set_xlabel("time (s)")
        bottom.set_ylabel("position (axis units)")
        bottom.legend(loc="upper right")
        fig.tight_layout()
        paths.append(out_dir / "sweep.png")
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)

    if "slalom" in runs:
        res = runs["slalom"]
        fig, ax = plt.subplots(figsize=(10, 4.5))
        ax.plot(res.t, res.reference, "k", lw=1.2, label="setpoint (motion cueing)")
        ax.plot(res.t, res.response_off, "C0", lw=1,
                label=f"platform, uncorrected ({res.delay_off_s * 1e3:.0f} ms)")
        ax.plot(res.t, res.response_on, "C1", lw=1,
                label=f"platform, corrected ({res.delay_on_s * 1e3:.0f} ms)")
        ax.plot(res.t, res.command_on, "C2:", lw=0.8, label="command to the platform")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("lateral position (m)")
        ax.set_title(f"Slalom: delay reduced by {res.reduction_s * 1e3:.0f} ms")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(True, alpha=0.3)
        fig.tight_layout()
        paths.append(out_dir / "slalom.png")
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)
    return paths


def write_report(report: dict[str, Any], out_dir: Path) -> list[Path]:
    """``report.json`` and ``report.md`` in ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    jp = out_dir / "report.json"
    jp.write_text(json.dumps(report, indent=2) + "\n")
    mp = out_dir / "report.md"
    mp.write_text(markdown(report))
    return [jp, mp]
