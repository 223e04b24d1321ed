"""docs/BENCH.md's first bench, run as written: its commands parsed from the page, with free
ports for 7447-7449 and the 8 s lane change for the 22 s slalom; every process exits as the
page says and the recording holds all four keys."""

from __future__ import annotations

import json
import re
import shlex
import signal
import subprocess
import time
from pathlib import Path

import pytest

from motcomp.io.zenoh_io import free_tcp_port
from tests.conftest import ROOT, motcomp_cmd, subprocess_env

pytestmark = pytest.mark.slow

PAGE = ROOT / "docs" / "BENCH.md"


def bench_commands() -> list[list[str]]:
    """The commands of the page's marked block, split as a shell would."""
    text = PAGE.read_text()
    block = re.search(r"<!-- bench:[^>]*-->\s*```sh\n(.*?)```", text, re.S)
    assert block, "docs/BENCH.md lost its bench block"
    return [shlex.split(line) for line in block.group(1).splitlines() if line.strip()]


def test_the_page_names_every_command_of_the_bench() -> None:
    names = [c[1] for c in bench_commands()]
    assert names == ["config", "hil", "run", "record", "source", "status"]


def test_the_first_bench_runs_as_written(tmp_path: Path) -> None:
    ports = {str(p): str(free_tcp_port()) for p in (7447, 7448, 7449)}
    env = subprocess_env()

    def local(argv: list[str]) -> list[str]:
        assert argv[0] == "motcomp"
        out = [re.sub(r":(744[789])$", lambda m: ":" + ports[m.group(1)], a) for a in argv[1:]]
        return motcomp_cmd(*["lanechange" if a == "slalom" else a for a in out])

    example, hil, run, record, source, status = bench_commands()
    assert example[-2] == ">"
    with (tmp_path / example[-1]).open("w") as fh:
        subprocess.run(local(example[:-2]), stdout=fh, check=True, cwd=tmp_path, env=env,
                       timeout=60)
    logs = {n: (tmp_path / f"{n}.log").open("w") for n in ("hil", "run", "record")}
    procs: dict[str, subprocess.Popen[str]] = {}
    try:
        for name, argv in (("hil", hil), ("run", run)):
            procs[name] = subprocess.Popen(local(argv), cwd=tmp_path, env=env, text=True,
                                           stdout=logs[name], stderr=subprocess.STDOUT)
        t_end = time.monotonic() + 30  # the service is up when its status answers
        while True:
            p = subprocess.run(local(status), cwd=tmp_path, env=env, capture_output=True,
                               text=True, timeout=60)
            if p.returncode == 0 or time.monotonic() > t_end:
                break
        assert p.returncode == 0, (p.stderr, (tmp_path / "run.log").read_text())
        procs["record"] = subprocess.Popen(local(record), cwd=tmp_path, env=env, text=True,
                                           stdout=logs["record"], stderr=subprocess.STDOUT)
        t_end = time.monotonic() + 20
        while "recording" not in (tmp_path / "record.log").read_text():
            assert time.monotonic() < t_end and procs["record"].poll() is None, \
                (tmp_path / "record.log").read_text()
            time.sleep(0.1)
        p = subprocess.run(local(source), cwd=tmp_path, env=env, capture_output=True,
                           text=True, timeout=120)
        assert p.returncode == 0, p.stderr
        p = subprocess.run(local(status), cwd=tmp_path, env=env, capture_output=True,
                           text=True, timeout=60)
        assert p.returncode == 0 and p.stdout.startswith("mode"), p.stderr
        assert re.search(r"frames\s+received [1-9]\d* ", p.stdout), p.stdout
        procs["record"].send_signal(signal.SIGTERM)
        assert procs["record"].wait(timeout=30) == 0
        for name in ("run", "hil"):
            procs[name].send_signal(signal.SIGTERM)
            assert procs[name].wait(timeout=30) == 0, (tmp_path / f"{name}.log").read_text()
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for fh in logs.values():
            fh.close()
    summary = (tmp_path / "record.log").read_text()
    for key in ("sim/motion/setpoint", "platform/setpoint", "platform/feedback",
                "motcomp/status"):
        assert re.search(rf"  {re.escape(key)}: [1-9]", summary), (key, summary)
    assert "config: the service's, attached" in summary
    p = subprocess.run(motcomp_cmd("info", str(tmp_path / "session.mcap"), "--json"),
                       env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    keys = {k["key"]: k["messages"] for k in json.loads(p.stdout)["keys"]}
    assert keys["sim/motion/setpoint"] > 4000  # the lane change: 8000 frames, some skipped
