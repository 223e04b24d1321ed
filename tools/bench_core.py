"""Benchmark: compensator tick time for 8 axes: the compiled kernel (production), its Python
reference (the same per-axis scalar code, bit-identical results) and a numpy-vectorised
formulation of the same tick, measured in the same run.

Writes the "core" section of docs/BENCHMARKS.md.  Usage: ``python tools/bench_core.py [--ticks N]``
"""

from __future__ import annotations

import argparse
import gc
import math
import time

import numpy as np
from _bench import machine, percentiles, write_section

from motcomp.core.compensator import Compensator
from motcomp.core.models import p1d_coefficients
from motcomp.core.saturation import AxisLimits
from motcomp.core.tuning import tune
from motcomp.presets import load_preset


class NumpyTick:
    """The same linear tick vectorised over axes with numpy (no bypass, no catch-up braking:
    a lower bound on what a numpy kernel costs)."""

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
        self.L = 64
        self.base = np.arange(n) * self.L
        self.off0, self.off1 = 1 - d, -d
        self.hist_c = np.zeros(n * self.L)
        self.hist_m = np.zeros(n * self.L)
        self.xc = np.zeros(n)
        self.xm = np.zeros(n)
        self.integ = np.zeros(n)
        self.deriv = np.zeros(n)
        self.wp = np.zeros(n)
        self.u = np.zeros(n)
        self.v = np.zeros(n)
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


def build(kernel: str = "c") -> Compensator:
    rails = load_preset("rails")
    hexapod = load_preset("hexapod")
    models = [rails.model] * 2 + [hexapod.model.to_p1d()] * 6
    gains = [tune("zn", rails.model).gains] * 2 + [tune("amigo", hexapod.model.to_p1d()).gains] * 6
    lim = AxisLimits(np.concatenate([rails.limits.p_min, hexapod.limits.p_min]),
                     np.concatenate([rails.limits.p_max, hexapod.limits.p_max]),
                     np.concatenate([rails.limits.v_max, hexapod.limits.v_max]),
                     np.concatenate([rails.limits.a_max, hexapod.limits.a_max]))
    return Compensator(models, gains, lim, 1000.0, kernel=kernel)  # type: ignore[arg-type]


def measure(step, refs: np.ndarray, as_list: bool) -> np.ndarray:  # type: ignore[no-untyped-def]
    times = np.empty(refs.shape[0])
    clock = time.perf_counter_ns
    rows = refs.tolist() if as_list else refs
    gc.collect()
    gc.disable()
    try:
        for i in range(refs.shape[0]):
            r = rows[i]
            t0 = clock()
            step(r)
            times[i] = clock() - t0
    finally:
        gc.enable()
    return times / 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--ticks", type=int, default=60000)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    t = np.arange(args.ticks) / 1000.0
    refs = np.stack([0.3 * (1 + i % 3) / 3 * np.sin(2 * math.pi * 0.3 * t + i)
                     for i in range(8)], axis=1)
    refs[:, 2:] *= 0.2
    results = {}
    # interleave the kernels in blocks so all see the same machine conditions
    compiled, python, vector = build("c"), build("python"), NumpyTick(build())
    blocks = 6
    names = ("compiled C (production)", "Python reference", "numpy-vectorised")
    parts: dict[str, list[np.ndarray]] = {name: [] for name in names}
    for b in np.array_split(np.arange(args.ticks), blocks):
        parts[names[0]].append(measure(compiled.step, refs[b], as_list=True))
        parts[names[1]].append(measure(python.step, refs[b], as_list=True))
        parts[names[2]].append(measure(vector.step, refs[b], as_list=False))
    same = compiled.output.tolist() == python.output.tolist()
    for name, chunks in parts.items():
        results[name] = percentiles(np.concatenate(chunks), (50, 99, 99.9))
    ratio = results[names[1]][50] / results[names[0]][50]
    ratio_np = results[names[2]][50] / results[names[1]][50]
    lines = [
        f"Machine: {machine()}.",
        "",
        f"`python tools/bench_core.py --ticks {args.ticks}`: one `Compensator.step` for the 8 axes "
        "(rails ZN + hexapod AMIGO, 1 kHz, sinusoidal references within the limits), timed with "
        "`perf_counter_ns` around each call (which adds about 0.1 us), GC disabled during the "
        "runs, the three kernels interleaved in 6 blocks.",
        "",
        "| kernel | median (us) | p99 (us) | p99.9 (us) |",
        "|---|---|---|---|",
    ]
    for name, q in results.items():
        lines.append(f"| {name} | {q[50]:.1f} | {q[99]:.1f} | {q[99.9]:.1f} |")
    lines += ["", f"Python / compiled median ratio in this run: {ratio:.1f}; the two ended on "
              f"{'bit-identical' if same else 'DIFFERENT'} commands.  numpy / Python median "
              f"ratio: {ratio_np:.2f} (the numpy variant does less work: no bypass, no catch-up "
              "braking).  Target: median <= 20 us."]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        write_section("core", text)


if __name__ == "__main__":
    main()
