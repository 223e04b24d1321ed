"""The tick compiled by mypyc from its one Python source, and the plain Python as the fallback
(why and what it gives: docs/BENCHMARKS.md, "The tick compiled"; the install: docs/DEPLOYMENT.md).

:data:`COMPILED_MODULES` are compiled when the package is installed on a machine with a C
compiler and a mypy in the tested range (setup.py; ``MOTCOMP_PURE_PYTHON=1`` at install skips
it).  The build imports every compiled module (:func:`check_build`) and only then records each
module's source hash in ``_compiled.json`` beside them.  At import (:func:`choose`, run by
``motcomp/core/__init__.py``) the compiled modules are used only all together: every one must be
present, built from the source now beside it and import without an exception; otherwise, or with
``MOTCOMP_PURE_PYTHON=1`` in the environment, every one is loaded from its ``.py`` (a compiled
module calls the others natively, so a mix would run stale code).  :data:`ACTIVE` says which and
why; :func:`status` adds what changed in the installed files since (a reinstall under a running
process, which keeps what it loaded).

A compiled class has no instance ``__dict__``: ``copy`` and ``pickle`` (replay snapshots, the
reload reader process) work on it only when it is declared
``@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)``, and a compiled frozen
dataclass cannot be restored field by field, so each defines ``__reduce__`` as
:func:`frozen_reduce`.  Both are no-ops for the plain Python modules.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import importlib.machinery
import importlib.util
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["ACTIVE", "COMPILED_MODULES", "PURE_ENV", "RECORD", "check_build", "choose",
           "frozen_reduce", "import_all", "since_start", "source_hashes", "status", "verdict"]

COMPILED_MODULES = ("axes", "bandlimit", "blend", "compensator", "envelope", "interp", "minjerk",
                    "playback", "predictor", "saturation", "shaper", "tick", "timeline")
"""Modules of ``motcomp.core`` compiled (the tick and all it calls per sample)."""
PURE_ENV = "MOTCOMP_PURE_PYTHON"
"""Set (to anything but ``""`` or ``0``) at install: no compilation; at run time: the plain
Python modules even where compiled ones are installed."""
RECORD = "_compiled.json"
"""Written by the build beside the modules, once they imported: ``{module: sha256 of its
source}``."""

ACTIVE = "plain Python (not chosen yet)"
"""``"compiled (mypyc)"`` or ``"plain Python (<why>)"``: set by :func:`choose`."""

CHECK_TIMEOUT_S = 300.0
"""How long :func:`check_build`'s process may take to import the built modules."""


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
    """Whether the compiled modules in ``folder`` may be imported: ``""`` if so, else why not
    (the files only: whether they import is :func:`import_all`'s answer)."""
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
    try:
        now = source_hashes(folder, modules)
    except OSError as exc:
        return f"sources unreadable ({type(exc).__name__}: {exc})"
    stale = [m for m in modules if built.get(m) != now[m]]
    if stale:
        return (f"source changed since the build: {', '.join(stale)} "
                f"(reinstall to compile again)")
    return ""


class _Started:
    """A meta path finder that finds nothing: it notes which of ``names`` began to import, in
    order (the innermost of the imports that failed is the last one begun)."""

    def __init__(self, names: Sequence[str]) -> None:
        self.names = set(names)
        self.started: list[str] = []

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> None:
        if name in self.names:
            self.started.append(name)


def import_all(package: str, modules: Sequence[str] = COMPILED_MODULES) -> str:
    """Import every one of ``package``'s ``modules``: ``""`` if all did, else why not -- the
    exception and the module that raised it, e.g. ``compiled modules failed to import:
    KeyError: 'ndarray' in motcomp.core.saturation`` -- with every module of ``package``'s
    top-level package that the attempt imported forgotten again (``sys.modules`` and the
    parent's attribute), so that the next import loads it anew."""
    names = [f"{package}.{m}" for m in modules]
    watch = _Started(names)
    before = set(sys.modules)
    sys.meta_path.insert(0, watch)
    name = ""
    try:
        for name in names:
            importlib.import_module(name)
    except Exception as exc:
        failed = [n for n in watch.started if n not in sys.modules]
        _forget(set(sys.modules) - before, package.partition(".")[0])
        text = f"{type(exc).__name__}: {exc}"
        if len(text) > 300:
            text = text[:297] + "..."
        return f"compiled modules failed to import: {text} in {failed[-1] if failed else name}"
    finally:
        sys.meta_path.remove(watch)
    return ""


def _forget(names: set[str], top: str) -> None:
    for name in names:
        if name != top and not name.startswith(top + "."):
            continue
        module = sys.modules.pop(name, None)
        parent, _, child = name.rpartition(".")
        if parent in sys.modules and getattr(sys.modules[parent], child, None) is module:
            delattr(sys.modules[parent], child)


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
    """Import the compiled modules of ``package`` (in ``folder``) or, if :func:`verdict` says
    no or one of them fails to import (:func:`import_all`), make every one load from its
    ``.py``; sets and returns :data:`ACTIVE`, and notes the installed files for
    :func:`since_start`."""
    global ACTIVE, _START
    start = _Installed.read(folder, modules)
    why = verdict(folder, modules) or import_all(package, modules)
    if why:
        finder = _PlainSource(package, folder, modules)
        if not any(isinstance(f, _PlainSource) and f.names == finder.names
                   for f in sys.meta_path):
            sys.meta_path.insert(0, finder)
        ACTIVE = f"plain Python ({why})"
    else:
        ACTIVE = "compiled (mypyc)"
    _START = start
    return ACTIVE


# --- a reinstall under a running process ------------------------------------------------------

Identity = tuple[int, int, int, int] | None
"""A file's ``(st_dev, st_ino, st_size, st_mtime_ns)``, or None if it is not there: a file
replaced (a new inode) or rewritten reads as another."""


def _identity(path: Path) -> Identity:
    try:
        st = path.stat()
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


@dataclasses.dataclass(frozen=True)
class _Installed:
    """The compiled modules' installed files at one moment: every file's identity (sources,
    extension files under each suffix, the record), the sources' hashes and the record."""

    folder: Path
    modules: tuple[str, ...]
    files: tuple[tuple[Path, Identity], ...]
    sources: dict[str, str]
    record: str | None

    @staticmethod
    def paths(folder: Path, modules: Sequence[str]) -> list[Path]:
        suffixes = importlib.machinery.EXTENSION_SUFFIXES
        return ([folder / f"{m}.py" for m in modules]
                + [folder / f"{m}{s}" for m in modules for s in suffixes] + [folder / RECORD])

    @staticmethod
    def identities(folder: Path, modules: Sequence[str]) -> tuple[tuple[Path, Identity], ...]:
        return tuple((p, _identity(p)) for p in _Installed.paths(folder, modules))

    @classmethod
    def read(cls, folder: Path, modules: Sequence[str]) -> _Installed:
        files = cls.identities(folder, modules)
        sources = {}
        for m in modules:
            try:
                sources[m] = hashlib.sha256((folder / f"{m}.py").read_bytes()).hexdigest()
            except OSError:
                sources[m] = ""
        try:
            record: str | None = (folder / RECORD).read_text()
        except OSError:
            record = None
        return cls(folder, tuple(modules), files, sources, record)

    def compiled(self) -> set[Path]:
        """The extension files present."""
        return {p for p, ident in self.files[len(self.modules):-1] if ident is not None}


_START: _Installed | None = None
"""The installed files when :func:`choose` ran."""
_SEEN: tuple[tuple[tuple[Path, Identity], ...], str] | None = None
"""The last identities :func:`since_start` described, and its answer."""


def since_start() -> str:
    """What changed in the installed compiled modules, their sources or the build's record
    since :func:`choose` ran (a reinstall under this process, which keeps running what it
    loaded), and what a restart would load; ``""`` if nothing did.  A few dozen ``stat``
    calls when nothing changed, the sources hashed again when something did."""
    global _SEEN
    start = _START
    if start is None:
        return ""
    files = _Installed.identities(start.folder, start.modules)
    if files == start.files:
        return ""
    seen = _SEEN
    if seen is not None and seen[0] == files:
        return seen[1]
    now = _Installed.read(start.folder, start.modules)
    what = []
    edited = [m for m in start.modules if now.sources[m] != start.sources[m]]
    if edited:
        what.append(f"sources changed: {', '.join(edited)}")
    then_so, now_so = start.compiled(), now.compiled()
    if then_so and not now_so:
        what.append("compiled modules removed")
    elif now_so and not then_so:
        what.append("compiled modules added")
    elif dict(start.files[len(start.modules):-1]) != dict(now.files[len(now.modules):-1]):
        what.append("compiled modules replaced")
    if now.record != start.record:
        what.append("build record " + ("removed" if now.record is None else
                                       "written" if start.record is None else "rewritten"))
    text = ""
    if what:
        why = verdict(start.folder, start.modules)
        text = (f"the installed build changed since start ({', '.join(what)}): this process "
                "runs what it loaded; " + (f"a restart would run the plain Python ({why})" if why
                                          else "restart to load the installed build"))
    _SEEN = (files, text)
    return text


def status() -> str:
    """:data:`ACTIVE`, followed by :func:`since_start`'s answer if the installed build changed
    (the service's status ``tick``)."""
    change = since_start()
    return f"{ACTIVE}; {change}" if change else ACTIVE


# --- the build's import check -----------------------------------------------------------------

_CHECK = """
import importlib.util, json, sys
spec = importlib.util.spec_from_file_location("_motcomp_native_check", sys.argv[1])
native = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(native)
print(json.dumps(native._check_here(*sys.argv[2:])))
"""


def check_build(build_lib: Path, source_root: Path, package: str = "motcomp.core",
                modules: Sequence[str] = COMPILED_MODULES) -> str:
    """Import every compiled module from the build output ``build_lib`` in a new process:
    ``""`` if all did, else why not.  The packages' ``__init__`` are not run (they would choose
    the plain Python: there is no record yet); their other modules come from ``build_lib``, then
    from ``source_root``.  Run by setup.py before it writes the record."""
    import subprocess

    try:
        p = subprocess.run([sys.executable, "-c", _CHECK, __file__, str(build_lib),
                            str(source_root), package, *modules],
                           capture_output=True, text=True, timeout=CHECK_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return f"importing the compiled modules took longer than {CHECK_TIMEOUT_S:g} s"
    lines = p.stdout.strip().splitlines()
    if p.returncode != 0 or not lines:
        said = (p.stderr.strip().splitlines() or [""])[-1]
        return f"the process importing the compiled modules failed (exit {p.returncode}) {said}"
    answer = json.loads(lines[-1])
    assert isinstance(answer, str)
    return answer


def _check_here(build_lib: str, source_root: str, package: str, *modules: str) -> str:
    """:func:`check_build`'s process: the packages of ``package`` as bare modules whose path is
    the build's folder, then the sources'; mypyc's shared library from ``build_lib``."""
    import types

    sys.path.insert(0, build_lib)
    parts = package.split(".")
    for i in range(1, len(parts) + 1):
        stub = types.ModuleType(".".join(parts[:i]))
        stub.__path__ = [str(Path(build_lib, *parts[:i])), str(Path(source_root, *parts[:i]))]
        sys.modules[stub.__name__] = stub
        if i > 1:
            setattr(sys.modules[".".join(parts[:i - 1])], parts[i - 1], stub)
    why = import_all(package, modules)
    if why:
        return why
    suffixes = tuple(importlib.machinery.EXTENSION_SUFFIXES)
    build = Path(build_lib).resolve()
    for m in modules:
        file = str(getattr(sys.modules[f"{package}.{m}"], "__file__", None))
        if not (file.endswith(suffixes) and Path(file).resolve().is_relative_to(build)):
            return f"{package}.{m} was loaded from {file}, not from the build"
    return ""
