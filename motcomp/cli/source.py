"""``motcomp source``: publish motion setpoints (built-in trajectories or a file)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from motcomp.cli._common import non_negative_float, non_negative_int, positive_int, rate_arg
from motcomp.io.zenoh_io import NoPeerError, add_zenoh_args, endpoints_from_args

ORDER = 4


def register(sub: argparse._SubParsersAction) -> None:
    from motcomp.sim.source import SIGNALS

    p = sub.add_parser(
        "source", help="publish motion setpoints (slalom, sweep, demo, or a file)",
        description="Stand-in for the vehicle model and motion cueing: publish setpoint frames "
                    "at a fixed rate on absolute deadlines.  Waits --wait-peer seconds for a "
                    "subscriber (the service) and exits 3 if none is reachable; shows its "
                    "progress on stderr (a bar on a terminal, a line every 5 s otherwise).")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--signal", choices=SIGNALS,
                   help="built-in motion: slalom (rails_y), sweep (rails_x), demo (rails and "
                        "hexapod, about 12 s)")
    g.add_argument("--file", type=Path,
                   help="msgpack stream of input frames, or CSV t,<axis>... (t,cmd with --axis)")
    p.add_argument("--axis", metavar="AXIS", help="axis of a CSV 'cmd' column")
    p.add_argument("--rate", type=rate_arg, default=1000.0, metavar="HZ",
                   help="publishing rate; files are resampled to it (default 1000 Hz)")
    p.add_argument("--repeat", type=positive_int, default=1, metavar="N",
                   help="play the motion N times (default 1)")
    p.add_argument("--key", default="sim/motion/setpoint",
                   help="key to publish on (default: sim/motion/setpoint, the service's input)")
    p.add_argument("--seq-start", type=non_negative_int, default=0, metavar="N",
                   help="seq of the first frame (default 0)")
    p.add_argument("--lead-in", type=non_negative_float, default=0.5, metavar="S",
                   help="wait after a subscriber is found before publishing (default 0.5 s)")
    p.add_argument("--wait-peer", type=non_negative_float, default=5.0, metavar="S",
                   help="wait up to S seconds for a subscriber of the key, exit 3 if none "
                        "(default 5; 0: publish without checking)")
    p.add_argument("--quiet", action="store_true", help="no progress, only the final summary")
    add_zenoh_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from motcomp.progress import Progress
    from motcomp.sim.source import builtin, load_trajectory, publish

    traj = (builtin(args.signal, args.rate) if args.signal
            else load_trajectory(args.file, args.rate, args.axis))
    total_s = traj.duration_s * args.repeat
    ep = endpoints_from_args(args)
    if not args.quiet:
        print(f"motcomp source: {traj.description or 'motion'}: {traj.samples * args.repeat} "
              f"samples at {traj.rate_hz:g} Hz ({total_s:.1f} s) on {args.key} "
              f"({ep.describe()})", file=sys.stderr, flush=True)
    try:
        with Progress("source", total_s, quiet=args.quiet, unit="s", every_s=5.0) as bar:
            stats = publish(traj, ep, args.key, args.seq_start, args.repeat,
                            lead_in_s=args.lead_in, wait_peer_s=args.wait_peer,
                            progress=bar.update)
    except NoPeerError as exc:
        print(f"motcomp source: {exc}; is the service running and its endpoint right?",
              file=sys.stderr)
        return 3
    print(stats.text(), flush=True)
    return 0
