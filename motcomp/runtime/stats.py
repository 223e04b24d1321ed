"""Loop statistics with bounded memory and bounded cost: the loop writes, the status thread reads.

The loop thread counts each tick's compute time and lateness into log-spaced histograms
(:data:`BINS_PER_DECADE` bins per decade from :data:`LOW_US`, so a bin is 2.3 % wide) kept per
*block* of ticks; a ring of :data:`BLOCKS` blocks plus the one being filled covers the window.
Recording is two integer increments; the status thread sums 33 small histograms, so a status
costs tens of microseconds whatever the window (percentiles over a raw window of samples cost
milliseconds of one C call holding the GIL: at 1 Hz that stalled the loop thread).

Percentiles are read as the upper edge of the bin that holds the nearest-rank sample: never
below the exact nearest-rank percentile, at most one bin width above it.  Torn reads between the
two threads only blur a percentile by a sample.  Maxima are exact, since start.
"""

from __future__ import annotations

import math
from array import array

import numpy as np

__all__ = ["BINS_PER_DECADE", "BLOCKS", "LOW_US", "LoopStats"]

LOW_US = 0.1
"""Lower edge of the first bin; smaller values (and zero or negative lateness) count there."""
BINS_PER_DECADE = 100
DECADES = 8
"""0.1 us to 10 s; larger values count in the last bin (the maxima stay exact)."""
BLOCKS = 32
_NBINS = BINS_PER_DECADE * DECADES + 1
_LOG_LOW = math.log10(LOW_US)
_EDGES = LOW_US * 10.0 ** (np.arange(1, _NBINS + 1) / BINS_PER_DECADE)
"""Upper edge of each bin (us)."""
_QUANTILES = (("p50", 0.5), ("p99", 0.99), ("p999", 0.999))


def _bin(x: float) -> int:
    if x <= LOW_US:
        return 0
    return min(int((math.log10(x) - _LOG_LOW) * BINS_PER_DECADE), _NBINS - 1)


def _quantiles(hist: np.ndarray) -> list[float]:
    n = int(hist.sum())
    cum = np.cumsum(hist)
    out = []
    for _, q in _QUANTILES:
        rank = max(1, math.ceil(q * n))  # nearest rank
        out.append(float(_EDGES[int(np.searchsorted(cum, rank))]))
    return out


class LoopStats:
    """Histograms of about the last ``window`` ticks (between ``window`` and ``window`` plus one
    block), plus running maxima, of each of the named ``series`` (default: compute time and
    lateness; the service also records the whole tick and its transport calls)."""

    def __init__(self, window: int, series: tuple[str, ...] = ("compute", "late")) -> None:
        self.window = max(int(window), BLOCKS)
        self.block = math.ceil(self.window / BLOCKS)
        self.series = tuple(series)
        self._zero = array("q", bytes(8 * _NBINS))
        # per series, a ring of BLOCKS + 1 histograms
        self._hists = [[array("q", self._zero) for _ in range(BLOCKS + 1)] for _ in series]
        self._cur = [h[0] for h in self._hists]
        self._left = self.block
        self._slot = 0
        self.n = 0
        self.maxima = [0.0] * len(series)

    def record(self, *values_us: float) -> None:
        """One tick's values, in the order of :attr:`series`."""
        if self._left == 0:  # start the next block, overwriting the oldest
            self._slot = slot = (self._slot + 1) % (BLOCKS + 1)
            for j, hists in enumerate(self._hists):
                cur = self._cur[j] = hists[slot]
                cur[:] = self._zero
            self._left = self.block
        self._left -= 1
        peaks = self.maxima
        for j, (cur, x) in enumerate(zip(self._cur, values_us, strict=True)):
            cur[_bin(x)] += 1
            if x > peaks[j]:
                peaks[j] = x
        self.n += 1

    def snapshot(self) -> dict[str, float]:
        """``{series}_{p50,p99,p999,max}_us``: percentiles over the window, maxima since start."""
        if self.n == 0:
            return {}
        out: dict[str, float] = {}
        for name, blocks, peak in zip(self.series, self._hists, self.maxima, strict=True):
            hist = np.zeros(_NBINS, np.int64)
            for b in blocks:
                hist += np.frombuffer(b.tobytes(), np.int64)  # a copy: no buffer export
            for (q, _), v in zip(_QUANTILES, _quantiles(hist), strict=True):
                out[f"{name}_{q}_us"] = min(v, peak)  # the bin's edge may lie above the max
            out[f"{name}_max_us"] = peak
        return out
