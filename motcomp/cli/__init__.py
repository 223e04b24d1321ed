"""The ``motcomp`` command.

Each sub-command lives in its own module of this package and exposes
``register(subparsers) -> None``; modules are discovered, so adding a command is adding a file.
The commands stay thin: they parse arguments and call library functions.

Exit codes: 0 success, 1 runtime failure, 2 bad input or usage (the message names the problem,
where it is and the offending value).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import time
from collections.abc import Sequence

from motcomp import __version__
from motcomp.errors import ConfigError, DataError, MotcompError

__all__ = ["STARTED", "build_parser", "main"]

STARTED = time.monotonic()
"""When the command started (its imports included): a ``--timeout`` or ``--wait-peer`` is
counted from here, so that the whole command takes what the user asked."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="motcomp",
        description="Identify a motion platform's lag and compensate it in real time.",
    )
    parser.add_argument("--version", action="version", version=f"motcomp {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    modules = []
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(module, "register"):
            modules.append(module)
    for module in sorted(modules, key=lambda m: (getattr(m, "ORDER", 50), m.__name__)):
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code = args.func(args)
    except (ConfigError, DataError) as exc:
        print(f"motcomp {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except MotcompError as exc:
        print(f"motcomp {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # the reader went away (e.g. `| head`): not an error of ours
        import os

        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    return int(code or 0)
