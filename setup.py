"""The wheel carries the repository's ``config/`` as ``motcomp/_config`` (see
motcomp/resources.py), and the tick's modules compiled by mypyc where a C compiler is at hand
(see motcomp/core/native.py; ``MOTCOMP_PURE_PYTHON=1`` skips it, a failed compilation leaves the
plain Python); everything else is in pyproject.toml.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

from setuptools import setup
from setuptools.command.build_ext import build_ext
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
CORE = ROOT / "motcomp" / "core"


def _native() -> Any:
    """motcomp/core/native.py on its own (the package's dependencies are not installed yet)."""
    spec = importlib.util.spec_from_file_location("_motcomp_native", CORE / "native.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _say(text: str) -> None:
    print(f"motcomp build: {text}", file=sys.stderr)


def _forget_build() -> None:
    """No record of compiled sources: whatever extension files an earlier build left are not
    used (motcomp/core/native.py)."""
    (CORE / _native().RECORD).unlink(missing_ok=True)


def compiled_extensions() -> list[Any]:
    """mypyc's extensions for ``native.COMPILED_MODULES`` and their source record, or none."""
    native = _native()
    _forget_build()
    if os.environ.get(native.PURE_ENV, "") not in ("", "0"):
        _say(f"{native.PURE_ENV} set: the tick stays plain Python")
        return []
    try:
        from mypyc.build import mypycify
    except ImportError:
        _say("mypyc not available: the tick stays plain Python")
        return []
    # a config of its own: the project's (pydantic's mypy plugin) needs what is not installed yet
    ini = Path(tempfile.mkdtemp()) / "mypyc.ini"
    ini.write_text("[mypy]\nignore_missing_imports = True\n")
    sources = [f"motcomp/core/{m}.py" for m in native.COMPILED_MODULES]
    try:
        extensions = mypycify(["--config-file", str(ini), *sources], opt_level="3")
    except BaseException as exc:  # mypy exits with SystemExit on a type error
        _say(f"mypyc failed ({type(exc).__name__}: {exc}): the tick stays plain Python")
        return []
    (CORE / native.RECORD).write_text(json.dumps(native.source_hashes(CORE), indent=1) + "\n")
    return list(extensions)


class BuildExtOrPlain(build_ext):
    """Compile the tick, or leave it plain Python if the compiler fails (no compiler here)."""

    def run(self) -> None:
        try:
            super().run()
        except Exception as exc:
            _forget_build()
            _say(f"compiling failed ({type(exc).__name__}: {exc}): the tick stays plain Python")


class BuildPyWithConfig(build_py):
    """Copy config/ into the built package as motcomp/_config."""

    def run(self) -> None:
        super().run()
        if not self.editable_mode:
            target = Path(self.build_lib) / "motcomp" / "_config"
            shutil.rmtree(target, ignore_errors=True)
            shutil.copytree(ROOT / "config", target)


setup(cmdclass={"build_py": BuildPyWithConfig, "build_ext": BuildExtOrPlain},
      ext_modules=compiled_extensions())
