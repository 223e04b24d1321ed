"""``motcomp status``, ``motcomp bypass``, ``motcomp reload``: talk to a running service."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import msgpack

from motcomp.cli._common import print_json
from motcomp.errors import ServiceError
from motcomp.io.zenoh_io import add_zenoh_args, endpoints_from_args, first_reply, open_session

ORDER = 2


def _service_args(p: argparse.ArgumentParser, key: str, timeout: float) -> None:
    """The key of the service endpoint, a timeout and zenoh's flags."""
    p.add_argument("--key", default=key, help=f"endpoint key (default: {key})")
    p.add_argument("--timeout", type=float, default=timeout, metavar="S")
    add_zenoh_args(p)


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("status", help="query a running service's status",
                       description="Query the service's status endpoint and print it.")
    s.add_argument("--json", action="store_true")
    _service_args(s, "motcomp/status", 3.0)
    s.set_defaults(func=run_status)

    b = sub.add_parser("bypass", help="turn compensation off (on) or back on (off), bumplessly",
                       description="Admin command (needs [admin] enabled = true).")
    b.add_argument("state", choices=["on", "off"])
    b.add_argument("--axes", nargs="+", metavar="AXIS", help="default: all driven axes")
    _service_args(b, "motcomp/admin", 3.0)
    b.set_defaults(func=run_bypass)

    pr = sub.add_parser("profile", help="switch the running service's scenario profile",
                        description="Make a profile of the service's config active (its gains "
                                    "replace the current ones, bumplessly). Needs [admin] "
                                    "enabled = true.")
    pr.add_argument("name", help="profile name, or 'none' for the config's base tuning")
    _service_args(pr, "motcomp/admin", 5.0)
    pr.set_defaults(func=run_profile)

    r = sub.add_parser("reload", help="reload a running service's config",
                       description="Ask the running service to re-read its config file (or "
                                   "FILE); prints the outcome, exits 1 if it was rejected. "
                                   "Needs [admin] enabled = true.")
    r.add_argument("--config", type=Path, metavar="FILE",
                   help="file to load instead of the one the service was started with")
    _service_args(r, "motcomp/admin", 5.0)
    r.set_defaults(func=run_reload)


def _request(args: argparse.Namespace, key: str, body: dict[str, Any] | None) -> dict[str, Any]:
    with open_session(endpoints_from_args(args)) as session:
        payload = msgpack.packb(body) if body is not None else None
        out = msgpack.unpackb(first_reply(session, key, payload, args.timeout))
    if not isinstance(out, dict):
        raise ServiceError(f"unexpected reply from {key}")
    return out


def _command(args: argparse.Namespace, name: str, body: dict[str, Any]) -> dict[str, Any] | None:
    """Call the admin endpoint ``name``; ``None`` (with the reason on stderr) if rejected."""
    out = _request(args, f"{args.key}/{name}", body)
    if not out.get("ok"):
        print(f"motcomp {name}: rejected: {out.get('error')}", file=sys.stderr)
        return None
    return out


def run_status(args: argparse.Namespace) -> int:
    st = _request(args, args.key, None)
    if args.json:
        print_json(st)
        return 0
    loop = st.get("loop", {})
    fr = st["frames"]
    print(f"mode {st['mode']}  config {st['config']['hash']} v{st['config']['version']}  "
          f"{st['rate_hz']:g} Hz  ticks {st['ticks']}  missed {st['missed_ticks']}")
    if loop:
        print(f"compute p50 {loop['compute_p50_us']:.1f} us  p99 {loop['compute_p99_us']:.1f} us"
              f"  (whole tick with transport calls p99 {loop.get('tick_p99_us', 0.0):.1f} us)"
              f"  lateness p99.9 {loop['late_p999_us']:.1f} us  max {loop['late_max_us']:.0f} us")
    print(f"frames received {fr['received']} accepted {fr['accepted']} rejected "
          f"{fr['rejected']} {fr['rejected_by_reason']}")
    print(f"stale {st['stale_s']:.2f} s (total {st['stale_total_s']:.2f} s)  "
          f"bypass {st['bypass']}  saturation {st['saturation']}")
    return 0


def run_bypass(args: argparse.Namespace) -> int:
    out = _command(args, "bypass", {"on": args.state == "on", "axes": args.axes})
    if out is None:
        return 1
    print(f"bypassed axes: {', '.join(out['bypass']) or 'none'}")
    return 0


def run_reload(args: argparse.Namespace) -> int:
    body = {"path": str(args.config.resolve())} if args.config else {}
    out = _command(args, "reload", body)
    if out is None:
        return 1
    print(f"reloaded: {out.get('path')} (hash {out.get('hash')}, version {out.get('version')})")
    return 0


def run_profile(args: argparse.Namespace) -> int:
    name = None if args.name == "none" else args.name
    out = _command(args, "profile", {"name": name})
    if out is None:
        return 1
    print(f"profile {out.get('profile')} active (config hash {out.get('hash')}, version "
          f"{out.get('version')})")
    return 0
