"""The floating-point mode the tick computes in: subnormal numbers flushed to zero.

At rest, the states of decaying filters (the reference's, the prefilters', the simulated
platform's) sink towards zero through the subnormals -- below 2.2e-308 --, and arithmetic on such
numbers takes some CPUs a hundred times longer than on normal ones.  Nothing the tick computes
means anything at that scale, so every thread that computes ticks flushes them: the service's
loop (:func:`motcomp.runtime.rt.schedule_loop`), the simulated platform's loop, a replay's engine
and the synthetic sessions -- the replay computes in the mode the service did, so it stays bit
for bit.  The mode is per thread (x86-64: MXCSR's FTZ and DAZ; AArch64: FPCR's FZ), set
through glibc's ``fegetenv``/``fesetenv``; threads started afterwards inherit it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform
import struct
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["FLUSHED", "flush_subnormals", "subnormals_flushed"]

FLUSHED = "subnormals flushed to zero"
"""What :func:`flush_subnormals` says when the mode holds (the service's status ``realtime``
ends with it)."""

_FLUSH_BITS = {"x86_64": (28, 0x8040), "aarch64": (0, 1 << 24)}
"""Where the flush-to-zero bits sit in glibc's ``fenv_t``: x86-64, the MXCSR (offset 28) with
FTZ (bit 15) and DAZ (bit 6: subnormal inputs read as zero); AArch64, the FPCR (offset 0) with
FZ (bit 24, both)."""
_FENV_BYTES = 64
"""Room for a ``fenv_t`` (32 bytes on x86-64, 8 on AArch64)."""


def _fenv_calls() -> tuple[Any, Any] | None:
    """glibc's ``fegetenv`` and ``fesetenv`` (None where they cannot be found)."""
    for name in (None, ctypes.util.find_library("m")):
        try:
            lib = ctypes.CDLL(name)
            return lib.fegetenv, lib.fesetenv
        except (OSError, AttributeError):
            continue
    return None


def _env() -> tuple[Any, Any, Any, int, int] | None:
    """``(fesetenv, the calling thread's fenv_t, its control word, offset, bits)``, or None
    where the mode is not known (another OS, CPU or a 32-bit process) or glibc fails."""
    where = _FLUSH_BITS.get(platform.machine())
    calls = _fenv_calls() if sys.platform.startswith("linux") else None
    if where is None or calls is None or struct.calcsize("P") != 8:
        return None
    get, put = calls
    offset, bits = where
    env = (ctypes.c_ubyte * _FENV_BYTES)()
    if get(env) != 0:
        return None
    return put, env, ctypes.c_uint32.from_buffer(env, offset), offset, bits


def _is_zero(x: float) -> bool:
    """True if ``x``'s bits are all zero but the sign's (read from its bytes: no arithmetic,
    which the mode itself would bend)."""
    return struct.unpack("<Q", struct.pack("<d", x))[0] & 0x7FFF_FFFF_FFFF_FFFF == 0


def _flushes(smallest_normal: float, subnormal: float) -> bool:
    """Whether the calling thread's arithmetic flushes a subnormal result (a quarter of the
    smallest normal) and reads a subnormal input as zero (a subnormal times 2^52, a normal
    number unless the input read as zero)."""
    return _is_zero(smallest_normal / 4.0) and _is_zero(subnormal * 2.0**52)


def _probe() -> bool:
    """True if the calling thread's arithmetic flushes subnormals (computed on a subnormal made
    from its bits)."""
    return _flushes(sys.float_info.min, struct.unpack("<d", struct.pack("<Q", 1))[0])


def flush_subnormals(on: bool = True) -> str:
    """Flush subnormal numbers to zero (results and inputs) in the calling thread's float
    arithmetic -- Python's, numpy's, the compiled tick's -- or stop (``on`` False); threads it
    starts afterwards inherit the mode.  Returns what happened, checked by computing."""
    found = _env()
    if found is None:
        return (f"subnormals not flushed (not known on {platform.system()} "
                f"{platform.machine()}, {8 * struct.calcsize('P')}-bit)")
    put, env, word, _, bits = found
    word.value = word.value | bits if on else word.value & ~bits
    if put(env) != 0:
        return "subnormals not flushed (fesetenv failed)"
    if _probe() != on:
        return "subnormals not flushed (the CPU ignored the mode)" if on else \
            "subnormals still flushed (the CPU ignored the mode)"
    return FLUSHED if on else "subnormals kept"


@contextmanager
def subnormals_flushed(on: bool = True) -> Iterator[str]:
    """:func:`flush_subnormals` (``on``) in the calling thread for the block, then its
    floating-point environment exactly as it was; yields what happened."""
    saved = _env()
    report = flush_subnormals(on)
    try:
        yield report
    finally:
        if saved is not None:
            put, env = saved[0], saved[1]
            put(env)
