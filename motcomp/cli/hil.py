"""``motcomp hil``: the simulated platform (hardware-in-the-loop stub)."""

from __future__ import annotations

import argparse

import numpy as np

from motcomp.cli._common import (
    add_log_arg,
    non_negative_float,
    non_negative_int,
    positive_float,
    rate_arg,
    setup_logging,
)
from motcomp.core.axes import AXES
from motcomp.core.models import parse_model
from motcomp.errors import ConfigError
from motcomp.io.zenoh_io import add_zenoh_args, endpoints_from_args

ORDER = 3


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "hil", help="simulated platform: setpoints in, feedback out",
        description="Simulate the platform: consume corrected setpoints (zenoh or CAN), apply "
                    "true per-axis dynamics (default: the rails and hexapod presets), enforce "
                    "hard limits, publish feedback with accelerometer noise. Logs its set-up "
                    "at start and a summary of its counters at exit (SIGTERM/SIGINT).")
    p.add_argument("--rate", type=rate_arg, default=1000.0, metavar="HZ",
                   help="simulation and feedback rate (default 1000 Hz)")
    p.add_argument("--truth", action="append", default=[], metavar="AXIS=SPEC",
                   help="true dynamics of an axis, e.g. rails_y=p1d:K=1,Td=0.02,Tp1=0.2")
    p.add_argument("--drift", action="append", default=[], metavar="AXIS=SPEC@T[+RAMP]",
                   help="the truth of AXIS becomes SPEC T seconds after the start (with +RAMP: "
                        "every parameter moves there linearly over RAMP s), e.g. "
                        "rails_y=p1d:K=1,Td=0.0275,Tp1=0.1858@60; repeatable")
    p.add_argument("--margin", type=non_negative_float, default=0.1, metavar="FRACTION",
                   help="hard limits = preset limits widened by this fraction (default 0.1)")
    p.add_argument("--transport", choices=["zenoh", "can"], default="zenoh",
                   help="where the setpoints come from (default zenoh: platform/setpoint)")
    p.add_argument("--can-interface", default="udp_multicast", metavar="NAME",
                   help="python-can interface with --transport can (default udp_multicast)")
    p.add_argument("--can-channel", default="239.74.163.2", metavar="CHANNEL",
                   help="python-can channel with --transport can (default 239.74.163.2)")
    p.add_argument("--dbc", default="", help="DBC file (default: the shipped motcomp.dbc)")
    p.add_argument("--quiet-sensor", action="store_true",
                   help="no accelerometer noise, tremor, bias or quantisation")
    p.add_argument("--seed", type=non_negative_int, default=0,
                   help="seed of the accelerometer noise (default 0)")
    p.add_argument("--duration", type=positive_float, default=float("inf"), metavar="S",
                   help="stop after S seconds (default: until SIGTERM/SIGINT)")
    add_zenoh_args(p)
    add_log_arg(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from motcomp.sim.hil import HilConfig, default_truth, parse_drift, run_hil
    from motcomp.sim.platform import MAX_DELAY_S, Accelerometer

    setup_logging(args.log_level)
    models, p_min, p_max, v_max = default_truth()
    for item in args.truth:
        axis, sep, spec = item.partition("=")
        if not sep or axis not in AXES:
            raise ConfigError(f"--truth {item!r}: expected AXIS=SPEC with AXIS in {AXES}")
        try:
            model = parse_model(spec)
        except ConfigError as e:
            raise ConfigError(f"--truth {item!r}: {e}") from None
        if model.dead_time_s > MAX_DELAY_S:  # a delay typed in ms, most likely
            raise ConfigError(f"--truth {item!r}: delay {model.dead_time_s:g} s beyond "
                              f"{MAX_DELAY_S:g} s (the range identify searches; times are in "
                              "seconds)")
        models[AXES.index(axis)] = model
    if not 0 <= args.margin <= 10:
        raise ConfigError(f"--margin must be in [0, 10], got {args.margin}")
    span = p_max - p_min
    sensor = Accelerometer() if args.quiet_sensor else Accelerometer(
        noise_std=0.05, bias=0.02, tremor_hz=14.0, tremor_amp=0.03, lsb=0.001)
    cfg = HilConfig(models=models, p_min=p_min - args.margin * span / 2,
                    p_max=p_max + args.margin * span / 2,
                    v_max=np.asarray(v_max) * (1 + args.margin),
                    rate_hz=args.rate, transport=args.transport, accelerometer=sensor,
                    seed=args.seed, can_interface=args.can_interface,
                    can_channel=args.can_channel, dbc=args.dbc, duration_s=args.duration,
                    drifts=[parse_drift(d) for d in args.drift])
    return run_hil(cfg, endpoints_from_args(args))
