"""The tick compiled by mypyc from its one Python source, and the plain Python as the fallback
(why and what it gives: docs/BENCHMARKS.md, "The tick compiled").

:data:`COMPILED_MODULES` are compiled when the package is installed on a machine with a C
compiler (setup.py; ``MOTCOMP_PURE_PYTHON=1`` at install skips it).  The build records each
module's source hash in ``_compiled.json`` beside them.  At import (:func:`choose`, run by
``motcomp/core/__init__.py``) the compiled modules are used only all together and only if every
one is present and was built from the source now beside it; otherwise, or with
``MOTCOMP_PURE_PYTHON=1`` in the environment, every one is loaded from its ``.py`` (a compiled
module calls the others natively, so a mix would run stale code).  :data:`ACTIVE` says which.

A compiled class has no instance ``__dict__``: ``copy`` and ``pickle`` (replay snapshots, the
reload reader process) work on it only when it is declared
``@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)``, and a compiled frozen
dataclass cannot be restored field by field, so each defines ``__reduce__`` as
:func:`frozen_reduce`.  Both are no-ops for the plain Python modules.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.machinery
import importlib.util
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["ACTIVE", "COMPILED_MODULES", "PURE_ENV", "RECORD", "choose", "frozen_reduce",
           "source_hashes", "verdict"]

COMPILED_MODULES = ("axes", "bandlimit", "compensator", "envelope", "interp", "minjerk",
                    "playback", "predictor", "saturation", "shaper", "tick", "timeline")
"""Modules of ``motcomp.core`` compiled (the tick and all it calls per sample)."""
PURE_ENV = "MOTCOMP_PURE_PYTHON"
"""Set (to anything but ``""`` or ``0``) at install: no compilation; at run time: the plain
Python modules even where compiled ones are installed."""
RECORD = "_compiled.json"
"""Written by the build beside the modules: ``{module: sha256 of its source}``."""

ACTIVE = "plain Python (not chosen yet)"
"""``"compiled (mypyc)"`` or ``"plain Python (<why>)"``: set by :func:`choose`."""


def frozen_reduce(obj: Any) -> tuple[Any, tuple[Any, ...]]:
    """``__reduce__`` of a frozen dataclass: rebuilt by its constructor from its ``init``
    fields (fields computed in ``__post_init__`` are computed again)."""
    return type(obj), tuple(getattr(obj, f.name) for f in dataclasses.fields(obj) if f.init)


def source_hashes(folder: Path, modules: Sequence[str] = COMPILED_MODULES) -> dict[str, str]:
    """``{module: sha256 hex of folder/module.py}``."""
    return {m: hashlib.sha256((folder / f"{m}.py").read_bytes()).hexdigest() for m in modules}


def _pure_wanted() -> bool:
    return os.environ.get(PURE_ENV, "") not in ("", "0")


def verdict(folder: Path, modules: Sequence[str] = COMPILED_MODULES) -> str:
    """Whether the compiled modules in ``folder`` may be used: ``""`` if so, else why not."""
    if _pure_wanted():
        return f"{PURE_ENV} is set"
    suffixes = importlib.machinery.EXTENSION_SUFFIXES
    missing = [m for m in modules
               if not any((folder / f"{m}{s}").is_file() for s in suffixes)]
    if len(missing) == len(modules):
        return "not compiled at install"
    if missing:
        return f"compiled modules missing: {', '.join(missing)}"
    try:
        built = json.loads((folder / RECORD).read_text())
    except (OSError, ValueError) as exc:
        return f"no record of the compiled sources ({type(exc).__name__})"
    now = source_hashes(folder, modules)
    stale = [m for m in modules if built.get(m) != now[m]]
    if stale:
        return (f"source changed since the build: {', '.join(stale)} "
                f"(reinstall to compile again)")
    return ""


class _PlainSource:
    """A meta path finder that loads the named modules from their ``.py``."""

    def __init__(self, package: str, folder: Path, modules: Sequence[str]) -> None:
        self.names = {f"{package}.{m}": folder / f"{m}.py" for m in modules}

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> Any:
        source = self.names.get(name)
        if source is None:
            return None
        return importlib.util.spec_from_file_location(
            name, source, loader=importlib.machinery.SourceFileLoader(name, str(source)))


def choose(package: str, folder: Path, modules: Sequence[str] = COMPILED_MODULES) -> str:
    """Use the compiled modules of ``package`` (in ``folder``) or, if :func:`verdict` says no,
    make every one load from its ``.py``; sets and returns :data:`ACTIVE`."""
    global ACTIVE
    why = verdict(folder, modules)
    if why:
        finder = _PlainSource(package, folder, modules)
        if not any(isinstance(f, _PlainSource) and f.names == finder.names
                   for f in sys.meta_path):
            sys.meta_path.insert(0, finder)
        ACTIVE = f"plain Python ({why})"
    else:
        ACTIVE = "compiled (mypyc)"
    return ACTIVE
