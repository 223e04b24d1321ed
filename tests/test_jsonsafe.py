"""motcomp.jsonsafe: the one rule for strict JSON."""

from __future__ import annotations

import json
import math

import numpy as np

from motcomp.jsonsafe import finite


def test_strict_json_of_numpy_and_non_finite_values() -> None:
    obj = {"a": np.float64(1.5), 2: [np.int64(3), math.nan, (math.inf, -math.inf)],
           "b": {"c": np.float32(0.25)}}
    out = finite(obj)
    assert out == {"a": 1.5, "2": [3, None, [None, None]], "b": {"c": 0.25}}
    assert type(out["a"]) is float and type(out["2"][0]) is int
    json.dumps(out, allow_nan=False)  # strict: no NaN left
