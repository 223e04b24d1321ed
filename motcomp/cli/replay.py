"""``motcomp replay``: replay recorded sessions offline (the service's tick, deterministic) or
one in real time."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from motcomp.cli._common import (
    add_log_arg,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    print_json,
    setup_logging,
)
from motcomp.errors import ConfigError
from motcomp.io.zenoh_io import NoPeerError, add_zenoh_args, endpoints_from_args

if TYPE_CHECKING:
    from motcomp.replay.offline import FileReplay


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay", help="replay a recording through the compensator (offline) or onto zenoh",
        description="Offline (default): feed the recorded inputs through the service's own "
                    "tick with the recorded config (or --config), tick by tick as the service "
                    "did, as fast as possible; report the apparent delay gained, saturation, "
                    "the differences from the recorded outputs and each config's platform model "
                    "against the recorded platform's feedback (docs/REPLAY.md). Several files "
                    "are replayed each on its own. --realtime: republish the recorded inputs of "
                    "one file on zenoh at their recorded timing.")
    p.add_argument("files", type=Path, nargs="+", metavar="FILE.mcap",
                   help="a recording (or the name of a rotated one: FILE-0001.mcap...)")
    p.add_argument("--config", type=Path, metavar="FILE",
                   help="replay with this config instead of the recorded one")
    p.add_argument("--compare", type=Path, metavar="FILE",
                   help="also replay with this config, side by side")
    p.add_argument("--out", type=Path, metavar="DIR", help="write figures here")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--jobs", "-j", type=positive_int, default=1, metavar="N",
                   help="replay the (file, config) pairs in N worker processes (default 1); "
                        "the results are the same, bit for bit")
    p.add_argument("--bypass", choices=["recorded", "config"], default="recorded",
                   help="compensation on/off per axis as the recording shows it (default: "
                        "follows the admin switches) or as the config says")
    p.add_argument("--run", type=non_negative_int, default=0, metavar="N",
                   help="which service run of the recording (the service restarted: output "
                        "seq starts again); default 0")
    p.add_argument("--quiet", action="store_true", help="no progress bar (or lines)")
    g = p.add_argument_group("real time")
    g.add_argument("--realtime", action="store_true",
                   help="republish the recorded inputs on zenoh on their recorded schedule")
    g.add_argument("--timing", choices=["publish", "log"], default="publish",
                   help="schedule from the frames' own t (publish, default) or from the "
                        "recorder's receive times (log)")
    g.add_argument("--speed", type=positive_float, default=1.0, metavar="FACTOR",
                   help="time scale (2: twice as fast; default 1)")
    g.add_argument("--restamp", action="store_true",
                   help="shift each frame's t to the present (the payload is re-encoded)")
    g.add_argument("--key", help="key to republish (default: the recording's input key)")
    g.add_argument("--lead-in", type=non_negative_float, default=0.5, metavar="S",
                   help="wait after a subscriber is found before the first frame (default 0.5 s)")
    g.add_argument("--wait-peer", type=non_negative_float, default=5.0, metavar="S",
                   help="wait up to S seconds for a subscriber of the key, exit 3 if none "
                        "(default 5; 0: send without checking)")
    add_zenoh_args(p)
    add_log_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    if args.realtime:
        if len(args.files) != 1:
            raise ConfigError(f"--realtime republishes one recording, got {len(args.files)}")
        return _realtime(args)
    if args.jobs < 1:
        raise ConfigError(f"--jobs must be at least 1, got {args.jobs}")
    return _offline(args)


def _realtime(args: argparse.Namespace) -> int:
    from motcomp.progress import Progress
    from motcomp.record.mcapio import message_counts, topic_span
    from motcomp.record.session import session_parts
    from motcomp.replay.realtime import input_key, republish

    (path,) = args.files
    parts = session_parts(path)
    key = args.key or input_key(parts[0])
    summaries = [message_counts(p) for p in parts]
    finished = [c for c in summaries if c is not None]
    spans = [s for s in (topic_span(p, key) for p in parts) if s is not None]
    # the progress runs over the frames republished, which may end before the recording
    whole = len(finished) == len(parts)
    duration = (spans[-1][1] - spans[0][0]) / 1e9 if whole and spans else 0.0
    recorded = (finished[-1][""][1] - finished[0][""][0]) / 1e9 if whole else 0.0
    ep = endpoints_from_args(args)
    if not args.quiet:
        span = (f" ({duration:.1f} s of {key} frames" + (
            f" in the {recorded:.1f} s recorded)" if recorded - duration > 0.5 else ")")
            if duration else "")
        print(f"motcomp replay: republishing {path}{span}"
              + f" at {args.speed:g}x ({ep.describe()})", file=sys.stderr, flush=True)
    try:
        with Progress("republishing", duration / args.speed, quiet=args.quiet or not duration,
                      unit="s", every_s=5.0) as bar:
            stats = republish(path, ep, key, args.timing, args.speed, args.restamp,
                              args.lead_in, progress=lambda s: bar.update(s / args.speed),
                              wait_peer_s=args.wait_peer)
    except NoPeerError as exc:
        print(f"motcomp replay: {exc}; is the service running and its endpoint right?",
              file=sys.stderr)
        return 3
    if args.json:
        print_json(stats.__dict__)
    else:
        print(stats.text())
    return 0


def _offline(args: argparse.Namespace) -> int:
    from motcomp.progress import Progress
    from motcomp.replay.offline import replay_files

    configs = [args.config] + ([args.compare] if args.compare is not None else [])
    several = len(args.files) > 1
    summaries = []
    t0 = time.perf_counter()
    last: tuple[FileReplay, dict[str, Any]] | None = None  # its report after the progress' end
    with Progress("replaying", 1.0, quiet=args.quiet, counts=False) as bar:
        for fr in replay_files(args.files, configs, args.jobs, args.run, args.bypass,
                               bar.update):
            summaries.append(_summary(args, fr, several, time.perf_counter() - t0))
            if len(summaries) < len(args.files):
                if not args.json:
                    _print_report(fr, summaries[-1])
            else:
                last = (fr, summaries[-1])
            t0 = time.perf_counter()
    if last is not None and not args.json:
        _print_report(*last)
    if args.json:
        print_json(summaries if several else summaries[0])
    sys.stdout.flush()
    return 0


def _summary(args: argparse.Namespace, fr: FileReplay, several: bool, wall_s: float
             ) -> dict[str, Any]:
    """The JSON summary of one recording's replays (figures written on the way)."""
    base = fr.runs[0]
    figures = []
    if args.out is not None:
        from motcomp.replay.offline import read_for_replay
        from motcomp.replay.plots import write_plots

        session = fr.session if fr.session is not None else read_for_replay(fr.path)
        out = args.out / fr.path.stem if several else args.out
        figures = [str(p) for p in write_plots(out, session, fr.runs)]
    sim_s = base.report.duration_s
    return {
        "file": fr.name,
        "session_s": sim_s,
        "ticks": base.report.ticks,
        "method": base.plan.method,
        "jobs": args.jobs,
        "wall_s": wall_s,
        "read_s": fr.read_s,
        "speedup": sim_s / wall_s if wall_s > 0 else math.inf,
        "warnings": fr.warnings,
        "notes": _notes(fr),
        "rejected_frames": base.result.rejected,
        "runs": [dict(r.report.as_dict(), timings=r.timings, rejected_frames=r.result.rejected)
                 for r in fr.runs],
        "figures": figures,
    }


def _notes(fr: FileReplay) -> list[str]:
    """The notes of every run of a recording, each once, in order."""
    out: list[str] = []
    for r in fr.runs:
        out += [n for n in r.plan.notes if n not in out]
    return out


def _print_report(fr: FileReplay, summary: dict[str, Any]) -> None:
    from motcomp.replay.analysis import report_text

    base = fr.runs[0]
    lines = [f"{fr.name}: {summary['session_s']:.1f} s, {base.report.ticks} ticks, replayed "
             f"from {base.plan.method} in {summary['wall_s']:.2f} s ({summary['speedup']:.0f}x "
             f"real time; reading {fr.read_s:.2f} s)"]
    for r in fr.runs:
        if r.result.rejected:
            lines.append(f"frames rejected by the tick ({r.label}): {r.result.rejected}")
    lines += [f"note: {n}" for n in _notes(fr)]
    print(report_text([r.report for r in fr.runs], lines))
    if any(not r.recorded_config for r in fr.runs):
        print("\n(differences from the recorded outputs are meaningful for the recorded "
              "config only)")
    for f in summary["figures"]:
        print(f"figure: {f}")
    print()
