"""Types of the compiled tick (motcomp/core/_ckernel.c)."""

from collections.abc import Sequence
from typing import Any

BUFFERS: str

class Stepper:
    def __init__(self, n: int, hist_len: int, buffers: Sequence[Any]) -> None: ...
    def step(self, reference: Sequence[float], k: int, fade_step: float
             ) -> tuple[list[float], list[int]]: ...
