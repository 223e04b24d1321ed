"""Build motcomp's wheel with given mypy versions and check that the result works.

For each version: a copy of this checkout (its tracked and new files), a venv with that mypy,
setuptools, numpy and msgpack, ``pip wheel --no-build-isolation`` (as a distribution or an
offline mirror builds, with the compiler it has), then the wheel's files imported by this
interpreter (which has motcomp's run-time dependencies): which tick runs, from which file, and
``motcomp config check`` on the example config.  By default the oldest and the newest mypy that
pyproject.toml's build requirement admits (the range setup.py compiles with); ``--admit``
widens the copy's range to the version tried, to see what the build's import check does with a
compiler outside it.  A few minutes of CPU per version (docs/DEPLOYMENT.md).

    python tools/check_toolchain.py                 # the range's oldest and newest
    python tools/check_toolchain.py 1.18.2 --admit  # a broken mypyc: the build falls back
"""

from __future__ import annotations

import argparse
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def mypy_requirement(root: Path) -> str:
    requires = tomllib.loads((root / "pyproject.toml").read_text())["build-system"]["requires"]
    return next(r for r in requires if re.match(r"mypy\s*[<>=!~]", r))


def copy_checkout(dest: Path) -> None:
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT,
                           check=True, capture_output=True, text=True).stdout.split("\0")
    for name in filter(None, files):
        src = ROOT / name
        if src.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)


def run(cmd: list[str], env: dict[str, str] | None = None, cwd: Path | None = None,
        check: bool = False) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd, check=check)


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def try_version(spec: str, work: Path, admit: bool) -> dict[str, str]:
    """Build with the mypy ``spec`` (``==1.2.3`` or a range) in ``work``; what came of it."""
    src, venv, wheels, site = work / "src", work / "venv", work / "wheels", work / "site"
    copy_checkout(src)
    build_reqs = [r for r in tomllib.loads((src / "pyproject.toml").read_text())
                  ["build-system"]["requires"] if not re.match(r"mypy\s*[<>=!~]", r)]
    run([sys.executable, "-m", "venv", str(venv)], check=True)
    pip = [str(venv / "bin" / "python"), "-m", "pip", "install", "-q"]
    p = run([*pip, *build_reqs, f"mypy{spec}"])
    if p.returncode != 0:
        return {"mypy": spec, "result": f"could not install mypy{spec}: {p.stderr[-500:]}"}
    version = run([str(venv / "bin" / "python"), "-c",
                   "import mypy.version; print(mypy.version.__version__)"]).stdout.strip()
    if admit:
        text = (src / "pyproject.toml").read_text()
        (src / "pyproject.toml").write_text(text.replace(f'"{mypy_requirement(src)}"',
                                                         f'"mypy=={version}"'))
    t0, cpu0 = time.monotonic(), _children_cpu_s()
    p = run([str(venv / "bin" / "python"), "-m", "pip", "wheel", "-v", "--no-build-isolation",
             "--no-deps", "-w", str(wheels), str(src)])
    out = {"mypy": version,
           "build_s": f"{time.monotonic() - t0:.0f} s, CPU {_children_cpu_s() - cpu0:.0f}",
           "build": " | ".join(ln.strip().removeprefix("motcomp build: ")
                               for ln in (p.stdout + p.stderr).splitlines()
                               if "motcomp build:" in ln)}
    if p.returncode != 0:
        out["result"] = f"pip wheel failed: {p.stderr.strip()[-500:]}"
        return out
    zipfile.ZipFile(next(wheels.glob("motcomp-*.whl"))).extractall(site)
    env = {"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}
    p = run([sys.executable, "-c", "import motcomp.core.native as n, motcomp.core.tick as t; "
             "print(n.ACTIVE); print(t.__file__)"], env=env, cwd=work)
    if p.returncode != 0:
        out["result"] = "BROKEN: " + (p.stderr.strip().splitlines() or ["?"])[-1]
        return out
    active, tick_file = p.stdout.strip().splitlines()
    chk = run([sys.executable, "-m", "motcomp", "config", "check",
               str(site / "motcomp" / "_config" / "motcomp.toml")], env=env, cwd=work)
    out["tick"] = f"{active} ({Path(tick_file).name})"
    out["result"] = ("works" if chk.returncode == 0 else
                     f"BROKEN: config check exit {chk.returncode}: {chk.stderr.strip()[-300:]}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("versions", nargs="*", help="mypy versions (default: the range's oldest "
                    "and newest)")
    ap.add_argument("--admit", action="store_true",
                    help="widen the copy's tested range to each version tried")
    args = ap.parse_args(argv)
    requirement = mypy_requirement(ROOT)
    lowest = re.search(r">=\s*([0-9][^,\s\"]*)", requirement)
    specs = ([f"=={v}" for v in args.versions] or
             [f"=={lowest.group(1)}" if lowest else requirement.removeprefix("mypy"),
              requirement.removeprefix("mypy")])
    print(f"pyproject.toml admits {requirement}")
    failed = False
    for spec in specs:
        with tempfile.TemporaryDirectory(prefix="motcomp-toolchain-") as tmp:
            res = try_version(spec, Path(tmp), args.admit)
        print(f"mypy {res['mypy']}: {res['result']}; tick: {res.get('tick', '-')}; "
              f"build {res.get('build_s', '-')} s: {res.get('build', '')}", flush=True)
        failed |= not res["result"].startswith("works")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
