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

__all__ = ["MODULE_OF", "STARTED", "build_parser", "main"]

STARTED = time.monotonic()
"""When the command started (its imports included): a ``--timeout`` or ``--wait-peer`` is
counted from here, so that the whole command takes what the user asked."""


MODULE_OF = {
    "run": "run", "status": "admin", "bypass": "admin", "profile": "admin", "reload": "admin",
    "hil": "hil", "source": "source", "record": "record", "replay": "replay", "info": "info",
    "export": "export", "config": "config_cmd", "demo": "demo", "design": "design",
    "evaluate": "design", "pareto": "design", "excite": "excite", "identify": "identify",
}
"""The module of each command, so that a command imports its own module only (``motcomp
status`` need not import the optimiser: on a busy host the imports were most of a 2 s
timeout).  A command missing here still works, through the whole parser
(tests/test_cli_ops.py checks the table against the modules' registrations)."""


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command, or of the commands of the module ``only``."""
    parser = argparse.ArgumentParser(
        prog="motcomp",
        description="Identify a motion platform's lag and compensate it in real time.",
    )
    parser.add_argument("--version", action="version", version=f"motcomp {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    modules = []
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_") or (only is not None and info.name != only):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(module, "register"):
            modules.append(module)
    for module in sorted(modules, key=lambda m: (getattr(m, "ORDER", 50), m.__name__)):
        module.register(sub)
    return parser


def _command_parser(parser: argparse.ArgumentParser, args: argparse.Namespace
                    ) -> argparse.ArgumentParser:
    """The innermost sub-parser ``args`` were parsed by (``motcomp config check``'s for
    ``config check``)."""
    while True:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction) and \
                    getattr(args, action.dest, None) in action.choices:
                parser = action.choices[getattr(args, action.dest)]
                break
        else:
            return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code.  As a process' entry (``argv`` None: the
    command line), it also sets how the process runs zenoh (:func:`use_one_zenoh_thread`)."""
    if argv is None:
        from motcomp.io.zenoh_io import use_one_zenoh_thread

        use_one_zenoh_thread()
    argv = list(sys.argv[1:] if argv is None else argv)
    try:  # Ctrl-C while the command's modules load: no traceback
        parser = build_parser(MODULE_OF.get(argv[0]) if argv else None)
    except KeyboardInterrupt:
        return 130
    args, extra = parser.parse_known_args(argv)
    if extra:  # said with the command's own usage, not the top level's
        _command_parser(parser, args).error(f"unrecognized arguments: {' '.join(extra)}")
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
