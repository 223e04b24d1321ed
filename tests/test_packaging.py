"""Deployment files: the systemd unit (verified by systemd-analyze when present), the
Dockerfile, the wheel, and the compiler range the build compiles the tick with."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from motcomp.resources import config_file


def unit_text() -> str:
    return config_file("motcomp.service").read_text()


def test_unit_has_notify_watchdog_reload_restart_and_allows_realtime() -> None:
    lines = {ln.split("=", 1)[0]: ln.split("=", 1)[1] for ln in unit_text().splitlines()
             if "=" in ln and not ln.startswith("#")}
    assert lines["Type"] == "notify"
    assert float(lines["WatchdogSec"]) > 0
    assert lines["ExecReload"] == "/bin/kill -HUP $MAINPID"
    assert lines["Restart"] == "on-failure"
    assert lines["KillSignal"] == "SIGTERM"
    assert "RestrictRealtime" not in lines  # it would forbid SCHED_FIFO
    assert "CAP_SYS_NICE" in lines["AmbientCapabilities"]
    assert lines["NoNewPrivileges"] == "yes" and lines["ProtectSystem"] == "strict"
    assert "motcomp run --config" in lines["ExecStart"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not here")
def test_systemd_analyze_verify(tmp_path: Path) -> None:
    exe = Path(sys.executable).parent / "motcomp"
    if not exe.exists():
        exe = Path(shutil.which("motcomp") or "/bin/true")
    unit = tmp_path / "motcomp.service"
    unit.write_text(unit_text().replace("/opt/motcomp/venv/bin/motcomp", str(exe)))
    p = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 0, p.stderr
    assert "motcomp.service" not in p.stderr, p.stderr  # no warning about our unit


ROOT = Path(__file__).resolve().parent.parent
SHIPPED = ["motcomp.toml", "demo.toml", "motcomp.dbc", "motcomp.service", "zenoh-acl.json5",
           "plants/rails.toml", "plants/hexapod.toml"]


def dockerfile() -> list[tuple[str, str]]:
    out = []
    text = (ROOT / "Dockerfile").read_text().replace("\\\n", " ")
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            instr, _, rest = line.partition(" ")
            out.append((instr.upper(), rest.strip()))
    return out


def test_dockerfile_lints_clean() -> None:
    exe = shutil.which("hadolint") or str(Path(sys.executable).parent / "hadolint")
    if not Path(exe).exists():
        pytest.skip("hadolint not installed")
    p = subprocess.run([exe, "--failure-threshold", "info", str(ROOT / "Dockerfile")],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stdout + p.stderr


def test_dockerfile_commands() -> None:
    import json

    from motcomp.cli import build_parser

    steps = dockerfile()
    instrs = [i for i, _ in steps]
    base = dict(steps)["FROM"]
    assert base.startswith("python:3.11") and "slim" in base
    # every COPY source exists; the package is installed; a non-root numeric user runs it
    for instr, rest in steps:
        if instr == "COPY" and not rest.startswith("--from="):
            for src in rest.split()[:-1]:
                assert (ROOT / src).exists(), src
    run = " ".join(rest for i, rest in steps if i == "RUN")
    # a build stage makes the wheel; the run stage installs it
    assert "pip wheel --no-cache-dir --no-deps -w /wheels ." in run
    assert "pip install --no-cache-dir /wheels/*.whl" in run
    assert [rest for i, rest in steps if i == "COPY" and rest.startswith("--from=build")]
    for name in ("motcomp.toml", "motcomp.dbc"):
        assert (ROOT / "config" / name).is_file()
    user = dict(steps)["USER"].split(":")[0]
    assert user.isdigit() and user != "0"
    assert instrs.index("USER") > max(i for i, s in enumerate(instrs) if s == "RUN")
    assert dict(steps)["STOPSIGNAL"] == "SIGTERM"
    # exec form (the service is PID 1 and gets SIGTERM itself), and it parses as our CLI
    entry = json.loads(dict(steps)["ENTRYPOINT"])
    cmd = json.loads(dict(steps)["CMD"])
    assert entry == ["motcomp"]
    args = build_parser().parse_args(cmd)
    assert args.command == "run" and str(args.config) == "/config/motcomp.toml"


@pytest.mark.slow
def test_wheel_ships_the_config_and_finds_it_installed(tmp_path: Path) -> None:
    """The wheel carries config/ as motcomp/_config, and an installed copy finds its presets
    from any directory (what the container and a /opt/motcomp venv run).  Built without the
    compiled tick (``MOTCOMP_PURE_PYTHON=1``: compiling it is a minute of CPU on a slow host);
    a compiled wheel's contents and import are what ``tools/check_toolchain.py`` checks, and the
    editable install the suite runs on is compiled (tests/test_native.py)."""
    import zipfile

    from motcomp.core import native

    env = {**os.environ, native.PURE_ENV: "1"}
    p = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                        str(tmp_path), str(ROOT)], capture_output=True, text=True, timeout=300,
                       env=env)
    assert p.returncode == 0, p.stderr
    wheel = next(tmp_path.glob("motcomp-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    for f in SHIPPED:
        assert f"motcomp/_config/{f}" in names, f
    # the tick's sources always (the plain Python fallback); its compiled modules with their
    # record where the build compiled them (a C compiler here), never the generated C
    core = [f"motcomp/core/{m}" for m in native.COMPILED_MODULES]
    assert all(f"{c}.py" in names for c in core)
    assert not any(n.endswith(".c") for n in names)
    compiled = [c for c in core if any(n.startswith(c + ".") and n.endswith(".so")
                                       for n in names)]
    assert compiled in ([], core), compiled
    assert (f"motcomp/core/{native.RECORD}" in names) == bool(compiled)
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    env = {"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}
    code = ("import motcomp.resources as r, motcomp.presets as p; print(r.config_dir()); "
            "print(p.load_preset('rails').model); import motcomp.core.tick as t, "
            "motcomp.core.native as n; print(n.ACTIVE, t.__file__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, cwd=tmp_path, timeout=60)
    assert out.returncode == 0, out.stderr
    assert str(site / "motcomp" / "_config") in out.stdout and "p1d:K=1" in out.stdout
    tick_line = out.stdout.splitlines()[-1]
    if compiled:
        assert tick_line.startswith("compiled (mypyc) ") and tick_line.endswith(".so")
    else:
        assert tick_line.startswith("plain Python (not compiled at install) ")
    chk = subprocess.run([sys.executable, "-m", "motcomp", "config", "check",
                          str(site / "motcomp" / "_config" / "motcomp.toml")],
                         capture_output=True, text=True, env=env, cwd=tmp_path, timeout=60)
    assert chk.returncode == 0, chk.stderr


def setup_py() -> Any:
    """setup.py's functions (``setup()`` itself runs only as ``__main__``, as setuptools runs
    it)."""
    spec = importlib.util.spec_from_file_location("_motcomp_setup", ROOT / "setup.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_tick_is_compiled_only_with_a_tested_mypy() -> None:
    """mypyc 1.10 cannot compile the tick, 1.16-1.19 build modules that raise ``KeyError:
    'ndarray'`` at import (a dataclass field typed by a numpy alias); 1.20.0, 1.20.2, 2.0.0 and
    2.4.1 were tested (tools/check_toolchain.py, docs/DEPLOYMENT.md).  A build without
    isolation checks the mypy it finds, which pip does not."""
    import tomllib

    setup = setup_py()
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    requirement = setup.tested_mypy()
    assert requirement in pyproject["build-system"]["requires"]
    assert requirement in pyproject["project"]["optional-dependencies"]["dev"]  # the same mypy
    for bad in ("1.10.0", "1.16.0", "1.18.2", "1.19.1", "99.0"):
        why = setup.untested_mypy(bad)
        assert why.startswith(f"mypy {bad} is outside the range the tick was tested with"), why
    for tested in ("1.20.0", "1.20.2", "2.0.0", "2.4.1"):
        assert setup.untested_mypy(tested) == ""
