"""``motcomp design`` and ``motcomp evaluate``: tune the compensator and measure the result."""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

from motcomp.cli._common import add_plant_args, print_json, rate_arg, resolve_plant
from motcomp.core.models import P1D, parse_model
from motcomp.core.tuning import RULES
from motcomp.design.timedomain import limits_for
from motcomp.errors import ConfigError

ORDER = 10


def _add_common(p: argparse.ArgumentParser) -> None:
    add_plant_args(p)
    p.add_argument("--rule", choices=RULES, default="zn",
                   help="tuning rule (default: zn, the paper's Ziegler-Nichols)")
    p.add_argument("--rate", type=rate_arg, default=1000.0, metavar="HZ",
                   help="loop rate for the discrete evaluation (default: 1000)")
    p.add_argument("--filter-n", type=float, default=10.0, metavar="N",
                   help="derivative filter tf = Td_pid / N (default: 10)")
    p.add_argument("--internal", metavar="SPEC",
                   help="internal P1D model of the compensator if it differs from the plant "
                        "(default: the plant, or its P1D approximation)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("design", help="tune the compensator for a plant and print its metrics",
                       description="Compute PID gains with a tuning rule and print the gains and "
                                   "the frequency-domain metrics of the corrected response.")
    _add_common(p)
    p.set_defaults(func=run_design)

    e = sub.add_parser("evaluate", help="design + time-domain runs, figures and a report",
                       description="Design, then simulate the compensator with saturation on a "
                                   "0.1-3 Hz swept sine and a slalom; write PNG figures, "
                                   "report.json and report.md to --out.")
    _add_common(e)
    e.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory")
    e.add_argument("--axis", default=None,
                   help="axis whose limits apply (default: the preset's lateral axis)")
    e.add_argument("--limits", nargs=3, type=float, metavar=("POS", "VEL", "ACC"),
                   help="symmetric limits when no preset is given (default 2.6 2.0 6.0)")
    e.set_defaults(func=run_evaluate)


def _internal(args: argparse.Namespace) -> P1D | None:
    if not args.internal:
        return None
    m = parse_model(args.internal)
    if not isinstance(m, P1D):
        raise ConfigError(f"--internal must be a p1d model, got {m.kind}")
    return m


def run_design(args: argparse.Namespace) -> int:
    from motcomp.design.report import design_report, markdown

    plant, _ = resolve_plant(args)
    report = design_report(plant, args.rule, args.rate, args.filter_n, model=_internal(args))
    if args.json:
        print_json(report)
    else:
        sys.stdout.write(markdown(report))
    for w in report["warnings"]:
        print(w, file=sys.stderr)
    return 0


def run_evaluate(args: argparse.Namespace) -> int:
    from motcomp.design.report import evaluation_report, markdown, write_figures, write_report

    plant, preset = resolve_plant(args)
    if preset is not None:
        axis = args.axis or ("rails_y" if "rails_y" in preset.axes else preset.axes[0])
        limits = preset.axis_limits(axis)
    else:
        pos, vel, acc = args.limits or (2.6, 2.0, 6.0)
        limits = limits_for(pos, vel, acc, (args.axis or "axis",))
    report, runs = evaluation_report(plant, args.rule, limits, args.rate, args.filter_n,
                                     model=_internal(args))
    # write everything into a temporary directory first: nothing half-written on failure
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=args.out, prefix=".tmp-") as tmp:
        tmp_path = Path(tmp)
        written = write_report(report, tmp_path) + write_figures(report, runs, plant, tmp_path)
        for path in written:
            shutil.move(str(path), args.out / path.name)
    if args.json:
        print_json(report)
    else:
        sys.stdout.write(markdown(report))
        print(f"\nwrote {', '.join(str(args.out / p.name) for p in written)}")
    for w in report["warnings"]:
        print(w, file=sys.stderr)
    return 0
