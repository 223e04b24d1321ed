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
                    "compensation off then on, and print the apparent delay of each axis, the "
                    "saturation counts and the loop statistics. About 30 s.")
    p.add_argument("--out", type=Path, default=Path("out/demo"), metavar="DIR",
                   help="where to write demo.png and the process logs (default: out/demo)")
    p.add_argument("--quiet", action="store_true", help="print only the final table")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from motcomp.demo import report, run_demo

    res = run_demo(args.out, quiet=args.quiet)
    print(report(res))
    return 0 if all(code == 0 for code in res.exit_codes.values()) else 1
