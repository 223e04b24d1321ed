"""One BLAS thread for the design's linear algebra.

The design's linear algebra is small: SLSQP's least-squares steps over a few hundred
constraints and seven unknowns, eigenvalues of 21 x 21 companion matrices.  A second BLAS
thread never speeds it up, and OpenBLAS threads spin while they wait: on a 2-core host under
load, one optimisation took 6.8 s of CPU in SLSQP with two threads and 0.46 s with one
(docs/BENCHMARKS.md, "Optimal tuning").  :func:`single_threaded` sets every OpenBLAS loaded in
the process (numpy and scipy each load their own copy) to one thread for a block, and restores
their counts after it.  Where no OpenBLAS is found (another BLAS, a system without
``/proc/self/maps``), it does nothing: the results are the same, only slower.
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import wraps
from typing import ParamSpec, TypeVar

__all__ = ["single_threaded", "with_one_blas_thread"]

_P = ParamSpec("_P")
_R = TypeVar("_R")
_SUFFIXES = ("", "64_")
_PREFIXES = ("scipy_openblas", "openblas")
_lock = threading.Lock()
_depth = 0
_saved: list[tuple[Callable[[int], None], int]] = []


def _openblas() -> list[tuple[Callable[[], int], Callable[[int], None]]]:
    """``(get, set)`` of the thread count of every OpenBLAS mapped into the process."""
    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({parts[-1] for parts in (line.split() for line in maps)
                            if len(parts) >= 6 and "openblas" in parts[-1].lower()})
    except OSError:
        return []
    found = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix in _PREFIXES:
            for suffix in _SUFFIXES:
                get = getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
                put = getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
                if get is not None and put is not None:
                    get.restype = ctypes.c_int
                    put.argtypes = [ctypes.c_int]
                    found.append((get, put))
                    break
            else:
                continue
            break
    return found


@contextmanager
def single_threaded() -> Iterator[None]:
    """Run the block with one OpenBLAS thread (nested blocks share the outermost setting)."""
    global _depth
    import scipy.linalg  # noqa: F401  -- scipy's own OpenBLAS is loaded with it

    with _lock:
        if _depth == 0:
            _saved.clear()
            for get, put in _openblas():
                _saved.append((put, int(get())))
                put(1)
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                for put, count in _saved:
                    put(count)
                _saved.clear()


def with_one_blas_thread(fn: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorator: ``fn`` runs in :func:`single_threaded`."""
    @wraps(fn)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with single_threaded():
            return fn(*args, **kwargs)

    return wrapper
