"""``motcomp record``: record a session's wire traffic to MCAP (its own process)."""

from __future__ import annotations

import argparse
from pathlib import Path

from motcomp.cli._common import add_log_arg, non_negative_float, positive_int, setup_logging
from motcomp.errors import ConfigError
from motcomp.io.zenoh_io import add_zenoh_args, endpoints_from_args

ORDER = 6


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "record", help="record the session's setpoints, outputs, feedback and status to MCAP",
        description="Subscribe to the input, output, feedback and status keys and write every "
                    "message as received to an MCAP file (docs/RECORDING.md). Runs until "
                    "SIGTERM/SIGINT or --duration; the file is finished cleanly either way.")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="FILE.mcap",
                   help="the recording to write")
    p.add_argument("--keys", action="append", default=[], metavar="KEY[,KEY...]",
                   help="keys to record (repeatable or comma-separated; zenoh wildcards allowed)"
                        "; default: the input, output, feedback and status keys")
    p.add_argument("--config", type=Path, metavar="FILE",
                   help="take the four default keys from this service config")
    p.add_argument("--duration", type=non_negative_float, default=0.0, metavar="S",
                   help="stop after S seconds (default: until SIGTERM/SIGINT)")
    p.add_argument("--rotate-mb", type=non_negative_float, default=0.0, metavar="N",
                   help="start a new part FILE-0001.mcap, -0002... every N MB")
    p.add_argument("--rotate-s", type=non_negative_float, default=0.0, metavar="S",
                   help="start a new part every S seconds")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"],
                   help="chunk compression (default: zstd if available, else lz4, else none)")
    p.add_argument("--chunk-kb", type=positive_int, default=1024, metavar="KB",
                   help="chunk size (default 1024 KiB); a chunk is also closed every --flush-s")
    p.add_argument("--flush-s", type=non_negative_float, default=1.0, metavar="S",
                   help="close the open chunk and fsync at least this often (default 1 s): what "
                        "a crash can lose")
    p.add_argument("--status-timeout", type=non_negative_float, default=0.5, metavar="S",
                   help="wait this long for the service's status at start (default 0.5 s; "
                        "0: do not ask)")
    add_zenoh_args(p)
    add_log_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from motcomp.record.recorder import RecordOptions, record
    from motcomp.record.session import DEFAULT_KEYS

    setup_logging(args.log_level)
    if not args.output.parent.is_dir():
        raise ConfigError(f"--output {args.output}: directory {args.output.parent} does not "
                          "exist (create it first)")
    keys = dict(DEFAULT_KEYS)
    if args.config:
        from motcomp.config import load_config

        cfg = load_config(args.config)
        keys = {"input": cfg.input.key, "output": cfg.output.key,
                "feedback": cfg.feedback.key, "status": cfg.status.key}
    chosen = [k.strip() for item in args.keys for k in item.split(",") if k.strip()]
    opts = RecordOptions(out=args.output, keys=chosen or list(keys.values()),
                         duration_s=args.duration, rotate_mb=args.rotate_mb,
                         rotate_s=args.rotate_s, compression=args.compression,
                         chunk_kb=args.chunk_kb, flush_s=args.flush_s,
                         status_key=keys["status"], status_timeout_s=args.status_timeout)
    summary = record(opts, endpoints_from_args(args))
    print(summary.text(), flush=True)
    return 3 if summary.unreached is not None else 0
