"""The wheel carries the repository's ``config/`` as ``motcomp/_config`` (see
motcomp/resources.py), and the tick's modules compiled by mypyc where a C compiler is at hand
and the mypy installed for the build is in the tested range, the build-system requirement in
pyproject.toml.  The compiled modules are imported once built, and recorded (motcomp/core/native.py)
only if every one imports; otherwise, with ``MOTCOMP_PURE_PYTHON=1``, or when the compiler
fails, the tick stays plain Python and the build says why (``pip install -v`` shows it).
Everything else is in pyproject.toml.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import json
import os
import shutil
import sys
import tempfile
import tomllib
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
    module = sys.modules.get(spec.name)
    if module is None:  # dataclasses look a module up in sys.modules
        module = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return module


def _say(text: str) -> None:
    print(f"motcomp build: {text}", file=sys.stderr)


def tested_mypy() -> str:
    """The build-system requirement on mypy in pyproject.toml: the compilers tested (e.g.
    ``mypy>=1.x,<2.y``)."""
    requires = tomllib.loads((ROOT / "pyproject.toml").read_text())["build-system"]["requires"]
    found = [r for r in requires if r.replace(" ", "").startswith(("mypy>", "mypy<", "mypy="))]
    if len(found) != 1:
        raise RuntimeError(f"pyproject.toml: one build requirement on mypy expected, not {found}")
    return str(found[0])


def untested_mypy(version: str) -> str:
    """``""`` if mypy ``version`` is in the tested range, else why it is not used."""
    from packaging.requirements import Requirement  # setuptools carries it

    requirement = Requirement(tested_mypy())
    if requirement.specifier.contains(version, prereleases=True):
        return ""
    return (f"mypy {version} is outside the range the tick was tested with "
            f"({requirement.specifier}, pyproject.toml)")


def _drop(path: Path) -> None:
    """Remove a built file (unlinked: a process that loaded it keeps its copy)."""
    path.unlink(missing_ok=True)


def _forget_checkout(extensions: bool = True) -> None:
    """The checkout's record of compiled sources removed, and with ``extensions`` the extension
    files an earlier editable install left in it: the plain Python runs from it
    (motcomp/core/native.py).  Only an editable install touches the checkout."""
    native = _native()
    _drop(CORE / native.RECORD)
    if extensions:
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            for m in native.COMPILED_MODULES:
                _drop(CORE / f"{m}{suffix}")
            for lib in ROOT.glob(f"*__mypyc{suffix}"):  # mypyc's shared library of the group
                _drop(lib)


def compiled_extensions() -> list[Any]:
    """mypyc's extensions for ``native.COMPILED_MODULES``, or none (said why)."""
    native = _native()
    why = ""
    if os.environ.get(native.PURE_ENV, "") not in ("", "0"):
        why = f"{native.PURE_ENV} set"
    else:
        try:
            from mypy.version import __version__ as mypy_version
            from mypyc.build import mypycify
        except ImportError:
            why = "mypyc not available"
        else:
            why = untested_mypy(mypy_version)
    if why:
        _say(f"{why}: the tick stays plain Python")
        return []
    # a config of its own: the project's (pydantic's mypy plugin) needs what is not installed yet
    ini = Path(tempfile.mkdtemp()) / "mypyc.ini"
    ini.write_text("[mypy]\nignore_missing_imports = True\n")
    sources = [f"motcomp/core/{m}.py" for m in native.COMPILED_MODULES]
    try:
        extensions = mypycify(["--config-file", str(ini), *sources], opt_level="3")
    except BaseException as exc:  # mypy exits with SystemExit on a type error
        _say(f"mypyc {mypy_version} failed ({type(exc).__name__}: {exc}): the tick stays "
             "plain Python")
        return []
    _say(f"compiling the tick with mypyc {mypy_version}")
    return list(extensions)


class BuildExtOrPlain(build_ext):
    """Compile the tick and record it once every compiled module imports from the build; or
    leave it plain Python (no compiler here, or the compiled modules do not import)."""

    def run(self) -> None:
        native = _native()
        if not self.extensions:
            super().run()
            return
        if self.inplace:
            _forget_checkout(extensions=False)  # until this build is checked
        try:
            super().run()
        except Exception as exc:
            self._plain(f"compiling failed ({type(exc).__name__}: {exc})")
            return
        build_lib = Path(self.build_lib)
        why = native.check_build(build_lib, ROOT)
        if why:
            self._plain(why)
            return
        record = json.dumps(native.source_hashes(CORE), indent=1) + "\n"
        for folder in [build_lib / "motcomp" / "core"] + ([CORE] if self.inplace else []):
            (folder / native.RECORD).write_text(record)
        _say("the compiled modules import: recorded, the tick runs compiled")

    def _plain(self, why: str) -> None:
        """No record, and this build's extension files removed from the build output (and,
        editable, from the checkout)."""
        for ext in self.extensions:
            _drop(Path(self.build_lib) / self.get_ext_filename(self.get_ext_fullname(ext.name)))
        if self.inplace:
            _forget_checkout()
        _say(f"{why}: the tick stays plain Python")


class BuildPyWithConfig(build_py):
    """Copy config/ into the built package as motcomp/_config; the record of compiled sources
    only from this build's own check (BuildExtOrPlain), never a copy of the checkout's."""

    def run(self) -> None:
        super().run()
        if self.editable_mode:
            if not self.distribution.ext_modules:  # not compiled: nor is the checkout
                _forget_checkout()
            return
        _drop(Path(self.build_lib) / "motcomp" / "core" / _native().RECORD)
        target = Path(self.build_lib) / "motcomp" / "_config"
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(ROOT / "config", target)


if __name__ == "__main__":  # as setuptools runs it (tests import the functions above)
    setup(cmdclass={"build_py": BuildPyWithConfig, "build_ext": BuildExtOrPlain},
          ext_modules=compiled_extensions())
