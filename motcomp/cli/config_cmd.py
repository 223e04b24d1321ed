"""``motcomp config check FILE``: validate a service config and print the effective one."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from motcomp.config import RESTART_KEYS, config_hash, load_config, new_tick, resolve_axes

ORDER = 5


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="check a service config file",
                       description="Configuration tools.")
    cs = p.add_subparsers(dest="config_command", metavar="ACTION")
    cs.required = True
    c = cs.add_parser("check", help="validate FILE and print the effective config",
                      description="Validate a config (includes merged, every axis resolved, "
                                  "gains checked for stability) and print the effective "
                                  "values; errors name the file, the key and the value "
                                  "(exit 2).")
    c.add_argument("file", type=Path)
    c.add_argument("--json", action="store_true", help="print the effective config as JSON")
    c.set_defaults(func=run_check)


def run_check(args: argparse.Namespace) -> int:

    cfg = load_config(args.file)
    axes = resolve_axes(cfg)
    # the stability of every gain/model pair, exactly as the service will check it
    new_tick(cfg, axes)
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
                  f"{lim.v_max[i]:g} acc {lim.a_max[i]:g}")
        print(f"restart-only keys: {', '.join(RESTART_KEYS)}; everything else can be reloaded")
    for w in axes.warnings:
        print(w, file=sys.stderr)
    return 0
