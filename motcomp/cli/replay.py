"""``motcomp replay``: replay a recorded session offline (fast, deterministic) or in real time."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from motcomp.cli._common import add_log_arg, print_json, setup_logging
from motcomp.errors import ConfigError
from motcomp.io.zenoh_io import add_zenoh_args, endpoints_from_args

ORDER = 7
FEEDBACK_WINDOWS = (12, 40.0)
"""Feedback is read in this many windows of this length (s) on long recordings: the recorded
delays are estimated on windows anyway (motcomp.replay.analysis)."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay", help="replay a recording through the compensator (offline) or onto zenoh",
        description="Offline (default): feed the recorded inputs through the compensator with "
                    "the recorded config (or --config), tick by tick as the service did, as "
                    "fast as possible; report the apparent delay gained, saturation and the "
                    "differences from the recorded outputs (docs/REPLAY.md). --realtime: "
                    "republish the recorded inputs on zenoh at their recorded timing.")
    p.add_argument("file", type=Path, metavar="FILE.mcap",
                   help="a recording (or the name of a rotated one: FILE-0001.mcap...)")
    p.add_argument("--config", type=Path, metavar="FILE",
                   help="replay with this config instead of the recorded one")
    p.add_argument("--compare", type=Path, metavar="FILE",
                   help="also replay with this config, side by side")
    p.add_argument("--out", type=Path, metavar="DIR", help="write figures here")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--engine", choices=["fast", "ticks"], default="fast",
                   help="fast: the offline engine (default); ticks: the service's own tick, "
                        "one by one (slow, the reference)")
    p.add_argument("--bypass", choices=["recorded", "config"], default="recorded",
                   help="compensation on/off per axis as the recording shows it (default: "
                        "follows the admin switches) or as the config says")
    p.add_argument("--run", type=int, default=0, metavar="N",
                   help="which service run of the recording (the service restarted: output "
                        "seq starts again); default 0")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    g = p.add_argument_group("real time")
    g.add_argument("--realtime", action="store_true",
                   help="republish the recorded inputs on zenoh on their recorded schedule")
    g.add_argument("--timing", choices=["publish", "log"], default="publish",
                   help="schedule from the frames' own t (publish, default) or from the "
                        "recorder's receive times (log)")
    g.add_argument("--speed", type=float, default=1.0, help="time scale (2: twice as fast)")
    g.add_argument("--restamp", action="store_true",
                   help="shift each frame's t to the present (the payload is re-encoded)")
    g.add_argument("--key", help="key to republish (default: the recording's input key)")
    g.add_argument("--lead-in", type=float, default=0.5, metavar="S",
                   help="wait after opening zenoh before the first frame (default 0.5 s)")
    add_zenoh_args(p)
    add_log_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    if args.realtime:
        return _realtime(args)
    return _offline(args)


def _realtime(args: argparse.Namespace) -> int:
    from motcomp.progress import Progress
    from motcomp.replay.realtime import republish

    if not (args.speed > 0 and math.isfinite(args.speed)):
        raise ConfigError(f"--speed must be a positive number, got {args.speed}")
    from motcomp.record.mcapio import message_counts
    from motcomp.record.session import session_parts

    parts = session_parts(args.file)
    spans = [c[""] for c in map(message_counts, parts) if c is not None]
    duration = (spans[-1][1] - spans[0][0]) / 1e9 if len(spans) == len(parts) else 0.0
    with Progress("republishing", duration / args.speed, quiet=args.quiet or not duration,
                  unit="s") as bar:
        stats = republish(args.file, endpoints_from_args(args), args.key, args.timing,
                          args.speed, args.restamp, args.lead_in,
                          progress=lambda s: bar.update(s / args.speed))
    if args.json:
        print_json(stats.__dict__)
    else:
        print(stats.text())
    return 0


def _offline(args: argparse.Namespace) -> int:
    from motcomp.progress import Progress
    from motcomp.record.session import read_session
    from motcomp.replay.analysis import report_text
    from motcomp.replay.offline import config_for, replay_offline

    t0 = time.perf_counter()
    with Progress("reading", 1.0, quiet=args.quiet) as bar:
        session = read_session(args.file, other_keys=False, acc=False, publish=False,
                               feedback_windows=FEEDBACK_WINDOWS)
        bar.update(1.0)
    t_read = time.perf_counter() - t0
    configs = [config_for(session, args.config)]
    if args.compare is not None:
        configs.append(config_for(session, args.compare))
    with Progress("replaying", 1.0, quiet=args.quiet) as bar:
        runs = replay_offline(session, configs, args.engine, args.run, args.bypass, bar.update)
    total = time.perf_counter() - t0
    base = runs[0]
    sim_s = base.report.duration_s
    speed = sim_s / total if total > 0 else math.inf
    figures = []
    if args.out is not None:
        from motcomp.replay.plots import write_plots

        figures = [str(p) for p in write_plots(args.out, session, runs)]
    summary = {
        "file": session.name,
        "session_s": sim_s,
        "ticks": base.report.ticks,
        "method": base.plan.method,
        "engine": args.engine,
        "wall_s": total,
        "read_s": t_read,
        "speedup": speed,
        "warnings": session.warnings,
        "notes": base.plan.notes,
        "rejected_frames": base.plan.rejected,
        "runs": [dict(r.report.as_dict(), timings=r.timings) for r in runs],
        "figures": figures,
    }
    if args.json:
        print_json(summary)
        return 0
    lines = [f"{session.name}: {sim_s:.1f} s, {base.report.ticks} ticks, replayed from "
             f"{base.plan.method} in {total:.2f} s ({speed:.0f}x real time; reading "
             f"{t_read:.2f} s)"]
    if base.plan.rejected:
        lines.append(f"frames rejected by the config: {base.plan.rejected}")
    lines += [f"note: {n}" for n in base.plan.notes]
    print(report_text([r.report for r in runs], lines))
    if any(not r.recorded_config for r in runs):
        print("\n(differences from the recorded outputs are meaningful for the recorded "
              "config only)")
    for f in figures:
        print(f"figure: {f}")
    sys.stdout.flush()
    return 0
