"""One rule for the JSON that motcomp writes: strict (``allow_nan=False``) and plain."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["finite"]


def finite(obj: Any) -> Any:
    """``obj`` for strict JSON: numpy numbers as Python's, NaN and infinities as None, mapping
    keys as strings, tuples as lists (recursively)."""
    if isinstance(obj, dict):
        return {str(k): finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
