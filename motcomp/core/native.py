"""What the tick's classes need to run both as plain Python and compiled by mypyc (the same
source; docs/BENCHMARKS.md, "The tick compiled").

A compiled class has no instance ``__dict__``: ``copy`` and ``pickle`` (replay snapshots, the
reload reader process) work on it only when it is declared
``@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)``, and a compiled frozen
dataclass cannot be restored field by field, so each defines ``__reduce__`` as
:func:`frozen_reduce`.  Both are no-ops for the plain Python module.
"""

from __future__ import annotations

import dataclasses
from typing import Any

__all__ = ["frozen_reduce"]


def frozen_reduce(obj: Any) -> tuple[Any, tuple[Any, ...]]:
    """``__reduce__`` of a frozen dataclass: rebuilt by its constructor from its ``init``
    fields (fields computed in ``__post_init__`` are computed again)."""
    return type(obj), tuple(getattr(obj, f.name) for f in dataclasses.fields(obj) if f.init)
