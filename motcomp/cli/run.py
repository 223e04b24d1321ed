"""``motcomp run``: the real-time compensator service."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from motcomp.cli._common import add_log_arg, setup_logging
from motcomp.config import check_envelope, load_config
from motcomp.io.zenoh_deploy import check_deployment, check_endpoints, service_endpoints
from motcomp.io.zenoh_io import add_zenoh_args, endpoints_from_args

ORDER = 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run", help="run the real-time compensator service",
        description="Subscribe to motion setpoints, compensate the platform's lag at a fixed "
                    "rate, publish corrected setpoints (zenoh and/or CAN). SIGTERM/SIGINT park "
                    "the platform at neutral and exit; SIGHUP reloads the config.")
    p.add_argument("--config", required=True, type=Path, metavar="FILE",
                   help="service config (TOML), e.g. config/motcomp.toml")
    p.add_argument("--allow-writable-envelope", action="store_true",
                   help="start even if a file of the hardware envelope ([envelope]) could be "
                        "changed by others than root and the service user (a source checkout "
                        "on a development machine; never on a platform): logged as a warning")
    add_zenoh_args(p)
    add_log_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from motcomp.runtime.service import Service

    setup_logging(args.log_level)
    cfg = load_config(args.config)
    _, warnings = check_envelope(args.config, cfg, allow_writable=args.allow_writable_envelope)
    for w in warnings:
        logging.getLogger("motcomp.run").warning("%s", w)
    ep = endpoints_from_args(args, service_endpoints(cfg.zenoh, args.config))
    check_deployment(ep.config_file)  # the files it names and their modes: as `config check`
    check_endpoints(ep)  # protocols the zenoh config allows (exit 2, not zenoh's failure)
    return Service(cfg, ep, config_path=args.config).run()
