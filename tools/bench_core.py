"""Benchmark: the cost of one tick for 8 axes at 1 kHz, in this process, without transport.

Times ``Compensator.step`` alone (the control law) and the whole
:func:`motcomp.core.tick.step` (a valid input frame every tick, encoded beforehand with
:func:`motcomp.io.wire.encode_input`: parse and check, reference, compensator, saturation
verdicts), both built from the example config as the service builds them
(:func:`motcomp.config.new_tick`), plus a numpy-vectorised sketch of the compensator's linear
arithmetic as a lower bound of what vectorising over 8 axes would cost.  The three run
interleaved in blocks, each on its own continuous timeline, ``gc.freeze()``-d as the service's
loop is.

With ``--gaps`` it times ``tick.step`` alone with a gap between two calls, spent spinning on the
clock in this thread (nothing of this process sleeps or runs in between): from back to back to
3 ms, interleaved in rounds.  Where the tick costs more after a longer gap, what it left in the
CPU's caches and predictors decays while it does nothing -- the machine's other work, on this
host or on the physical cores under a virtual one -- and the loop at 1 kHz pays that at every
tick (docs/BENCHMARKS.md, "The tick after a gap").

With ``--compare-plain`` the whole measurement runs in child processes, alternately with the
installed tick (compiled by mypyc where the install compiled it) and with the plain Python
modules (``MOTCOMP_PURE_PYTHON=1``), three rounds each, and the section gives both and their
ratio (docs/BENCHMARKS.md, "The tick compiled").

Writes the "core" section of docs/BENCHMARKS.md.
Usage: ``python tools/bench_core.py [--ticks 60000] [--quick] [--no-write] [--compare-plain |
--gaps]``
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable

import numpy as np
from _bench import machine, write_section

from motcomp.config import load_config, new_tick
from motcomp.core import native
from motcomp.core.axes import AXES
from motcomp.core.compensator import Compensator
from motcomp.core.models import p1d_coefficients
from motcomp.core.tick import step
from motcomp.io.wire import encode_input
from motcomp.resources import config_file

BLOCKS = 12
"""Blocks each implementation's ticks are cut into; the implementations alternate by block."""


class NumpyTick:
    """The compensator's linear arithmetic (PID, internal model, a velocity and acceleration
    clip) vectorised over axes with numpy; no bypass, no setpoint weights, no target tracker:
    it does less than :meth:`Compensator.step`, so its time is a lower bound."""

    def __init__(self, comp: Compensator) -> None:
        n = comp.n
        h = comp.dt_s
        g = comp.gains
        self.kp = np.array([x.kp for x in g])
        self.kih = np.array([x.ki * h for x in g])
        self.ad = np.array([x.tf / (x.tf + h) for x in g])
        self.bd = np.array([x.kd / (x.tf + h) for x in g])
        co = [p1d_coefficients(m, h) for m in comp.models]
        self.phi, self.g0, self.g1 = (np.array([c[i] for c in co]) for i in range(3))
        d = np.array([c[3] for c in co])
        self.L = 1 << math.ceil(math.log2(int(d.max()) + 2))
        self.base = np.arange(n) * self.L
        self.off0, self.off1 = 1 - d, -d
        self.hist_c = np.zeros(n * self.L)
        self.hist_m = np.zeros(n * self.L)
        self.xc, self.xm, self.integ, self.deriv, self.wp, self.u, self.v = (
            np.zeros(n) for _ in range(7))
        lim = comp.limits
        self.pmin, self.pmax, self.vmax = lim.p_min, lim.p_max, lim.v_max
        self.ah = lim.a_max * h
        self.two_a = 2 * lim.a_max
        self.h = h
        self.k = 0

    def step(self, r: np.ndarray) -> np.ndarray:
        r = np.where(np.isfinite(r), r, 0.0)
        y = self.xc
        w = r - y
        self.deriv = self.ad * self.deriv + self.bd * (w - self.wp)
        self.wp = w
        v = self.kp * w + self.integ + self.deriv
        vel = (v - self.u) / self.h
        b_hi = np.sqrt(self.ah**2 + self.two_a * np.maximum(self.pmax - self.u, 0)) - self.ah
        b_lo = self.ah - np.sqrt(self.ah**2 + self.two_a * np.maximum(self.u - self.pmin, 0))
        vel = np.clip(vel, np.maximum(b_lo, -self.vmax), np.minimum(b_hi, self.vmax))
        vel = np.clip(vel, self.v - self.ah, self.v + self.ah)
        u = self.u + vel * self.h
        self.v = vel
        self.u = u
        self.integ = self.integ + self.kih * w
        mask = self.L - 1
        k = self.k
        self.hist_c[self.base + (k & mask)] = v
        self.xc = (self.phi * y + self.g0 * self.hist_c[self.base + ((k + self.off0) & mask)]
                   + self.g1 * self.hist_c[self.base + ((k + self.off1) & mask)])
        self.hist_m[self.base + (k & mask)] = u
        self.xm = (self.phi * self.xm + self.g0 * self.hist_m[self.base + ((k + self.off0) & mask)]
                   + self.g1 * self.hist_m[self.base + ((k + self.off1) & mask)])
        self.k = k + 1
        return u


def references(ticks: int, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``(ticks, 8)`` sinusoids at 0.3 Hz, a different phase per axis, within half of each
    axis' position range."""
    t = np.arange(ticks) / 1000.0
    amp = 0.5 * (hi - lo) / 2
    mid = (hi + lo) / 2
    return np.stack([mid[i] + amp[i] * np.sin(2 * math.pi * 0.3 * t + i)
                     for i in range(len(AXES))], axis=1)


def input_frames(rows: list[list[float]]) -> list[bytes]:
    """A valid 8-axis input frame per row, sample ``k`` at ``k`` ms."""
    return [encode_input(k, k / 1000.0, dict(zip(AXES, row, strict=True)))
            for k, row in enumerate(rows)]


def measure(call: Callable[[int], object], ks: range) -> np.ndarray:
    """Time ``call(k)`` for each ``k`` (us)."""
    out = np.empty(len(ks))
    clock = time.perf_counter_ns
    for j, k in enumerate(ks):
        t0 = clock()
        call(k)
        out[j] = clock() - t0
    return out / 1e3


def run(ticks: int) -> tuple[dict[str, np.ndarray], dict[str, list[float]], dict[str, object]]:
    """Per-tick times (us) and block medians of each implementation, and what the tick state
    ended with."""
    cfg = load_config(config_file("motcomp.toml"))
    if cfg.loop.rate_hz != 1000.0:
        raise SystemExit(f"the example config runs at {cfg.loop.rate_hz:g} Hz, not 1 kHz")
    _, alone = new_tick(cfg)
    params, state = new_tick(cfg)
    comp = alone.comp
    lim = comp.limits
    refs = references(ticks, lim.p_min, lim.p_max)
    rows = refs.tolist()
    frames = input_frames(rows)
    vector = NumpyTick(new_tick(cfg)[1].comp)
    comp_step = comp.step
    calls: dict[str, Callable[[int], object]] = {
        "`Compensator.step`": lambda k: comp_step(rows[k]),
        "`tick.step` (frame in, `TickOutput` out)":
            lambda k: step(state, params, k * 1_000_000, frames[k]),
        "numpy sketch (lower bound)": lambda k: vector.step(refs[k]),
    }
    parts: dict[str, list[np.ndarray]] = {name: [] for name in calls}
    gc.collect()
    gc.freeze()
    try:
        for b in np.array_split(np.arange(ticks), BLOCKS):
            ks = range(int(b[0]), int(b[-1]) + 1)
            for name, call in calls.items():
                parts[name].append(measure(call, ks))
    finally:
        gc.unfreeze()
    times = {name: np.concatenate(p) for name, p in parts.items()}
    blocks = {name: [float(np.median(x)) for x in p] for name, p in parts.items()}
    check = {"accepted": state.accepted, "rejected": state.rejected, "ticks": state.ticks,
             "mode": state.mode, "u_max": float(np.max(np.abs(comp.output)))}
    return times, blocks, check


ROUNDS = 3
"""Rounds of ``--compare-plain``: each runs the installed tick, then the plain Python one."""


def percentiles(times: dict[str, np.ndarray]) -> dict[str, list[float]]:
    return {name: [float(x) for x in np.percentile(t, (50, 99, 99.9))]
            for name, t in times.items()}


def compare_plain(ticks: int) -> str:
    """Both ticks in child processes, alternately; the section's text."""
    figures: dict[str, list[dict[str, object]]] = {"installed": [], "plain": []}
    for _ in range(ROUNDS):
        for kind in figures:
            env = {k: v for k, v in os.environ.items() if k != native.PURE_ENV}
            if kind == "plain":
                env[native.PURE_ENV] = "1"
            p = subprocess.run([sys.executable, __file__, "--ticks", str(ticks), "--json"],
                               env=env, capture_output=True, text=True, check=True)
            figures[kind].append(json.loads(p.stdout))
    active = {kind: str(runs[0]["active"]) for kind, runs in figures.items()}
    names = list(figures["installed"][0]["percentiles"])  # type: ignore[call-overload]

    def med(kind: str, name: str, q: int) -> float:
        return float(np.median([r["percentiles"][name][q]  # type: ignore[index]
                                for r in figures[kind]]))

    lines = [
        f"Machine: {machine()}.",
        "",
        f"`python tools/bench_core.py --ticks {ticks} --compare-plain`: as below, in child "
        f"processes, {ROUNDS} rounds each alternately of the installed tick "
        f"({active['installed']}) and the plain Python one ({active['plain']}); the median "
        "over the rounds of each figure.",
        "",
        "| code | installed: median / p99 / p99.9 (us) | plain Python: median / p99 / p99.9 (us) "
        "| median ratio |",
        "|---|---|---|---|",
    ]
    for name in names:
        a = [med("installed", name, q) for q in range(3)]
        b = [med("plain", name, q) for q in range(3)]
        lines.append(f"| {name} | {a[0]:.1f} / {a[1]:.1f} / {a[2]:.1f} | "
                     f"{b[0]:.1f} / {b[1]:.1f} / {b[2]:.1f} | {b[0] / a[0]:.2f}x |")
    return "\n".join(lines)


GAPS_US = (0, 50, 150, 400, 1000, 3000)
"""Gaps between two calls of ``--gaps`` (us; 0: back to back)."""
GAP_ROUNDS = 3


def gaps(ticks: int) -> str:
    """``tick.step`` after each of :data:`GAPS_US`, ``ticks`` calls per gap in
    :data:`GAP_ROUNDS` interleaved rounds; the section's text."""
    cfg = load_config(config_file("motcomp.toml"))
    params, state = new_tick(cfg)
    lim = state.comp.limits
    per = max(ticks // GAP_ROUNDS, 1)
    warm = 2000
    total = warm + per * GAP_ROUNDS * len(GAPS_US)
    frames = input_frames(references(total, lim.p_min, lim.p_max).tolist())
    clock = time.perf_counter_ns
    times: dict[int, list[float]] = {g: [] for g in GAPS_US}
    gc.collect()
    gc.freeze()
    try:
        for k in range(warm):
            step(state, params, k * 1_000_000, frames[k])
        k = warm
        end = clock()
        for _ in range(GAP_ROUNDS):
            for gap in GAPS_US:
                for _ in range(per):
                    due = end + gap * 1000
                    while clock() < due:
                        pass
                    t0 = clock()
                    step(state, params, k * 1_000_000, frames[k])
                    end = clock()
                    times[gap].append((end - t0) / 1e3)
                    k += 1
    finally:
        gc.unfreeze()
    if state.accepted != total:
        raise SystemExit(f"the tick accepted {state.accepted} of {total} frames")
    q = {g: np.percentile(t, (50, 99)) for g, t in times.items()}
    lines = [
        f"Machine: {machine()}.",
        "",
        f"`python tools/bench_core.py --gaps --ticks {ticks}` (tick: {native.ACTIVE}): "
        f"`tick.step` on the example config's 8 axes, {per * GAP_ROUNDS} calls after each gap "
        f"in {GAP_ROUNDS} interleaved rounds; the gap spent spinning on the clock in the same "
        "thread (the CPU never idle, nothing else of this process running).",
        "",
        "| gap before the call | median (us) | p99 (us) | median / back to back |",
        "|---|---|---|---|",
    ]
    for g in GAPS_US:
        name = "back to back" if g == 0 else f"{g} us"
        lines.append(f"| {name} | {q[g][0]:.1f} | {q[g][1]:.1f} | {q[g][0] / q[0][0]:.2f}x |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ticks", type=int, default=60000, help="ticks per implementation")
    ap.add_argument("--quick", action="store_true", help="a smoke test: 6000 ticks")
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument("--compare-plain", action="store_true",
                    help="the installed tick against the plain Python one (child processes)")
    ap.add_argument("--gaps", action="store_true",
                    help="tick.step after gaps of 0-3 ms spent spinning (section core-gaps)")
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    ticks = 6000 if args.quick else args.ticks
    for asked, section, measure_section in ((args.gaps, "core-gaps", gaps),
                                            (args.compare_plain, "core-compiled", compare_plain)):
        if asked:
            text = measure_section(ticks)
            print(text)
            if not args.no_write:
                write_section(section, text)
            return
    times, blocks, check = run(ticks)
    if args.json:
        print(json.dumps({"active": native.ACTIVE, "percentiles": percentiles(times),
                          "check": check}))
        return
    med = {name: float(np.median(t)) for name, t in times.items()}
    names = list(times)
    lines = [
        f"Machine: {machine()}.",
        "",
        f"`python tools/bench_core.py --ticks {ticks}` (tick: {native.ACTIVE}): the example "
        "config's 8 axes at 1 kHz, "
        "sinusoidal references within half of each axis' range; each call timed with "
        "`perf_counter_ns` (which adds about 0.1 us), the three interleaved in "
        f"{BLOCKS} blocks of {ticks // BLOCKS} ticks, GC frozen as in the service's loop.  "
        "`tick.step` takes a valid msgpack input frame every tick (parse and check, reference, "
        "compensator, saturation verdicts; its output is not encoded).",
        "",
        "| code | median (us) | p99 (us) | p99.9 (us) | block medians (us) |",
        "|---|---|---|---|---|",
    ]
    for name, t in times.items():
        q = np.percentile(t, (50, 99, 99.9))
        lines.append(f"| {name} | {q[0]:.1f} | {q[1]:.1f} | {q[2]:.1f} | "
                     f"{min(blocks[name]):.1f}-{max(blocks[name]):.1f} |")
    lines += [
        "",
        f"The tick beyond the compensator (frame checks, reference, prediction, verdicts) costs "
        f"{med[names[1]] - med[names[0]]:.1f} us at the median; the tick accepted "
        f"{check['accepted']} of {check['ticks']} frames (rejected {check['rejected']}), mode "
        f"{check['mode']!r} at the end, largest |command| {check['u_max']:.3g}.  numpy sketch / "
        f"`Compensator.step` median ratio: {med[names[2]] / med[names[0]]:.2f} (the sketch does "
        "less work).  Target: `Compensator.step` median <= 20 us.",
    ]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        write_section("core", text)


if __name__ == "__main__":
    main()
