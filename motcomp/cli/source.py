"""``motcomp source``: publish motion setpoints (built-in trajectories or a file)."""

from __future__ import annotations

import argparse
from pathlib import Path

from motcomp.cli._common import rate_arg
from motcomp.io.zenoh_io import add_zenoh_args, endpoints_from_args

ORDER = 4


def register(sub: argparse._SubParsersAction) -> None:
    from motcomp.sim.source import SIGNALS

    p = sub.add_parser(
        "source", help="publish motion setpoints (slalom, sweep, demo, or a file)",
        description="Stand-in for the vehicle model and motion cueing: publish setpoint frames "
                    "at a fixed rate on absolute deadlines.")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--signal", choices=SIGNALS)
    g.add_argument("--file", type=Path,
                   help="msgpack stream of input frames, or CSV t,<axis>... (t,cmd with --axis)")
    p.add_argument("--axis", help="axis of a CSV 'cmd' column")
    p.add_argument("--rate", type=rate_arg, default=1000.0, metavar="HZ")
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--key", default="sim/motion/setpoint")
    p.add_argument("--seq-start", type=int, default=0)
    p.add_argument("--lead-in", type=float, default=0.5, metavar="S",
                   help="wait after opening the session before publishing (default 0.5 s)")
    add_zenoh_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from motcomp.sim.source import builtin, load_trajectory, publish

    traj = (builtin(args.signal, args.rate) if args.signal
            else load_trajectory(args.file, args.rate, args.axis))
    end = publish(traj, endpoints_from_args(args), args.key, args.seq_start, args.repeat,
                  lead_in_s=args.lead_in)
    sent = end - args.seq_start
    samples = traj.samples * args.repeat
    print(f"published {sent} frames (seq {args.seq_start}-{end - 1}) of {samples} samples"
          + (f"; {samples - sent} not sent: their instants passed while this process was "
             "stalled" if sent < samples else ""), flush=True)
    return 0
