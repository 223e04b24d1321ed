"""``motcomp export``: a recording as JSON MCAP for viewers, or as tables for pandas."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from motcomp.cli._common import print_json

ORDER = 8


def register(sub: argparse._SubParsersAction) -> None:
    from motcomp.record.export import FORMATS

    p = sub.add_parser(
        "export", help="write a recording for viewers (JSON MCAP) or pandas (CSV, Parquet)",
        description="Write a recording in the forms other tools read (docs/RECORDING.md): "
                    "--format mcap (default): every message as JSON with a JSON Schema per "
                    "channel, for Foxglove and PlotJuggler (frames that do not fit their key's "
                    "schema on <key>/invalid, as received); csv or parquet: a directory with "
                    "one table per stream (input, output, feedback, status).  The recording "
                    "itself is left as it is (replays need its bytes).")
    p.add_argument("file", type=Path, metavar="FILE.mcap",
                   help="a recording (or the name of a rotated one: FILE-0001.mcap...)")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="OUT",
                   help="the MCAP file to write (--format mcap) or the directory of tables")
    p.add_argument("--format", choices=FORMATS, default="mcap",
                   help="mcap (default), csv or parquet (needs pyarrow: motcomp[parquet])")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar (or lines)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from motcomp.progress import Progress
    from motcomp.record.export import export

    with Progress("exporting", 1.0, quiet=args.quiet or args.format != "mcap") as bar:
        summary = export(args.file, args.output, args.format, bar.update)
    if args.json:
        print_json({"paths": [str(p) for p in summary.paths], "format": summary.format,
                    "counts": summary.counts, "invalid": summary.invalid,
                    "warnings": summary.warnings, "seconds": summary.seconds})
    else:
        print(summary.text())
    sys.stdout.flush()
    return 0
