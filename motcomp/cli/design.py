"""``motcomp design``, ``motcomp evaluate`` and ``motcomp pareto``: tune the compensator, measure
the result, and map the delay / over-amplification trade-off.

``--plant`` takes a preset, a preset file or a config fragment (``motcomp identify``'s
``<axis>.toml``), ``--axis`` the axis (:func:`motcomp.presets.plant_source`); ``design`` prints
and with ``--out`` writes the ``[axes.<axis>]`` table for the service config."""

from __future__ import annotations

import argparse
import os
import re
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from motcomp.cli._common import add_plant_args, non_negative_float, print_json, rate_arg
from motcomp.config import InputConfig
from motcomp.core.bandlimit import BAND_HZ_DEFAULT
from motcomp.core.models import P1D, parse_model
from motcomp.design.optimal import Constraints, OptimalOptions, Uncertainty
from motcomp.design.predictor import DEFAULT_ORDER, DEFAULT_POLE_HZ, PredictionOptions
from motcomp.design.report import DESIGN_RULES, OPTIMAL
from motcomp.design.timedomain import limits_for
from motcomp.errors import ConfigError
from motcomp.presets import DEFAULT_AXIS, PlantSource, list_presets, plant_source
from motcomp.progress import Progress, ProgressCallback

ORDER = 10

_DEFAULTS = Constraints()
_UNCERTAINTY = Uncertainty()


def _add_optimal(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("optimal tuning (--rule optimal, pareto)")
    g.add_argument("--peak-db", type=float, default=_DEFAULTS.peak_db, metavar="DB",
                   help=f"bound on the peak gain of the delivered response "
                        f"(default {_DEFAULTS.peak_db:g} dB)")
    g.add_argument("--gain-db", type=float, default=_DEFAULTS.gain_error_db, metavar="DB",
                   help=f"bound on the in-band gain error (default {_DEFAULTS.gain_error_db:g} dB)")
    g.add_argument("--band", type=float, nargs=2, default=list(_DEFAULTS.band_hz),
                   metavar=("LO", "HI"),
                   help="driver band of the delay and gain-error metrics (default 0.1 2 Hz)")
    g.add_argument("--max-command", type=float, default=_DEFAULTS.max_command_gain,
                   metavar="GAIN",
                   help=f"bound on the command amplification max|u/r| at any frequency "
                        f"(default {_DEFAULTS.max_command_gain:g})")
    g.add_argument("--hf-gain", type=float, default=None, metavar="GAIN",
                   help="bound on the command amplification at and above --hf-from: what "
                        "input jitter and steps reach the platform multiplied by (default: the "
                        "--max-command bound; docs/TUNING.md has the trade-off)")
    g.add_argument("--hf-from", type=float, default=_DEFAULTS.hf_from_hz, metavar="HZ",
                   help=f"lower edge of the range of --hf-gain (default "
                        f"{_DEFAULTS.hf_from_hz:g} Hz)")
    g.add_argument("--command-excess-db", type=float, default=_DEFAULTS.command_excess_db,
                   metavar="DB",
                   help=f"in-band bound on the command relative to the exact inverse of the "
                        f"model (default {_DEFAULTS.command_excess_db:g} dB)")
    g.add_argument("--max-ms", type=float, default=_DEFAULTS.max_sensitivity, metavar="MS",
                   help=f"bound on the internal loop's maximum sensitivity "
                        f"(default {_DEFAULTS.max_sensitivity:g})")
    g.add_argument("--plain-pid", action="store_true",
                   help="keep the setpoint weights at b = c = 1 (a plain PID)")
    g.add_argument("--robust", action="store_true",
                   help="optimise the worst case over the model-uncertainty set")
    g.add_argument("--uncertainty", type=float, nargs=3, metavar=("K_REL", "TD_S", "T_REL"),
                   default=[_UNCERTAINTY.gain_rel, _UNCERTAINTY.dead_time_s,
                            _UNCERTAINTY.time_constant_rel],
                   help="uncertainty set of --robust: relative K error, Td error (s), relative "
                        "time-constant error (default 0.1 0.005 0.2)")
    g.add_argument("--quiet", action="store_true", help="no progress bar on stderr")
    q = p.add_argument_group("predictive prefilter (--rule optimal; docs/TUNING.md "
                             "\"Predictive prefilter\")")
    q.add_argument("--prediction", choices=("auto", "on", "off"), default=None,
                   help="design the prefilter before the compensator: auto (design's default) "
                        "where it gains the minimum worst-delay gain under the same bounds; on "
                        "(pareto: draw the frontier with prediction too); off (pareto's "
                        "default)")
    q.add_argument("--prediction-order", type=int, default=DEFAULT_ORDER, metavar="N",
                   help=f"number of Laguerre functions (default {DEFAULT_ORDER})")
    q.add_argument("--prediction-pole-hz", type=float, default=DEFAULT_POLE_HZ, metavar="HZ",
                   help=f"their pole (default {DEFAULT_POLE_HZ:g} Hz)")
    q.add_argument("--chain-hf-gain", type=float, default=None, metavar="GAIN",
                   help="with --prediction on: bound the whole chain's command gain at and above "
                        "--hf-from to GAIN (um of command per um of input noise) and minimise "
                        "its worst delay within it (default: hold the optimal PID's worst delay "
                        "with the least command gain)")
    q.add_argument("--step-rise-s", type=non_negative_float, default=None, metavar="S",
                   help="bound the delivered response's overshoot on a minimum-jerk step of this "
                        "rise time (0: the ideal step; default: no step bound)")
    q.add_argument("--overshoot", type=non_negative_float, default=0.05, metavar="FRAC",
                   help="that bound, as a fraction of the step (default 0.05)")


_AXIS_HELP = (f"the axis: which [axes.NAME] of a --plant fragment to read (needed when it holds "
              f"several), and the section the design is for (default: the fragment's axis, else "
              f"{DEFAULT_AXIS} if the preset has it, else the preset's first)")


def _add_common(p: argparse.ArgumentParser) -> None:
    add_plant_args(p)
    p.add_argument("--axis", default=None, metavar="NAME", help=_AXIS_HELP)
    p.add_argument("--rule", choices=DESIGN_RULES, default="zn",
                   help="tuning rule (default: zn, the paper's Ziegler-Nichols; optimal: "
                        "numerical optimisation, see docs/TUNING.md)")
    p.add_argument("--rate", type=rate_arg, default=1000.0, metavar="HZ",
                   help="loop rate for the discrete evaluation (default: 1000)")
    p.add_argument("--filter-n", type=float, default=10.0, metavar="N",
                   help="derivative filter tf = Td_pid / N of the rules (default: 10)")
    p.add_argument("--internal", metavar="SPEC",
                   help="internal P1D model of the compensator if it differs from the plant "
                        "(default: the plant, or its P1D approximation)")
    _add_input_chain(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    _add_optimal(p)


def _add_input_chain(p: argparse.ArgumentParser) -> None:
    p.add_argument("--input-lag-ms", type=non_negative_float, default=None, metavar="MS",
                   help="lag of the input reconstruction before the compensator, cancelled "
                        "with the platform's delay: the config's input.playback_lag_s (1.7 ms; "
                        "`motcomp status` shows it as input lag), plus the pairing's phase "
                        "identify reports for a model identified through the stack, or the "
                        "platform's setpoint age for a preset (default: for a fragment whose "
                        "comment names the pairing's phase, input.playback_lag_s' default plus "
                        "that phase; else 0)")
    p.add_argument("--input-band-hz", type=non_negative_float, default=BAND_HZ_DEFAULT,
                   metavar="HZ",
                   help="the service's reference band limit (input.band_hz; default "
                        f"{BAND_HZ_DEFAULT:g}; 0: none): its delay is added to --input-lag-ms "
                        "and cancelled, and the report gives what input noise does to the "
                        "command with it (docs/WIRE.md)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("design", help="tune the compensator for a plant and print its metrics",
                       description="Compute PID gains with a tuning rule (or by numerical "
                                   "optimisation) and print the gains and the frequency-domain "
                                   "metrics of the corrected response.")
    _add_common(p)
    p.add_argument("--out", type=Path, metavar="FILE",
                   help="write the design as a config fragment ([axes.NAME] with model and "
                        "gains, or bypass) to FILE, to include in the site config")
    p.set_defaults(func=run_design)

    e = sub.add_parser("evaluate", help="design + time-domain runs, figures and a report",
                       description="Design, then simulate the compensator with saturation on a "
                                   "0.1-3 Hz swept sine and a slalom; write PNG figures, "
                                   "report.json and report.md to --out.")
    _add_common(e)
    e.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory")
    e.add_argument("--limits", nargs=3, type=float, metavar=("POS", "VEL", "ACC"),
                   help="symmetric limits when --plant gives none (default 2.6 2.0 6.0)")
    e.set_defaults(func=run_evaluate)

    r = sub.add_parser("pareto", help="residual delay vs peak-gain bound, with the rules",
                       description="Optimise for each peak-gain bound (with and without "
                                   "setpoint weights), place ZN, CC, AMIGO and SIMC on the same "
                                   "axes; write pareto.png, pareto.md and pareto.json to --out. "
                                   "With --prediction on, also the worst delay vs the peak bound "
                                   "for each --hf-bounds, with and without the predictive "
                                   "prefilter (pareto_prediction.png).")
    add_plant_args(r)
    r.add_argument("--axis", default=None, metavar="NAME", help=_AXIS_HELP)
    r.add_argument("--rate", type=rate_arg, default=1000.0, metavar="HZ",
                   help="loop rate (default: 1000)")
    r.add_argument("--internal", metavar="SPEC", help="internal P1D model (default: the plant's)")
    r.add_argument("--bounds", type=float, nargs="+", default=[1.0, 3.0, 6.0, 8.0, 10.0],
                   metavar="DB", help="peak-gain bounds (default 1 3 6 8 10 dB)")
    r.add_argument("--hf-bounds", type=float, nargs="+", default=[3.0, 10.0, 60.0],
                   metavar="GAIN",
                   help="with --prediction on: the HF command-gain bounds of the frontier with "
                        "and without prediction (default 3 10 60)")
    _add_input_chain(r)
    r.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory")
    r.add_argument("--json", action="store_true", help="print one JSON object")
    _add_optimal(r)
    r.set_defaults(func=run_pareto)


def _source(args: argparse.Namespace) -> PlantSource:
    """The plant of ``--plant`` or ``--model``.

    Raises
    ------
    ConfigError
        Also when ``--plant`` is given a model spec (``p1d:K=1,...``), naming ``--model``.
    """
    plant = args.plant
    if plant and Path(plant).suffix != ".toml" and re.match(r"^[A-Za-z0-9]+:", plant):
        presets = ", ".join(list_presets())
        raise ConfigError(f"--plant {plant!r}: --plant takes a preset name ({presets}) or a "
                          f".toml file; a model spec goes with --model: --model {plant}")
    source = plant_source(plant, args.model, args.axis)
    if getattr(args, "input_lag_ms", 0.0) is None:
        args.input_lag_ms = default_input_lag_ms(source)
        if source.pairing_phase_ms is not None:
            print(f"input lag {args.input_lag_ms:.2f} ms: input.playback_lag_s's default "
                  f"{PLAYBACK_LAG_DEFAULT_S * 1e3:g} ms plus the pairing's phase "
                  f"{source.pairing_phase_ms:.2f} ms that {source.label} names (give "
                  "--input-lag-ms for a config with another playback lag)", file=sys.stderr)
    return source


PLAYBACK_LAG_DEFAULT_S = InputConfig.model_fields["playback_lag_s"].default
"""The service config's default ``input.playback_lag_s`` (the example config's)."""


def default_input_lag_ms(source: PlantSource) -> float:
    """The input lag (ms) to design ``source`` with when none is given: for a model identified
    through the stack, the playback lag plus the pairing's phase its fragment names (its Td
    holds neither: docs/TUNING.md); else 0."""
    if source.pairing_phase_ms is None:
        return 0.0
    return max(0.0, PLAYBACK_LAG_DEFAULT_S * 1e3 + source.pairing_phase_ms)


def _internal(args: argparse.Namespace) -> P1D | None:
    if not args.internal:
        return None
    m = parse_model(args.internal)
    if not isinstance(m, P1D):
        raise ConfigError(f"--internal must be a p1d model, got {m.kind}")
    return m


def _options(args: argparse.Namespace) -> OptimalOptions:
    constraints = Constraints(
        peak_db=args.peak_db, gain_error_db=args.gain_db, band_hz=tuple(args.band),
        max_command_gain=args.max_command, command_excess_db=args.command_excess_db,
        max_sensitivity=args.max_ms, hf_command_gain=args.hf_gain, hf_from_hz=args.hf_from)
    k_rel, td_s, t_rel = args.uncertainty
    uncertainty = Uncertainty(k_rel, td_s, t_rel) if args.robust else None
    return OptimalOptions(constraints=constraints, uncertainty=uncertainty,
                          setpoint_weights=not args.plain_pid)


def _prediction(args: argparse.Namespace, default: str) -> PredictionOptions:
    return PredictionOptions(mode=args.prediction or default, order=args.prediction_order,
                             pole_hz=args.prediction_pole_hz, step_rise_s=args.step_rise_s,
                             overshoot=args.overshoot, chain_hf_gain=args.chain_hf_gain)


@contextmanager
def _progress(args: argparse.Namespace, label: str) -> Iterator[ProgressCallback | None]:
    """A progress callback drawing on stderr (nothing with --quiet or when not optimising):
    the share done, the stage and what it is doing."""
    if args.quiet or getattr(args, "rule", OPTIMAL) != OPTIMAL:
        yield None
        return
    with Progress(label, total=1.0, counts=False) as bar:
        def update(done: float, total: float, note: str) -> None:
            bar.total = max(float(total), 1e-12)
            bar.update(done, note)

        yield update


def run_design(args: argparse.Namespace) -> int:
    from motcomp.design.report import config_fragment, design_report, fragment_markdown, markdown

    source = _source(args)
    with _progress(args, "optimal tuning") as progress:
        report = design_report(source.model, args.rule, args.rate, args.filter_n,
                               model=_internal(args), options=_options(args), progress=progress,
                               input_lag_s=args.input_lag_ms / 1e3,
                               input_band_hz=args.input_band_hz,
                               prediction=_prediction(args, "auto" if args.rule == "optimal"
                                                      else "off"))
    fragment = config_fragment(report, source.axis, source.label)
    if args.out is not None:
        _write_file_atomically(args.out, fragment)
    if args.json:
        print_json(report)
    else:
        sys.stdout.write(markdown(report))
        sys.stdout.write(fragment_markdown(fragment, str(args.out) if args.out else None))
    for w in report["warnings"]:
        print(w, file=sys.stderr)
    if args.out is not None and args.json:
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _write_file_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file beside it (never half-written).

    Raises
    ------
    ConfigError
        If the file cannot be written.
    """
    tmp: str | None = None
    try:
        with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=f".{path.name}.",
                                         delete=False) as f:
            tmp = f.name
            f.write(text)
        umask = os.umask(0o022)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # as open() would create it, not mkstemp's 0600
        os.replace(tmp, path)
    except OSError as exc:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        raise ConfigError(f"{path}: cannot write: {exc.strerror or exc}") from None


def _write_atomically(out: Path, write: Callable[[Path], list[Path]]) -> list[Path]:
    """Write everything into a temporary directory first: nothing half-written on failure."""
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out, prefix=".tmp-") as tmp:
        written = write(Path(tmp))
        for path in written:
            shutil.move(str(path), out / path.name)
    return [out / p.name for p in written]


def run_evaluate(args: argparse.Namespace) -> int:
    from motcomp.design.report import evaluation_report, markdown, write_figures, write_report

    if args.prediction == "on" or args.chain_hf_gain is not None:
        raise ConfigError("motcomp evaluate does not simulate the predictive prefilter yet: "
                          "use motcomp design for its frequency-domain metrics")
    source = _source(args)
    plant = source.model
    limits = source.limits
    if limits is None:
        pos, vel, acc = args.limits or (2.6, 2.0, 6.0)
        limits = limits_for(pos, vel, acc, (source.axis,))
    with _progress(args, "optimal tuning") as progress:
        report, runs = evaluation_report(plant, args.rule, limits, args.rate, args.filter_n,
                                         model=_internal(args), options=_options(args),
                                         progress=progress, input_lag_s=args.input_lag_ms / 1e3,
                                         input_band_hz=args.input_band_hz)
    written = _write_atomically(
        args.out, lambda tmp: write_report(report, tmp) + write_figures(report, runs, plant, tmp))
    if args.json:
        print_json(report)
    else:
        sys.stdout.write(markdown(report))
        print(f"\nwrote {', '.join(str(p) for p in written)}")
    for w in report["warnings"]:
        print(w, file=sys.stderr)
    return 0


def run_pareto(args: argparse.Namespace) -> int:
    from motcomp.design.pareto import (
        pareto,
        pareto_figure,
        pareto_json,
        pareto_markdown,
        prediction_figure,
        prediction_frontier,
        prediction_markdown,
    )
    from motcomp.design.report import with_input_lag

    if args.chain_hf_gain is not None:
        raise ConfigError("--chain-hf-gain is an option of motcomp design: pareto's frontier "
                          "with prediction spans --hf-bounds")
    platform = _source(args).model
    internal = _internal(args) or platform.to_p1d()
    # the plant as the compensator sees it, as motcomp design takes it
    plant, lag_s = with_input_lag(platform, args.rate, args.input_lag_ms / 1e3,
                                  args.input_band_hz)
    options = _options(args)
    prediction = _prediction(args, "off")
    with _progress(args, "pareto frontier") as progress:
        result = pareto(plant, internal, args.rate, tuple(args.bounds),
                        options.constraints, progress=progress)
    points = []
    if prediction.mode == "on":
        with _progress(args, "frontier with prediction") as progress:
            points = prediction_frontier(plant, internal, args.rate, tuple(args.bounds),
                                         tuple(args.hf_bounds), options.constraints,
                                         prediction, progress)
    chain = (f"The input's lag, {lag_s * 1e3:.2f} ms (--input-lag-ms {args.input_lag_ms:g}, "
             f"the band limit at --input-band-hz {args.input_band_hz:g}), is added to "
             f"{platform.spec()}'s dead time, as motcomp design adds it.\n\n")
    text = chain + pareto_markdown(result) + (
        prediction_markdown(points, options.constraints.band_hz) if points else "")
    data = {"input_lag_ms": lag_s * 1e3, **pareto_json(result)}
    if points:
        data["prediction"] = [p.as_dict() for p in points]

    def write(tmp: Path) -> list[Path]:
        paths = [tmp / "pareto.md", tmp / "pareto.json", tmp / "pareto.png"]
        paths[0].write_text(text)
        import json

        paths[1].write_text(json.dumps(data, indent=2) + "\n")
        pareto_figure(result, paths[2])
        if points:
            paths.append(prediction_figure(points, f"{platform.spec()} at {args.rate:g} Hz, "
                                                   f"input lag {lag_s * 1e3:.2f} ms",
                                           tmp / "pareto_prediction.png"))
        return paths

    written = _write_atomically(args.out, write)
    if args.json:
        print_json(data)
    else:
        sys.stdout.write(text)
        print(f"\nwrote {', '.join(str(p) for p in written)}")
    return 0
