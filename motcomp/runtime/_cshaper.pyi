"""Types of the reference shaper's compiled loops (motcomp/runtime/_cshaper.c)."""

from collections.abc import Mapping

def update_axes(pos: Mapping[str, float], index: Mapping[str, int], driven: list[bool], t: float,
                fresh_allowed: bool, stale_after_s: float, live: list[float],
                t_frame: list[float], slope: list[float], period: list[float]) -> None: ...
def live_now(t_now: float, age: float, late: float, max_extrapolation_s: float,
             live: list[float], slope: list[float], t_frame: list[float],
             period: list[float]) -> list[float]: ...
