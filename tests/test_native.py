"""The tick compiled by mypyc and its plain Python source: which one runs (the build's files, a
compiled module that fails to import, the build's own import check, a reinstall under a running
process), and that both give the same outputs bit for bit (motcomp/core/native.py,
docs/DEPLOYMENT.md, docs/BENCHMARKS.md)."""

from __future__ import annotations

import importlib.machinery
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import textwrap
from pathlib import Path

import pytest

from motcomp.core import native

SUFFIX = importlib.machinery.EXTENSION_SUFFIXES[0]
MODULES = ("a", "b")


def fake_build(folder: Path) -> None:
    """Two modules, each with its source, an extension file and the build's record."""
    for m in MODULES:
        (folder / f"{m}.py").write_text(f"X = {m!r}\n")
        (folder / f"{m}{SUFFIX}").write_bytes(b"")
    (folder / native.RECORD).write_text(json.dumps(native.source_hashes(folder, MODULES)))


def test_the_compiled_modules_are_used_only_all_present_and_built_from_their_source(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(native.PURE_ENV, raising=False)
    fake_build(tmp_path)
    assert native.verdict(tmp_path, MODULES) == ""
    monkeypatch.setenv(native.PURE_ENV, "1")
    assert native.PURE_ENV in native.verdict(tmp_path, MODULES)
    monkeypatch.setenv(native.PURE_ENV, "0")
    assert native.verdict(tmp_path, MODULES) == ""
    (tmp_path / "b.py").write_text("X = 'edited'\n")
    assert "source changed since the build: b" in native.verdict(tmp_path, MODULES)
    fake_build(tmp_path)
    (tmp_path / f"a{SUFFIX}").unlink()
    assert native.verdict(tmp_path, MODULES) == "compiled modules missing: a"
    (tmp_path / f"b{SUFFIX}").unlink()
    assert native.verdict(tmp_path, MODULES) == "not compiled at install"
    fake_build(tmp_path)
    (tmp_path / native.RECORD).unlink()
    assert "no record of the compiled sources" in native.verdict(tmp_path, MODULES)
    fake_build(tmp_path)
    (tmp_path / "a.py").unlink()
    assert native.verdict(tmp_path, MODULES).startswith("sources unreadable (FileNotFoundError: ")


def test_plain_python_is_loaded_from_the_source_beside_a_stale_extension(tmp_path: Path) -> None:
    """A package whose 'compiled' module is a broken file and whose source changed: the
    plain source is what imports (the broken extension would raise if it were loaded)."""
    pkg = tmp_path / "fakepkg"
    pkg.mkdir()
    fake_build(pkg)
    (pkg / "a.py").write_text("X = 'the source'\n")
    (pkg / "__init__.py").write_text("")
    code = textwrap.dedent(f"""
        import sys
        from pathlib import Path
        sys.path.insert(0, {str(tmp_path)!r})
        from motcomp.core import native
        print(native.choose("fakepkg", Path({str(pkg)!r}), {MODULES!r}))
        import fakepkg.a, fakepkg.b
        print(fakepkg.a.X, fakepkg.b.X)
    """)
    env = {k: v for k, v in os.environ.items() if k != native.PURE_ENV}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=60)
    assert p.returncode == 0, p.stderr
    active, values = p.stdout.splitlines()
    assert active.startswith("plain Python (source changed since the build: a")
    assert values == "the source b"


# --- real extension modules, built from a few lines of C -------------------------------------

EXTENSION_C = """
#define PY_SSIZE_T_CLEAN
#include <Python.h>
static struct PyModuleDef def = {PyModuleDef_HEAD_INIT, PKG "." NAME, NULL, -1, NULL};
PyMODINIT_FUNC INIT(void) {
#ifdef IMPORTS
    PyObject *dep = PyImport_ImportModule(PKG "." IMPORTS);
    if (dep == NULL) return NULL;
    Py_DECREF(dep);
#endif
#ifdef RAISES
    PyErr_SetString(PyExc_KeyError, RAISES);
    return NULL;
#endif
    PyObject *mod = PyModule_Create(&def);
    if (mod != NULL && PyModule_AddStringConstant(mod, "X", "compiled " NAME) < 0) {
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
"""


def build_extension(folder: Path, name: str, package: str = "fakepkg", imports: str = "",
                    raises: str = "") -> Path:
    """``folder/name<suffix>``: a real extension module ``package.name`` whose attribute ``X``
    is ``"compiled <name>"``; at import it first imports ``package.<imports>``, and with
    ``raises`` it raises ``KeyError(raises)`` instead of initialising."""
    cc = shutil.which("cc") or shutil.which("gcc")
    include = Path(sysconfig.get_paths()["include"])
    if cc is None or not (include / "Python.h").is_file():
        pytest.skip("no C compiler or Python headers here")
    source = folder / f"_{name}.c"
    source.write_text(EXTENSION_C)
    out = folder / f"{name}{SUFFIX}"
    defs = [f'-DPKG="{package}"', f'-DNAME="{name}"', f"-DINIT=PyInit_{name}"]
    defs += [f'-DIMPORTS="{imports}"'] if imports else []
    defs += [f'-DRAISES="{raises}"'] if raises else []
    subprocess.run([cc, "-shared", "-fPIC", f"-I{include}", *defs, "-o", str(out), str(source)],
                   check=True, capture_output=True, timeout=60)
    source.unlink()
    return out


def real_build(pkg: Path, modules: tuple[str, ...], imports: dict[str, str] | None = None,
               raises: str = "", record: bool = True) -> None:
    """A package ``fakepkg`` in ``pkg``: each module's source (``X = "plain <name>"``), its
    extension (``raises``: the one that raises ``KeyError('ndarray')``) and the record."""
    pkg.mkdir(parents=True, exist_ok=True)
    (pkg / "__init__.py").write_text("")
    for m in modules:
        (pkg / f"{m}.py").write_text(f"X = 'plain {m}'\n")
        build_extension(pkg, m, imports=(imports or {}).get(m, ""),
                        raises="ndarray" if m == raises else "")
    if record:
        (pkg / native.RECORD).write_text(json.dumps(native.source_hashes(pkg, modules)))


def run_child(code: str, path: Path) -> list[str]:
    """``code`` in a new interpreter with ``path`` first on sys.path; its output's lines."""
    env = {k: v for k, v in os.environ.items() if k != native.PURE_ENV}
    prelude = (f"import sys\nfrom pathlib import Path\nsys.path.insert(0, {str(path)!r})\n"
               "from motcomp.core import native\n")
    p = subprocess.run([sys.executable, "-c", prelude + textwrap.dedent(code)],
                       capture_output=True, text=True, env=env, timeout=60)
    assert p.returncode == 0, p.stderr
    return p.stdout.splitlines()


CHOOSE_AND_IMPORT = """
    pkg = Path(sys.path[0]) / "fakepkg"
    print(native.choose("fakepkg", pkg, ("a", "c", "b")))
    import fakepkg.a
    from fakepkg import c
    import fakepkg.b as b
    print(fakepkg.a.X, c.X, b.X, all(m.__file__.endswith(".py") for m in (fakepkg.a, b, c)))
"""


def test_compiled_modules_that_import_are_used(tmp_path: Path) -> None:
    real_build(tmp_path / "fakepkg", ("a", "b", "c"), imports={"c": "b"})
    assert run_child(CHOOSE_AND_IMPORT, tmp_path) == [
        "compiled (mypyc)", "compiled a compiled c compiled b False"]


def test_a_compiled_module_that_raises_at_import_leaves_every_module_plain(
        tmp_path: Path) -> None:
    """``c`` imports ``b``, whose initialisation raises (as mypyc 1.16-1.20's modules did:
    ``KeyError: 'ndarray'``): the culprit is named, and every module -- ``a`` too, which had
    imported compiled -- then loads from its source."""
    real_build(tmp_path / "fakepkg", ("a", "b", "c"), imports={"c": "b"}, raises="b")
    assert run_child(CHOOSE_AND_IMPORT, tmp_path) == [
        "plain Python (compiled modules failed to import: KeyError: 'ndarray' in fakepkg.b)",
        "plain a plain c plain b True"]


def test_an_extension_that_is_no_extension_leaves_every_module_plain(tmp_path: Path) -> None:
    """Any failure counts: a file with an extension's name that does not load (ImportError)."""
    pkg = tmp_path / "fakepkg"
    real_build(pkg, ("a", "b", "c"))
    (pkg / f"c{SUFFIX}").write_bytes(b"not a shared object")
    active, values = run_child(CHOOSE_AND_IMPORT, tmp_path)
    assert active.startswith("plain Python (compiled modules failed to import: ImportError: ")
    assert active.endswith(" in fakepkg.c)")
    assert values == "plain a plain c plain b True"


def test_the_build_check_imports_every_module_from_the_build_output(tmp_path: Path) -> None:
    """:func:`native.check_build`, which setup.py runs before it writes the record: the
    package's ``__init__`` is not run, the modules come from the build output first."""
    src, build = tmp_path / "src", tmp_path / "build"
    (src / "fakepkg").mkdir(parents=True)
    (src / "fakepkg" / "__init__.py").write_text("raise RuntimeError('not run by the check')\n")
    for m in ("a", "b", "c", "d"):
        (src / "fakepkg" / f"{m}.py").write_text(f"X = 'plain {m}'\n")
    real_build(build / "fakepkg", ("a", "b", "c"), imports={"c": "b"}, record=False)
    assert native.check_build(build, src, "fakepkg", ("a", "b", "c")) == ""
    why = native.check_build(build, src, "fakepkg", ("a", "b", "c", "d"))
    assert why.startswith("fakepkg.d was loaded from ") and why.endswith("d.py, not from the build")
    build_extension(build / "fakepkg", "b", raises="ndarray")
    assert native.check_build(build, src, "fakepkg", ("a", "c", "b")) == (
        "compiled modules failed to import: KeyError: 'ndarray' in fakepkg.b")


REINSTALL = """
    import json, os, shutil
    pkg = Path(sys.path[0]) / "fakepkg"
    modules = ("a", "b")
    print(native.choose("fakepkg", pkg, modules))
    import fakepkg.a, fakepkg.b
    print(native.status())
    for m in modules:  # a reinstall: each file replaced (a new inode), the same record
        so = next(pkg.glob(m + ".*.so"), None)
        if so is not None:
            shutil.copy(so, pkg / "new.so")
            os.replace(pkg / "new.so", so)
    if (pkg / native.RECORD).exists():
        record = (pkg / native.RECORD).read_text()
        (pkg / native.RECORD).unlink()
        print(native.status())
        (pkg / native.RECORD).write_text(record)
    print(native.status())
    (pkg / "b.py").write_text("X = 'edited'")
    print(native.status())
    print(fakepkg.a.X, fakepkg.b.X)
"""


def test_the_status_says_a_reinstall_under_the_running_process(tmp_path: Path) -> None:
    real_build(tmp_path / "fakepkg", ("a", "b"))
    lines = run_child(REINSTALL, tmp_path)
    change = ("compiled (mypyc); the installed build changed since start ({}): this process "
              "runs what it loaded; {}")
    assert lines == [
        "compiled (mypyc)",
        "compiled (mypyc)",  # nothing changed: ACTIVE alone
        change.format("compiled modules replaced, build record removed",
                      "a restart would run the plain Python (no record of the compiled "
                      "sources (FileNotFoundError))"),
        change.format("compiled modules replaced", "restart to load the installed build"),
        change.format("sources changed: b, compiled modules replaced",
                      "a restart would run the plain Python (source changed since the build: "
                      "b (reinstall to compile again))"),
        "compiled a compiled b",  # what it loaded, still
    ]


def test_the_status_says_a_source_edited_under_a_plain_python_process(tmp_path: Path) -> None:
    pkg = tmp_path / "fakepkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    for m in ("a", "b"):
        (pkg / f"{m}.py").write_text(f"X = 'plain {m}'\n")
    lines = run_child(REINSTALL, tmp_path)
    assert lines == [
        "plain Python (not compiled at install)",
        "plain Python (not compiled at install)",
        "plain Python (not compiled at install)",
        "plain Python (not compiled at install); the installed build changed since start "
        "(sources changed: b): this process runs what it loaded; a restart would run the "
        "plain Python (not compiled at install)",
        "plain a plain b",
    ]


@pytest.mark.slow
def test_a_service_whose_install_is_replaced_keeps_running_and_says_so(tmp_path: Path) -> None:
    """The service runs from a copy of this install; the copy is then reinstalled under it as
    ``pip install -e`` does (record removed, each compiled file replaced by a new one, record
    written again) and a source edited: the service keeps ticking on what it loaded and its
    status' ``tick`` says what changed."""
    import signal
    import time

    import msgpack

    from motcomp.io.zenoh_io import (
        ZenohEndpoints,
        first_reply,
        free_tcp_port,
        loopback,
        open_session,
    )
    from motcomp.resources import config_dir, config_file
    from motcomp.runtime.service import BUILD_CHECK_S

    root = Path(__file__).resolve().parent.parent
    site = tmp_path / "site"
    shutil.copytree(root / "motcomp", site / "motcomp",
                    ignore=shutil.ignore_patterns("__pycache__", "_config"))
    groups = list(root.glob(f"*__mypyc{SUFFIX}"))  # mypyc's shared library, if compiled
    for lib in groups:
        shutil.copy2(lib, site / lib.name)
    cfg = tmp_path / "service.toml"
    cfg.write_text(f'include = ["{config_file("motcomp.toml")}"]\n')
    env = {k: v for k, v in os.environ.items() if k != native.PURE_ENV}
    env.update(PYTHONPATH=str(site), MOTCOMP_CONFIG_DIR=str(config_dir()))
    port = free_tcp_port()

    def status(session: object) -> dict[str, object]:
        for _ in range(100):
            try:
                st: dict[str, object] = msgpack.unpackb(
                    first_reply(session, "motcomp/status", None, 1.0))
            except Exception:
                time.sleep(0.2)
                continue
            if isinstance(st.get("ticks"), int) and st["ticks"] > 0:
                return st
            time.sleep(0.2)
        raise AssertionError("the service did not answer its status query")

    log = tmp_path / "svc.log"
    with log.open("wb") as fh:
        svc = subprocess.Popen([sys.executable, "-m", "motcomp", "run", "--config", str(cfg),
                                "-l", loopback(port)], stdout=fh, stderr=subprocess.STDOUT,
                               env=env, cwd=tmp_path)
    try:
        with open_session(ZenohEndpoints(connect=(loopback(port),))) as session:
            before = status(session)
            assert before["tick"] == native.ACTIVE  # the copy is this install
            core = site / "motcomp" / "core"
            record = core / native.RECORD
            kept = record.read_text() if record.exists() else None
            record.unlink(missing_ok=True)
            for so in [*core.glob(f"*{SUFFIX}"), *(site / lib.name for lib in groups)]:
                shutil.copy2(so, so.with_suffix(".new"))
                os.replace(so.with_suffix(".new"), so)
            if kept is not None:
                record.write_text(kept)
            with (core / "shaper.py").open("a") as f:
                f.write("# edited\n")
            compiled = native.ACTIVE.startswith("compiled")
            settled = (
                f"{native.ACTIVE}; the installed build changed since start (sources changed: "
                f"shaper{', compiled modules replaced' if compiled else ''}): this process runs "
                f"what it loaded; a restart would run the plain Python ("
                + ("source changed since the build: shaper (reinstall to compile again))"
                   if compiled else native.ACTIVE.removeprefix("plain Python (")))
            # the build is looked at every BUILD_CHECK_S: once while the record was being
            # written, it rightly says so ("no record of the compiled sources
            # (JSONDecodeError)"), and the next look says what settled
            after = status(session)
            t_end = time.monotonic() + 3 * BUILD_CHECK_S
            while after["tick"] != settled and time.monotonic() < t_end:
                time.sleep(0.2)
                after = status(session)
        assert after["tick"] == settled
        assert isinstance(after["ticks"], int) and isinstance(before["ticks"], int)
        assert after["ticks"] > before["ticks"]
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=30) == 0, log.read_text()[-3000:]
    finally:
        if svc.poll() is None:
            svc.kill()
            svc.wait()
    text = log.read_text()
    assert f"tick {native.ACTIVE}" in text  # the start-up log


REPLAY = textwrap.dedent("""
    import json, sys
    import numpy as np
    from motcomp.config import load_config, resolve_axes
    from motcomp.core import native
    from motcomp.record import read_session
    from motcomp.replay.engine import run_ticks
    from motcomp.replay.offline import plan_for
    from motcomp.resources import config_file
    cfg = load_config(config_file("motcomp.toml"))
    s = read_session(sys.argv[1])
    plan = plan_for(s, cfg, resolve_axes(cfg))
    res = run_ticks(plan, s.inputs, cfg)
    rows = np.flatnonzero(plan.output >= 0)
    rec = s.outputs.pos[plan.output[rows]]
    print(json.dumps({"active": native.ACTIVE, "rows": int(rows.size),
                      "equal": bool(np.array_equal(res.u[rows], rec)),
                      "max_diff": float(np.abs(res.u[rows] - rec).max())}))
""")


def test_compiled_and_plain_python_ticks_agree_bit_for_bit(tmp_path: Path) -> None:
    """A synthetic session written by the compiled tick (jittered and stalled input, a gap,
    bypass switches, a step, bad and partial frames, parking) replayed by the plain Python
    one: every output equal, bit for bit."""
    if not native.ACTIVE.startswith("compiled"):
        pytest.skip(f"the tick is not compiled here: {native.ACTIVE}")
    from motcomp.config import load_config
    from motcomp.replay.synth import SynthOptions, synthesize
    from motcomp.resources import config_file

    path = tmp_path / "rich.mcap"
    synthesize(path, load_config(config_file("motcomp.toml")),
               SynthOptions(duration_s=20.0, seed=11, stalls=[(4.5, 3), (9.0, 30)],
                            gaps=[(6.0, 0.4)], bypass=[(8.0, True, ("rails_x",)),
                                                       (12.0, False, ("rails_x",))],
                            steps=[(14.0, "rails_y", 0.3)], partial_every=7, bad_every=97,
                            no_t_every=13, park_at_s=18.0))
    env = {**os.environ, native.PURE_ENV: "1"}
    p = subprocess.run([sys.executable, "-c", REPLAY, str(path)], capture_output=True,
                       text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["active"] == f"plain Python ({native.PURE_ENV} is set)"
    assert out["rows"] > 19_000
    assert out["equal"], out
