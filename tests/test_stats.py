"""Loop statistics: histogram percentiles against exact order statistics, the sliding window."""

from __future__ import annotations

import math

import numpy as np
import pytest

from motcomp.runtime.stats import BINS_PER_DECADE, BLOCKS, LoopStats

WIDTH = 10 ** (1 / BINS_PER_DECADE)  # ratio of a bin's upper to lower edge


def nearest_rank(x: np.ndarray, q: float) -> float:
    s = np.sort(x)
    return float(s[max(1, math.ceil(q * s.size)) - 1])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_percentiles_bracket_the_exact_order_statistics(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 20_000
    compute = rng.gamma(2.0, 40.0, n) + rng.pareto(1.5, n) * 5.0  # a heavy tail
    late = np.abs(rng.normal(0.0, 30.0, n))
    st = LoopStats(n)
    for c, la in zip(compute.tolist(), late.tolist(), strict=True):
        st.record(c, la)
    snap = st.snapshot()
    for name, x in (("compute", compute), ("late", late)):
        for key, q in (("p50", 0.5), ("p99", 0.99), ("p999", 0.999)):
            exact = nearest_rank(x, q)
            got = snap[f"{name}_{key}_us"]
            assert exact <= got <= exact * WIDTH * (1 + 1e-12), (name, key, exact, got)
        assert snap[f"{name}_max_us"] == x.max()


def test_window_forgets_old_ticks_and_keeps_exact_maxima() -> None:
    st = LoopStats(1000)
    for _ in range(1000):  # a slow spell, then the window and two blocks of fast ticks
        st.record(500.0, 900.0)
    for _ in range(1000 + 2 * st.block):
        st.record(20.0, 2.0)
    snap = st.snapshot()
    assert 20.0 <= snap["compute_p999_us"] <= 20.0 * WIDTH
    assert 2.0 <= snap["late_p999_us"] <= 2.0 * WIDTH
    assert snap["compute_max_us"] == 500.0 and snap["late_max_us"] == 900.0
    # the window spans BLOCKS full blocks plus the one being filled: one fast block less and
    # a slow tick is still in it
    st2 = LoopStats(1000)
    for _ in range(1000):
        st2.record(500.0, 900.0)
    for _ in range(BLOCKS * st2.block - 1):
        st2.record(20.0, 2.0)
    assert st2.snapshot()["compute_p999_us"] == 500.0


def test_zero_and_out_of_range_values() -> None:
    st = LoopStats(100)
    assert st.snapshot() == {}
    for _ in range(100):
        st.record(0.0, -3.0)  # a deadline met exactly; a clock that went backwards
    snap = st.snapshot()
    assert snap["compute_p50_us"] == 0.0 and snap["late_p999_us"] == 0.0
    st.record(5e8, 1.0)  # beyond the last bin: counted there, the maximum stays exact
    assert st.snapshot()["compute_max_us"] == 5e8


def test_named_series_are_kept_apart() -> None:
    st = LoopStats(100, ("tick", "compute", "io", "late"))
    for k in range(100):
        st.record(30.0 + k % 2, 20.0, 10.0 + k % 2, 1.0)
    snap = st.snapshot()
    assert sorted({key.split("_")[0] for key in snap}) == ["compute", "io", "late", "tick"]
    assert snap["tick_max_us"] == 31.0 and snap["io_max_us"] == 11.0
    assert 20.0 <= snap["compute_p99_us"] <= 20.0 * WIDTH
    with pytest.raises(ValueError):
        st.record(1.0, 2.0)  # one value per series
