"""Shared fixtures and helpers."""

from __future__ import annotations

import fcntl
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Generator, Mapping
from pathlib import Path
from typing import IO, Any, cast

import pytest

from motcomp.core.models import P1D
from motcomp.runtime.probe import HostClock, loop_kept_from_cpu

ROOT = Path(__file__).resolve().parent.parent

RAILS = P1D(K=1.0, Td=0.0175, Tp1=0.1857683128)

_CPU_START = pytest.StashKey[tuple[float, float, float]]()
_LOCK = pytest.StashKey["_SuiteLock"]()
_LOCK_DIR_KEY = pytest.StashKey[Path]()
_LOCK_DIR = "motcomp_lock_dir"
_ALONE = pytest.StashKey[set[str]]()

ALONE_HELPERS = ("HostProbe", "judge_realtime", "skip_if_starved")
"""A test module that imports one of these judges what the host held while it ran: its tests
run with no other test of the suite beside them (as do those marked ``alone``)."""


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--cpu-over", type=float, default=None, metavar="S",
                     help="list the tests that used more than S seconds of CPU: the test's "
                          "process and the child processes it waited for (docs/TESTING.md)")


def pytest_configure(config: pytest.Config) -> None:
    """On several workers (pytest-xdist's ``-n``), the controller makes the directory of the
    workers' shared lock; each worker opens it.  pytest-xdist gives no worker a test before every
    worker has collected, so the workers' collections never run beside a test."""
    if hasattr(config, "workerinput"):
        where = config.workerinput.get(_LOCK_DIR)
        if where:
            config.stash[_LOCK] = _SuiteLock(Path(where))
    elif getattr(config.option, "numprocesses", None):
        config.stash[_LOCK_DIR_KEY] = Path(tempfile.mkdtemp(prefix="motcomp-tests-"))


def idle_cpus(seconds: float = 0.5) -> float:
    """How many of the host's CPUs were idle over ``seconds`` (/proc/stat: idle and I/O wait
    over all time; the host's CPU count if it cannot be read)."""
    def sample() -> tuple[int, int]:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        return v[3] + v[4], sum(v[:8])

    n = os.cpu_count() or 1
    try:
        idle0, total0 = sample()
        time.sleep(seconds)
        idle1, total1 = sample()
    except (OSError, ValueError, IndexError):
        return float(n)
    return n * (idle1 - idle0) / max(1, total1 - total0)


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int | None:
    """``-n auto``: a worker per CPU this process may use that the host leaves idle (a CPU hog
    beside the suite takes one), at least one; PYTEST_XDIST_AUTO_NUM_WORKERS overrides."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
        os.cpu_count() or 1)
    return max(1, min(usable, int(idle_cpus() + 0.5)))


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node: Any) -> None:
    """pytest-xdist: each worker gets the lock's directory."""
    where = node.config.stash.get(_LOCK_DIR_KEY, None)
    if where is not None:
        node.workerinput[_LOCK_DIR] = str(where)


def pytest_unconfigure(config: pytest.Config) -> None:
    if (lock := config.stash.get(_LOCK, None)) is not None:
        lock.release()
    if (where := config.stash.get(_LOCK_DIR_KEY, None)) is not None:
        shutil.rmtree(where, ignore_errors=True)


class _SuiteLock:
    """The workers' shared lock, taken per test module: shared by ordinary modules, exclusive
    for a module whose tests run alone.  A module waiting to run alone holds the gate, so no
    other module starts meanwhile (the ones running finish first)."""

    def __init__(self, where: Path) -> None:
        self._gate: IO[str] = (where / "gate").open("a")
        self._lock: IO[str] = (where / "lock").open("a")
        self.module: str | None = None

    def take(self, module: str, alone: bool) -> None:
        if module == self.module:
            return
        self.release()
        fcntl.flock(self._gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(self._lock, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        finally:
            fcntl.flock(self._gate, fcntl.LOCK_UN)
        self.module = module

    def release(self) -> None:
        if self.module is not None:
            fcntl.flock(self._lock, fcntl.LOCK_UN)
            self.module = None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The modules that run alone first (each worker collects the same order): the others then
    run side by side to the end."""
    alone: set[str] = set()
    for item in items:
        module = getattr(item, "module", None)
        if item.get_closest_marker("alone") is not None or (
                module is not None and any(name in vars(module) for name in ALONE_HELPERS)):
            alone.add(_module_of(item))
    config.stash[_ALONE] = alone
    items.sort(key=lambda it: _module_of(it) not in alone)


def _module_of(item: pytest.Item) -> str:
    return item.nodeid.split("::")[0]


def runs_alone(item: pytest.Item) -> bool:
    """Whether ``item``'s module runs with no other test beside it: it imports one of
    :data:`ALONE_HELPERS`, or one of its tests is marked ``alone``."""
    return _module_of(item) in item.config.stash.get(_ALONE, set())


def _cpu_s() -> tuple[float, float]:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, kids.ru_utime + kids.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None
                            ) -> Generator[None, None, None]:
    """On several workers, the module's share of the suite lock first; with ``--cpu-over``,
    the test's wall time and CPU from here to the end of its teardown."""
    if (lock := item.config.stash.get(_LOCK, None)) is not None:
        lock.take(_module_of(item), runs_alone(item))
    if item.config.getoption("--cpu-over") is not None:
        item.stash[_CPU_START] = (time.monotonic(), *_cpu_s())
    yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]
                              ) -> Generator[None, Any, None]:
    """With ``--cpu-over``: the test's wall time and CPU (its setup and teardown included) on
    its teardown's report, which reaches the controller from a worker too."""
    outcome = yield
    if call.when != "teardown" or (start := item.stash.get(_CPU_START, None)) is None:
        return
    own, kids = _cpu_s()
    outcome.get_result().user_properties.append(
        ("cpu", (time.monotonic() - start[0], own - start[1], kids - start[2])))


_CPU_ROWS: list[tuple[str, float, float, float]] = []
"""(test, wall time, its own CPU, its children's) from each test's teardown report."""


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.when != "teardown":
        return
    for name, value in report.user_properties:
        if name == "cpu":
            wall, own, kids = (float(v) for v in cast(tuple[float, float, float], value))
            _CPU_ROWS.append((report.nodeid, wall, own, kids))


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int,
                            config: pytest.Config) -> None:
    limit = config.getoption("--cpu-over")
    if limit is None:
        return
    rows = _CPU_ROWS
    over = sorted((r for r in rows if r[2] + r[3] > limit), key=lambda r: -(r[2] + r[3]))
    tr = terminalreporter
    tr.section(f"tests that used more than {limit:g} s of CPU")
    for nodeid, wall, own, kids in over:
        tr.write_line(f"{own + kids:7.1f} s CPU ({own:.1f} s its own, {kids:.1f} s its "
                      f"children's) in {wall:.1f} s: {nodeid}")
    total = sum(r[2] + r[3] for r in rows)
    tr.write_line(f"{len(over)} of {len(rows)} tests; all of them: {total:.0f} s of CPU")


@pytest.fixture
def rails() -> P1D:
    return RAILS


EXAMPLE_RAILS = ("design", "--plant", "rails", "--rule", "optimal", "--input-lag-ms", "2.8",
                 "--prediction", "on", "--band", "0.03", "2", "--chain-hf-gain", "20", "--json",
                 "--quiet")
"""The example config's rails design (config/motcomp.toml)."""


@pytest.fixture(scope="session")
def example_rails_design(tmp_path_factory: pytest.TempPathFactory
                         ) -> tuple[subprocess.CompletedProcess[str], Path]:
    """:data:`EXAMPLE_RAILS` run once per session with ``--out``, this machine's defaults: the
    finished process and the fragment it wrote."""
    frag = tmp_path_factory.mktemp("example_rails") / "design.toml"
    p = subprocess.run(motcomp_cmd(*EXAMPLE_RAILS, "--out", str(frag)), capture_output=True,
                       text=True, env=subprocess_env(), timeout=300)
    return p, frag


def motcomp_cmd(*args: str) -> list[str]:
    """Command line running this checkout's motcomp (works without installing)."""
    return [sys.executable, "-m", "motcomp", *args]


def subprocess_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


STARVED = "of its deadlines while the data were recorded"
"""What ``motcomp identify`` says when it refuses a fragment from a run the host starved ..."""
DEGRADED = "while the data were recorded: the host took the loop's time"
"""... and when it writes one with a warning: the service missed more than
:data:`~motcomp.runtime.clock.DEGRADED_MISSED_SHARE` of its deadlines during the run."""


def skip_if_starved(p: subprocess.CompletedProcess[str], what: str) -> None:
    """``identify`` refused its fragment because the service missed too many deadlines during
    the run (exit 2, said on stderr): the host could not support the run, which the product said
    clearly; the test reports it as not judged (docs/TESTING.md)."""
    if p.returncode == 2 and STARVED in p.stderr:
        pytest.skip(f"not judged ({what}): {p.stderr.strip().splitlines()[-1]}")


def judge_realtime(clock: HostClock | None, what: str,
                   status: Mapping[str, Any] | None = None,
                   identify: subprocess.CompletedProcess[str] | None = None) -> None:
    """Skip the rest of a real-time test as *not judged*, with the host's figures, when the host
    itself could not hold the loop rate while it was measured: its bare clock (:class:`HostProbe`
    around the measurement) missed too many deadlines; or the service's loop or its platform's
    (the service's ``status`` at the end, if given) missed too many waiting for a CPU that other
    threads held (:func:`~motcomp.runtime.probe.loop_kept_from_cpu`); or ``identify`` (its run,
    if given) wrote its fragment warning that the fit carries the host's stalls.  Never a wider
    bound: docs/TESTING.md."""
    if clock is None:
        raise AssertionError("the host probe has no result: judge after its run")
    if not clock.holds():
        pytest.skip(f"not judged ({what}): {clock.describe()}")
    if status is not None and (why := loop_kept_from_cpu(status)) is not None:
        pytest.skip(f"not judged ({what}): {why}")
    if identify is not None and identify.returncode == 0 and DEGRADED in identify.stderr:
        warned = next(ln for ln in identify.stderr.splitlines() if DEGRADED in ln)
        pytest.skip(f"not judged ({what}): identify warned: {warned.strip()}")


def ran_in_plain_python(request: pytest.FixtureRequest) -> bool:
    """For a test that replaces functions of the tick's modules (which the compiled tick calls
    natively, past the module's attributes): under the compiled tick, run the test again in a
    child pytest with the plain Python modules (``MOTCOMP_PURE_PYTHON=1``), fail if it fails
    there, and return True (the caller returns); under the plain Python, return False."""
    from motcomp.core import native

    if not native.ACTIVE.startswith("compiled"):
        return False
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n",
                        "0", request.node.nodeid],
                       cwd=ROOT, env={**os.environ, native.PURE_ENV: "1"}, capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, f"in the plain Python tick:\n{p.stdout[-4000:]}\n{p.stderr[-2000:]}"
    assert "\n1 passed" in "\n" + p.stdout, p.stdout[-2000:]  # it ran, and was not skipped
    return True


ADMIN = "[admin]\nenabled = true\n"
"""The site config's lines that enable the admin endpoints (reload, bypass)."""


def site_config(path: Path, *includes: Path | str) -> Path:
    """Write the site config ``path``: the example config, then ``includes``, admin enabled."""
    from motcomp.resources import config_file

    files = ", ".join(f'"{f}"' for f in (config_file("motcomp.toml"), *includes))
    path.write_text(f"include = [{files}]\n{ADMIN}")
    return path
