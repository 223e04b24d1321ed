"""Progress on a stream that is not a terminal: plain lines while a long job runs, even one
that reports nothing in between (a log file, a systemd unit, CI); nothing for a short job, and
nothing with ``quiet``."""

from __future__ import annotations

import io
import subprocess
import time

from motcomp.progress import Progress
from tests.conftest import motcomp_cmd, subprocess_env


def test_plain_lines_while_a_silent_job_runs_and_one_at_its_end() -> None:
    out = io.StringIO()
    with Progress("fitting", total=4.0, stream=out, every_s=0.05) as bar:
        bar.advance(note="p1d")
        time.sleep(0.3)  # the job reports nothing for a while
    lines = out.getvalue().splitlines()
    assert len(lines) >= 3, lines
    assert lines[0].startswith("fitting: 1.0 of 4.0 (25 %) after ") and lines[0].endswith(" p1d")
    assert lines[-1].startswith("fitting: done after ") and lines[-1].endswith(" s")
    assert "\r" not in out.getvalue()


def test_short_jobs_and_quiet_print_nothing_and_a_failure_says_stopped() -> None:
    out = io.StringIO()
    with Progress("x", total=1.0, stream=out):
        pass
    with Progress("q", total=1.0, stream=out, quiet=True, every_s=0.01):
        time.sleep(0.05)
    assert out.getvalue() == ""
    try:
        with Progress("y", total=1.0, stream=out, every_s=0.02):
            time.sleep(0.1)
            raise ValueError("boom")
    except ValueError:
        pass
    assert out.getvalue().splitlines()[-1].startswith("y: stopped after ")
    # a job that handled a signal and returned: stopped too, not done, and not at 100 %
    with Progress("z", total=10.0, stream=out, every_s=0.02) as bar:
        bar.update(4.0)
        time.sleep(0.1)
        bar.interrupted()
    assert out.getvalue().splitlines()[-1].startswith("z: stopped after ")
    assert bar.done == 4.0


def test_a_long_command_is_not_silent_when_stderr_is_a_file() -> None:
    """``motcomp source`` waiting 7 s for a service that is not there, its progress every 5 s:
    a line says how far it got, then the error."""
    p = subprocess.run(motcomp_cmd("source", "--signal", "slalom", "-e", "tcp/127.0.0.1:1",
                                   "--wait-peer", "7"),
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert p.returncode != 0
    assert "source: 0.0 of " in p.stderr and " after 5 s" in p.stderr, p.stderr
    assert "no subscriber of sim/motion/setpoint" in p.stderr
