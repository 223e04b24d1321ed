"""Shared fixtures and helpers."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
from collections.abc import Generator, Mapping
from pathlib import Path
from typing import Any

import pytest

from motcomp.core.models import P1D
from motcomp.runtime.probe import HostClock, loop_kept_from_cpu

ROOT = Path(__file__).resolve().parent.parent

RAILS = P1D(K=1.0, Td=0.0175, Tp1=0.1857683128)

_CPU_USE = pytest.StashKey[list[tuple[str, float, float, float]]]()


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--cpu-over", type=float, default=None, metavar="S",
                     help="list the tests that used more than S seconds of CPU: the test's "
                          "process and the child processes it waited for (docs/TESTING.md)")


def _cpu_s() -> tuple[float, float]:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, kids.ru_utime + kids.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None
                            ) -> Generator[None, None, None]:
    """With ``--cpu-over``: each test's wall time and CPU (its setup and teardown included)."""
    if item.config.getoption("--cpu-over") is None:
        yield
        return
    own0, kids0 = _cpu_s()
    wall0 = time.monotonic()
    yield
    own1, kids1 = _cpu_s()
    item.config.stash.setdefault(_CPU_USE, []).append(
        (item.nodeid, time.monotonic() - wall0, own1 - own0, kids1 - kids0))


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int,
                            config: pytest.Config) -> None:
    limit = config.getoption("--cpu-over")
    if limit is None:
        return
    rows = config.stash.get(_CPU_USE, [])
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
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                        request.node.nodeid],
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
