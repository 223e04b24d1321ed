"""``motcomp config check FILE``: validate a service config and print the effective one;
``motcomp config example [NAME]``: print a file shipped with the package (the documented
example config by default)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from motcomp.config import (
    RESTART_KEYS,
    check_envelope,
    config_hash,
    load_config,
    new_tick,
    resolve_axes,
    source_report,
)
from motcomp.core.predictor import PredictorParams
from motcomp.errors import ConfigError
from motcomp.io.zenoh_deploy import check_service_zenoh

ORDER = 5


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="check a service config; print the shipped example",
                       description="Configuration tools.")
    cs = p.add_subparsers(dest="config_command", metavar="ACTION")
    cs.required = True
    c = cs.add_parser("check", help="validate FILE and print the effective config",
                      description="Validate a config (includes merged, every axis resolved, "
                                  "gains checked for stability) and print the effective "
                                  "values; errors name the file, the key and the value "
                                  "(exit 2).")
    c.add_argument("file", type=Path, help="the service config (TOML)")
    c.add_argument("--json", action="store_true", help="print the effective config as JSON")
    c.set_defaults(func=run_check)
    e = cs.add_parser("example", help="print the documented example config (or another "
                                      "shipped file)",
                      description="Print a file shipped with motcomp to stdout: by default the "
                                  "example service config, every key documented "
                                  "(`motcomp config example > site.toml`). --list names the "
                                  "others (plant presets, the CAN DBC, the zenoh access-control "
                                  "example, the systemd unit).")
    e.add_argument("name", nargs="?", default="motcomp.toml", metavar="NAME",
                   help="shipped file to print, as --list names it (default: motcomp.toml)")
    e.add_argument("--list", action="store_true",
                   help="list the shipped files and where they are, print none")
    e.set_defaults(func=run_example)


def run_check(args: argparse.Namespace) -> int:

    cfg = load_config(args.file)
    axes = resolve_axes(cfg)
    # the stability of every gain/model pair, exactly as the service will check it
    new_tick(cfg, axes)
    envelope_lines = check_envelope(args.file, cfg)[0]  # as `motcomp run` does at start
    zenoh_note = check_service_zenoh(cfg.zenoh, args.file)  # as the service opens zenoh
    can_note = []
    if cfg.output.transport in ("can", "both"):  # as the service opens its CAN output
        from motcomp.io.can_io import check_can_output

        can_note = [check_can_output(cfg.output.can, Path(args.file).resolve())]
    effective = cfg.model_dump(mode="json")
    if args.json:
        json.dump({"hash": config_hash(cfg), "config": effective}, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(f"{args.file}: OK (hash {config_hash(cfg)})")
        print(f"loop {cfg.loop.rate_hz:g} Hz, input {cfg.input.key}, output "
              f"{cfg.output.transport} ({cfg.output.key}), admin "
              f"{'on' if cfg.admin.enabled else 'off'}")
        for i, name in enumerate(axes.names):
            if not axes.driven[i]:
                print(f"  {name:<10} not driven (held at neutral)")
                continue
            g = axes.gains[i]
            lim = axes.limits
            print(f"  {name:<10} {'BYPASS ' if axes.bypass[i] else ''}model {axes.plants[i]} "
                  f"-> internal {axes.models[i]}; kp={g.kp:.4g} ki={g.ki:.4g} kd={g.kd:.4g} "
                  f"tf={g.tf:.4g}; pos [{lim.p_min[i]:g}, {lim.p_max[i]:g}] vel "
                  f"{lim.v_max[i]:g} acc {lim.a_max[i]:g}"
                  + _prediction_text(axes.prediction[i], axes.predict[i]))
        print(f"restart-only keys: {', '.join(RESTART_KEYS)}; everything else can be reloaded")
    notes, source_warnings = source_report(args.file, cfg)
    if not args.json:
        print("\n".join([*notes, zenoh_note, *can_note, *envelope_lines]))
    for w in source_warnings:
        print(w, file=sys.stderr)
    for w in axes.warnings:
        print(w, file=sys.stderr)
    return 0


_ABOUT = {
    "motcomp.toml": "example service config, every key documented",
    "demo.toml": "the config `motcomp demo` runs",
    "motcomp.dbc": "CAN frame definitions (output.can)",
    "motcomp.service": "systemd unit",
    "zenoh-acl.json5": "zenoh access control, user/password authentication over TCP",
    "zenoh-tls.json5": "zenoh access control, mutual TLS (certificates)",
    "plants/rails.toml": "plant preset: X-Y rails (P1D)",
    "plants/hexapod.toml": "plant preset: hexapod (P2UZD)",
}


def shipped_files() -> list[str]:
    """The files shipped in motcomp's config directory, relative to it."""
    from motcomp.resources import config_dir

    root = config_dir()
    return sorted(str(p.relative_to(root)) for p in root.rglob("*")
                  if p.is_file() and "__pycache__" not in p.parts)


def run_example(args: argparse.Namespace) -> int:
    from motcomp.resources import config_dir, config_file

    names = shipped_files()
    if args.list:
        print(f"shipped files in {config_dir()} (`motcomp config example NAME` prints one):")
        for name in names:
            print(f"  {name:<22} {_ABOUT.get(name, '')}".rstrip())
        return 0
    if args.name not in names:
        raise ConfigError(f"no shipped file {args.name!r}; shipped: {', '.join(names)}")
    sys.stdout.write(config_file(*Path(args.name).parts).read_text())
    return 0


def _prediction_text(p: PredictorParams | None, used: bool) -> str:
    """``; prediction ...`` for an axis' line (empty without one)."""
    if p is None:
        return ""
    return (f"; prediction {p.order} Laguerre functions, pole {p.pole_hz:g} Hz, band "
            f"{p.band_hz[0]:g}-{p.band_hz[1]:g} Hz{'' if used else ' (predict = false: unused)'}")
