"""What "the same design" means in the tests: gains within the optimiser's stated tolerance
(:data:`motcomp.design.optimal.GAIN_RTOL`), prefilters whose frequency responses agree within
:data:`motcomp.design.predictor.RESPONSE_RTOL` -- never an optimiser's output bit for bit."""

from __future__ import annotations

import math

import numpy as np

from motcomp.core.pid import PIDGains
from motcomp.core.predictor import PredictorParams, predictor_freqresp
from motcomp.design.optimal import GAIN_RTOL
from motcomp.design.predictor import RESPONSE_RTOL

GAINS = ("kp", "ki", "kd", "tf", "b", "c")


def assert_same_gains(a: PIDGains, b: PIDGains) -> None:
    for name in GAINS:
        x, y = getattr(a, name), getattr(b, name)
        assert math.isclose(x, y, rel_tol=GAIN_RTOL), (name, x, y)


def assert_same_prefilter(a: PredictorParams, b: PredictorParams) -> None:
    f = np.concatenate([np.geomspace(1e-3, 10.0, 400), np.linspace(10.0, 499.0, 400)])
    fa, fb = predictor_freqresp(a, f), predictor_freqresp(b, f)
    assert np.max(np.abs(fa - fb)) <= RESPONSE_RTOL * np.max(np.abs(fa))


def prefilter(table: dict[str, object]) -> PredictorParams:
    """A ``prediction`` table (a fragment's, the report's) as the service reads it."""
    return PredictorParams(pole_hz=float(table["pole_hz"]),  # type: ignore[arg-type]
                           coeffs=tuple(table["coeffs"]),  # type: ignore[arg-type]
                           rate_hz=float(table["rate_hz"]),  # type: ignore[arg-type]
                           band_hz=tuple(table["band_hz"]))  # type: ignore[arg-type]
