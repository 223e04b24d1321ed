"""``motcomp demo``: service + simulated platform + motion source, compensation off then on."""

from __future__ import annotations

import argparse
from pathlib import Path

ORDER = 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="run the whole system on this machine and print the delay gained",
        description="Start the simulated platform, the service and a motion source on loopback "
                    "(no router or hardware), drive a slalom, a sweep and hexapod motion with "
                    "compensation off then on, and print per axis the apparent delay and the "
                    "smoothness of the command the platform receives (HF acceleration and jerk "
                    "RMS, share of ticks at the acceleration limit) beside the ideal run's (the "
                    "same motion perfectly timed: the floor), the saturation counts and the loop "
                    "statistics. About 35 s.")
    p.add_argument("--out", type=Path, default=Path("out/demo"), metavar="DIR",
                   help="where to write demo.png (positions, command and its acceleration) and "
                        "the process logs (default: out/demo)")
    p.add_argument("--quiet", action="store_true", help="print only the final table")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from motcomp.demo import report, run_demo

    res = run_demo(args.out, quiet=args.quiet)
    print(report(res))
    return 0 if all(code == 0 for code in res.exit_codes.values()) else 1
