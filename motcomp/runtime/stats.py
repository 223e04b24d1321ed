"""Loop statistics with bounded memory: the loop writes, the status thread reads.

The loop thread stores one compute time and one lateness per tick into fixed ring buffers (a
float store, no allocation); the status thread computes percentiles over a copy.  Torn reads
between the two threads only blur a percentile by one sample.
"""

from __future__ import annotations

import numpy as np

__all__ = ["LoopStats"]


class LoopStats:
    """Ring buffers of the last ``window`` ticks, plus running maxima."""

    def __init__(self, window: int) -> None:
        self.window = max(int(window), 16)
        self.compute_us = np.zeros(self.window)
        self.late_us = np.zeros(self.window)
        self.n = 0
        self.max_compute_us = 0.0
        self.max_late_us = 0.0

    def record(self, compute_us: float, late_us: float) -> None:
        i = self.n % self.window
        self.compute_us[i] = compute_us
        self.late_us[i] = late_us
        self.n += 1
        if compute_us > self.max_compute_us:
            self.max_compute_us = compute_us
        if late_us > self.max_late_us:
            self.max_late_us = late_us

    def snapshot(self) -> dict[str, float]:
        """Percentiles (us) over the window, and the maxima since start."""
        k = min(self.n, self.window)
        if k == 0:
            return {}
        comp = self.compute_us[:k].copy()
        late = self.late_us[:k].copy()
        cq = np.percentile(comp, [50, 99, 99.9])
        lq = np.percentile(late, [50, 99, 99.9])
        return {
            "compute_p50_us": float(cq[0]), "compute_p99_us": float(cq[1]),
            "compute_p999_us": float(cq[2]), "compute_max_us": self.max_compute_us,
            "late_p50_us": float(lq[0]), "late_p99_us": float(lq[1]),
            "late_p999_us": float(lq[2]), "late_max_us": self.max_late_us,
        }
