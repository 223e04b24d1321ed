"""The predictive prefilter applied by the recursion of its factors, through ``lfilter``:
``L_0 = s / (1 - a z^-1)``, ``L_k = L_{k-1} (z^-1 - a) / (1 - a z^-1)`` -- written here, not taken
from the package, so that tests compare the package's filters with an independent computation."""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import lfilter

from motcomp.core.predictor import PredictorParams


def laguerre_filter(p: PredictorParams, x: np.ndarray) -> np.ndarray:
    """``F`` of ``p`` applied to ``x`` from rest."""
    a = math.exp(-2 * math.pi * p.pole_hz / p.rate_hz)
    y = p.coeffs[0] * x
    lk = lfilter([math.sqrt(1 - a * a)], [1.0, -a], x)
    for c in p.coeffs[1:]:
        y = y + c * lk
        lk = lfilter([-a, 1.0], [1.0, -a], lk)
    return np.asarray(y)
