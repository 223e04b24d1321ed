"""Real-time scheduling and pinning are best effort and report what happened."""

from __future__ import annotations

import os
import subprocess
import sys

from motcomp.runtime.rt import pin_to_cpu, set_realtime


def test_off_by_default() -> None:
    assert "normal" in set_realtime(0)
    assert pin_to_cpu(-1) == "not pinned"


def test_reports_match_the_kernel_state() -> None:
    # in a child process, so this test process keeps its own policy
    code = (
        "import os, threading\n"
        "from motcomp.runtime.rt import set_realtime, pin_to_cpu\n"
        "out = {}\n"
        "def run():\n"
        "    out['rt'] = set_realtime(1)\n"
        "    out['pol'] = os.sched_getscheduler(0)\n"
        "    out['pin'] = pin_to_cpu(0)\n"
        "    out['aff'] = os.sched_getaffinity(0)\n"
        "t = threading.Thread(target=run); t.start(); t.join()\n"
        "print(out['rt']); print(out['pol'] == os.SCHED_FIFO); print(out['pin']);"
        " print(out['aff'] == {0})\n"
        "print(os.sched_getscheduler(0) == os.SCHED_FIFO)\n"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    lines = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           env=env, check=True, timeout=60).stdout.splitlines()
    rt, is_fifo, pin, pinned, main_fifo = lines
    assert ("SCHED_FIFO priority 1" in rt) == (is_fifo == "True")
    assert ("pinned to CPU 0" in pin) == (pinned == "True")
    assert main_fifo == "False"  # only the calling thread was raised
