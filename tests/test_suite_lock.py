"""The suite's lock on several workers (tests/conftest.py): ordinary modules side by side, a
module that runs alone with none beside it, and no new module started while one waits to run
alone."""

from __future__ import annotations

import threading
from pathlib import Path

from tests.conftest import _SuiteLock


def test_a_module_alone_waits_for_those_running_and_holds_back_those_to_come(tmp_path: Path
                                                                             ) -> None:
    a, b, c = (_SuiteLock(tmp_path) for _ in range(3))
    a.take("m1", alone=False)
    b.take("m2", alone=False)  # beside m1: no wait
    order: list[str] = []
    alone_in, alone_out = threading.Event(), threading.Event()

    def alone() -> None:
        c.take("m3", alone=True)
        order.append("m3")
        alone_in.set()
        alone_out.wait(10)
        c.release()

    def later() -> None:
        b.take("m4", alone=False)  # leaves m2, then waits behind m3
        order.append("m4")

    t_alone = threading.Thread(target=alone)
    t_alone.start()
    assert not alone_in.wait(0.3)  # m1 and m2 still run
    t_later = threading.Thread(target=later)
    t_later.start()
    t_later.join(0.3)
    assert order == []  # m2 left, m1 still runs, m3 waits: m4 waits behind it
    a.release()
    assert alone_in.wait(10)
    t_later.join(0.3)
    assert order == ["m3"]  # alone: m4 has not started
    alone_out.set()
    t_alone.join(10)
    t_later.join(10)
    assert order == ["m3", "m4"]
    b.release()


def test_the_same_module_takes_nothing_again(tmp_path: Path) -> None:
    a, b = _SuiteLock(tmp_path), _SuiteLock(tmp_path)
    a.take("m1", alone=True)
    a.take("m1", alone=True)  # its next test: still held, no wait on itself
    done = threading.Event()

    def other() -> None:
        b.take("m2", alone=False)
        done.set()

    t = threading.Thread(target=other)
    t.start()
    assert not done.wait(0.3)
    a.take("m5", alone=False)  # leaves m1: m2 may run beside m5
    assert done.wait(10)
    t.join(10)
    a.release()
    b.release()
