"""Argument helpers shared by the commands."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from motcomp.errors import ConfigError

if TYPE_CHECKING:  # imported where used: a command that needs no model does not load them
    from motcomp.core.models import ProcessModel
    from motcomp.presets import Preset


def add_plant_args(p: argparse.ArgumentParser, required: bool = True) -> None:
    """``--plant NAME | --model SPEC`` (and ``--platform SPEC`` for a mismatched truth)."""
    group = p.add_mutually_exclusive_group(required=required)
    group.add_argument("--plant", metavar="NAME",
                       help="plant preset (config/plants/NAME.toml): rails, hexapod, or a path")
    group.add_argument("--model", metavar="SPEC",
                       help="model spec, e.g. p1d:K=1,Td=0.0175,Tp1=0.1858")


def _number(text: str, kind: Callable[[str], float], what: str) -> float:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def rate_arg(text: str) -> float:
    """A rate in Hz: a positive finite number."""
    return _positive(text, "a rate in Hz (a positive number)")


def finite_float(text: str) -> float:
    """Any finite number (argparse ``type``)."""
    return _number(text, float, "a finite number")


def positive_float(text: str) -> float:
    """A finite number > 0 (argparse ``type``)."""
    return _positive(text, "a positive number")


def _positive(text: str, what: str) -> float:
    value = _number(text, float, what)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0 (argparse ``type``)."""
    value = _number(text, float, "a number >= 0")
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1 (argparse ``type``)."""
    value = int(_number(text, int, "a whole number >= 1"))
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    """An integer >= 0 (argparse ``type``)."""
    value = int(_number(text, int, "a whole number >= 0"))
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return value


def resolve_plant(args: argparse.Namespace) -> tuple[ProcessModel, Preset | None]:
    """The plant model from ``--plant`` or ``--model``, and the preset if one was named."""
    from motcomp.core.models import parse_model
    from motcomp.presets import load_preset

    if getattr(args, "plant", None):
        preset = load_preset(args.plant)
        return preset.model, preset
    if getattr(args, "model", None):
        return parse_model(args.model), None
    raise ConfigError("give --plant NAME or --model SPEC")


def remaining(timeout_s: float, floor_s: float = 0.1) -> float:
    """What is left of ``timeout_s`` counted from the command's start
    (:data:`motcomp.cli.STARTED`: imports and opening the session take part of it), at least
    ``floor_s`` (one look at the network)."""
    import time

    from motcomp.cli import STARTED

    return max(floor_s, timeout_s - (time.monotonic() - STARTED))


def print_json(obj: Any, indent: int | None = 2) -> None:
    """``obj`` as strict JSON on stdout: NaN and infinities as null (:func:`~motcomp.jsonsafe.
    finite`), numpy values as Python's; ``indent`` None: on one line."""
    from motcomp.jsonsafe import finite

    json.dump(finite(obj), sys.stdout, indent=indent, allow_nan=False, default=_json_default)
    sys.stdout.write("\n")


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def setup_logging(level: str = "info") -> None:
    """Log lines to stderr (journald adds its own timestamps under systemd)."""
    import logging

    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO),
                        format="%(asctime)s %(name)s %(levelname)s: %(message)s",
                        stream=sys.stderr)


def add_log_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"],
                   help="log level (default: info)")
