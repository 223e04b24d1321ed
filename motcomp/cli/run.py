"""``motcomp run``: the real-time compensator service."""

from __future__ import annotations

import argparse
from pathlib import Path

from motcomp.cli._common import add_log_arg, setup_logging
from motcomp.config import load_config
from motcomp.io.zenoh_io import ZenohEndpoints, add_zenoh_args, endpoints_from_args

ORDER = 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run", help="run the real-time compensator service",
        description="Subscribe to motion setpoints, compensate the platform's lag at a fixed "
                    "rate, publish corrected setpoints (zenoh and/or CAN). SIGTERM/SIGINT park "
                    "the platform at neutral and exit; SIGHUP reloads the config.")
    p.add_argument("--config", required=True, type=Path, metavar="FILE",
                   help="service config (TOML), e.g. config/motcomp.toml")
    add_zenoh_args(p)
    add_log_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from motcomp.runtime.service import Service

    setup_logging(args.log_level)
    cfg = load_config(args.config)
    z = cfg.zenoh
    zfile = z.config_file
    if zfile and not Path(zfile).is_absolute():  # relative to the service's config file
        zfile = str(args.config.resolve().parent / zfile)
    base = ZenohEndpoints(zfile, tuple(z.connect), tuple(z.listen), z.multicast_scouting)
    return Service(cfg, endpoints_from_args(args, base), config_path=args.config).run()
