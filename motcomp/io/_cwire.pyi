"""Types of the service's compiled wire operations (motcomp/io/_cwire.c)."""

from collections.abc import Mapping, Sequence
from typing import Any

def pack_output(seq: int, t: float, src_seq: int, axes: Sequence[str],
                positions: Sequence[float], flags: Sequence[str]) -> bytes: ...
def parse_input(payload: bytes, index: Mapping[str, int], lo: Any, hi: Any
                ) -> tuple[int, float | None, dict[str, float]] | None: ...
