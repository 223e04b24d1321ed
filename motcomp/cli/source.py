"""``motcomp source``: publish motion setpoints (built-in trajectories or a file)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from motcomp.cli._common import (
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    rate_arg,
    remaining,
)
from motcomp.errors import ConfigError
from motcomp.io.zenoh_io import NoPeerError, add_zenoh_args, endpoints_from_args

ORDER = 4


def stall_range(text: str) -> tuple[float, float]:
    """``A-B`` (or ``A``): stall durations in ms, ``0 < A <= B`` (argparse ``type``)."""
    lo, sep, hi = text.partition("-")
    try:
        a = float(lo)
        b = float(hi) if sep else a
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a range of ms A-B (e.g. 2-15), got "
                                         f"{text!r}") from None
    if not (math.isfinite(a) and math.isfinite(b) and 0 < a <= b):
        raise argparse.ArgumentTypeError(f"expected a range of ms A-B with 0 < A <= B, got "
                                         f"{text!r}")
    return a, b


def register(sub: argparse._SubParsersAction) -> None:
    from motcomp.sim.source import SIGNALS

    p = sub.add_parser(
        "source", help="publish motion setpoints (built-in signals or a file)",
        description="Stand-in for the vehicle model and motion cueing: publish setpoint frames "
                    "at a fixed rate on absolute deadlines.  Waits --wait-peer seconds for a "
                    "subscriber (the service) and exits 3 if none is reachable; shows its "
                    "progress on stderr (a bar on a terminal, a line every 5 s otherwise).  "
                    "--jitter-us, --stall-every-s/--stall-ms and --no-t make it a realistic, "
                    "imperfect sender: each frame's t stays its sample's nominal instant; the "
                    "frames due during such a stall go out in a burst when it ends, as a "
                    "vehicle model catching up does.  A stall this process did not ask for (its "
                    "host kept it from its CPU for a period or more) is not caught up: the "
                    "samples whose instants passed are not sent, as a vehicle model on wall "
                    "time skips them, and the summary counts them ('not sent'); seq counts the "
                    "frames sent.")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--signal", choices=SIGNALS,
                   help="built-in motion: slalom (rails_y, 22 s), lanechange (rails_y: 1.5 m "
                        "in 2 s and back, 8 s), sweep (rails_x, 0.1-3 Hz, 60 s), bandsweep "
                        "(rails_x, 0.1-2 Hz sized for the exact inverse of the rails' model, "
                        "22 s), demo (rails and hexapod, about 12 s), driving (rails_y: "
                        "slaloms and lane changes, 120 s)")
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
    p.add_argument("--jitter-us", type=non_negative_float, default=0.0, metavar="J",
                   help="send each frame late by a random amount in [0, J] us after its nominal "
                        "instant (shorter than a period; default 0)")
    p.add_argument("--stall-every-s", type=positive_float, metavar="S",
                   help="stall now and then, about every S seconds (exponential intervals); "
                        "needs --stall-ms")
    p.add_argument("--stall-ms", type=stall_range, metavar="A-B",
                   help="stall durations, uniform in [A, B] ms (e.g. 2-15); the frames due "
                        "during a stall go out in a burst at its end; needs --stall-every-s")
    p.add_argument("--no-t", action="store_true",
                   help="frames without the t field: the receiver times samples by arrival")
    p.add_argument("--seed", type=non_negative_int, metavar="N",
                   help="seed of the jitter and stall draws (default: a fresh one, reported "
                        "in the summary)")
    p.add_argument("--json", action="store_true",
                   help="print the summary as one JSON object (with t0_s, the nominal instant "
                        "of the first sample) instead of a sentence")
    p.add_argument("--quiet", action="store_true", help="no progress, only the final summary")
    add_zenoh_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from motcomp.progress import Progress
    from motcomp.sim.source import SenderTiming, builtin, load_trajectory, publish

    if (args.stall_every_s is None) != (args.stall_ms is None):
        given, missing = (("--stall-every-s", "--stall-ms") if args.stall_ms is None
                          else ("--stall-ms", "--stall-every-s"))
        raise ConfigError(f"{given} needs {missing}")
    timing = SenderTiming(args.jitter_us, args.stall_every_s or 0.0, args.stall_ms, args.seed)
    try:
        timing.check_rate(args.rate)
    except ConfigError as exc:
        raise ConfigError(f"--jitter-us: {exc}") from None
    traj = (builtin(args.signal, args.rate) if args.signal
            else load_trajectory(args.file, args.rate, args.axis))
    total_s = traj.duration_s * args.repeat
    ep = endpoints_from_args(args)
    if not args.quiet:
        manner = "" if not timing.random and not args.no_t else (
            f", {timing.describe()}{', without t' if args.no_t else ''}")
        print(f"motcomp source: {traj.description or 'motion'}: {traj.samples * args.repeat} "
              f"samples at {traj.rate_hz:g} Hz ({total_s:.1f} s){manner} on {args.key} "
              f"({ep.describe()})", file=sys.stderr, flush=True)
    try:
        with Progress("source", total_s, quiet=args.quiet, unit="s", every_s=5.0) as bar:
            stats = publish(traj, ep, args.key, args.seq_start, args.repeat,
                            lead_in_s=args.lead_in,
                            wait_peer_s=remaining(args.wait_peer) if args.wait_peer > 0 else 0.0,
                            wait_peer_asked_s=args.wait_peer,
                            progress=bar.update, timing=timing, with_t=not args.no_t,
                            warn=lambda text: print(f"motcomp source: {text}", file=sys.stderr,
                                                    flush=True))
            if stats.stopped:
                bar.interrupted()
    except NoPeerError as exc:
        print(f"motcomp source: {exc}; is the service running and its endpoint right?",
              file=sys.stderr)
        return 3
    if args.json:
        print(json.dumps(stats.as_dict()), flush=True)
    else:
        print(stats.text(), flush=True)
    return 0
