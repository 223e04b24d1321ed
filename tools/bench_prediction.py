"""Benchmark: the predictive prefilter in time, through the config's tick, offline.

Each signal is fed perfectly timed to the config's tick (:func:`motcomp.sim.ideal.ideal_run`,
what the service runs) twice -- compensation as configured, and with every axis' prediction off
(``predict = false``; the PID as configured) -- and the command is run through the axis' true
platform model (``motcomp.core.models.simulate_axis`` with the config's ``model``, the hil's
dynamics).  Per run, on the axis the signal moves:

* delay: the delivered motion behind the signal (cross-correlation; for the lane change and
  the steps, of the velocities);
* overshoot: how far the delivered motion goes beyond the signal's own range, in % of that
  range (a step's size), and the part prediction adds to the run without it;
* HF acc: the command's acceleration RMS above 5 Hz; limited: share of ticks the limiter acted;
* fallbacks: how often the band monitor fell back.

Signals: the slalom (rails_y), the band sweep (rails_x), the lane change (rails_y; and a
10 cm sway on hex_y), heave / roll / pitch sines and a 0.1-2 Hz sweep on the hexapod, and
braking steps (minimum-jerk, rise 0-0.6 s, 2 mm-0.1 m) on hex_x and rails_x, and sudden reversals
(0.5 s at 0.02-0.3 m/s, then back) on hex_x.  Writes
docs/BENCHMARKS.md's "prediction-time" section (not with ``--no-write``) and
``prediction_time.json`` into ``--out``.

Usage: ``python tools/bench_prediction.py [--config config/motcomp.toml] [--out DIR]
[--no-write] [--section NAME]``
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _bench import machine, write_section

from motcomp.config import ServiceConfig, load_config, resolve_axes
from motcomp.core.axes import AXIS_INDEX
from motcomp.core.minjerk import min_jerk
from motcomp.core.models import simulate_axis
from motcomp.core.quality import command_quality, estimate_delay
from motcomp.errors import ConfigError
from motcomp.sim.ideal import ideal_run
from motcomp.sim.source import band_sweep, builtin, lane_change

RATE_HZ = 1000.0
STEPS = ((0.1, 0.0), (0.1, 0.3), (0.02, 0.0), (0.02, 0.15), (0.02, 0.3), (0.002, 0.0),
         (0.002, 0.3), (0.05, 0.6))
"""Braking steps on hex_x: (size, rise time); on rails_x ten times the size."""


def _step(size: float, rise_s: float, rest_s: float = 2.0, hold_s: float = 3.0) -> np.ndarray:
    n0, n1 = int(rest_s * RATE_HZ), max(int(rise_s * RATE_HZ), 1)
    x = np.arange(n1) / n1
    return np.concatenate([np.zeros(n0), size * min_jerk(x),
                           np.full(int(hold_s * RATE_HZ), size)])


def signals() -> list[tuple[str, str, np.ndarray, bool]]:
    """(name, axis, samples at 1 kHz, judge the delay on velocities).  The hexapod's sines
    and sweep start and end in 2 s minimum-jerk fades, as a motion source's would (a sine
    that starts with its full speed is a velocity step: the limiter's, not the predictor's)."""
    t = np.arange(int(24 * RATE_HZ)) / RATE_HZ
    fade = np.clip(np.minimum(t, t[-1] - t) / 2.0, 0.0, 1.0)
    env = min_jerk(fade)
    out = [("slalom", "rails_y", builtin("slalom", RATE_HZ).pos["rails_y"], False),
           ("bandsweep", "rails_x", band_sweep(RATE_HZ), False),
           ("lanechange", "rails_y", lane_change(RATE_HZ), True),
           ("heave 0.5 Hz", "hex_z", 0.05 * env * np.sin(2 * np.pi * 0.5 * t), False),
           ("roll 0.25 Hz", "hex_roll", 0.1 * env * np.sin(2 * np.pi * 0.25 * t), False),
           ("pitch 0.35 Hz", "hex_pitch", 0.08 * env * np.sin(2 * np.pi * 0.35 * t), False),
           ("sweep 0.1-2 Hz", "hex_y",
            0.02 * env * np.sin(2 * np.pi * (0.1 * t + 1.9 / 48 * t * t)), False)]
    n = 2000  # a 10 cm sway in 2 s and back (the lane change, as the hexapod's cue)
    move = 0.1 * min_jerk(np.arange(n) / n)
    out.append(("lane change 10 cm", "hex_y", np.concatenate(
        [np.zeros(1000), move, np.full(2000, 0.1), move[::-1], np.zeros(1500)]), True))
    for size, rise in STEPS:
        out.append((f"step {size * 1e3:g} mm, rise {rise:g} s", "hex_x", _step(size, rise), True))
    for speed in (0.02, 0.1, 0.3):  # sudden reversals: 0.5 s at speed, then back at once
        up = speed * np.arange(500) / RATE_HZ
        out.append((f"reversal at {speed:g} m/s", "hex_x", np.concatenate(
            [np.zeros(1000), up, up[-1] - speed * np.arange(1, 501) / RATE_HZ,
             np.zeros(2000)]), True))
    for size, rise in ((0.5, 0.0), (0.5, 0.5), (0.1, 0.3)):
        out.append((f"step {size * 1e3:g} mm, rise {rise:g} s", "rails_x", _step(size, rise),
                    True))
    return out


def _without_prediction(cfg: ServiceConfig) -> ServiceConfig:
    axes = {a: ax.model_copy(update={"predict": False}) for a, ax in cfg.axes.items()}
    return cfg.model_copy(update={"axes": axes})


def run(cfg: ServiceConfig, axis: str, r: np.ndarray, on_velocity: bool) -> dict[str, float]:
    plants = resolve_axes(cfg).plants
    res = ideal_run(cfg, {axis: r}, RATE_HZ)
    u = res.u[axis]
    y = simulate_axis(plants[AXIS_INDEX[axis]], u, RATE_HZ)
    n = min(y.size, r.size)
    ref, y = r[:n], y[:n]
    a, b = (np.diff(ref), np.diff(y)) if on_velocity else (ref, y)
    try:
        delay = estimate_delay(a, b, RATE_HZ, max_lag_s=0.3, min_lag_s=-0.1)
    except ConfigError:  # no peak within the lags (a limiter-bound step): not a delay
        delay = math.nan
    span = float(np.ptp(ref))
    over = max(float(y.max() - ref.max()), float(ref.min() - y.min()), 0.0)
    q = command_quality(u, RATE_HZ)
    return {"delay_ms": delay * 1e3, "overshoot_pct": 100 * over / span if span else 0.0,
            "hf_acc_rms": q.hf_acc_rms, "limited_pct": 100 * float(res.acted[axis].mean())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="config/motcomp.toml")
    ap.add_argument("--out", default="out/bench")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--section", default="prediction-time",
                    help="the BENCHMARKS.md section written (default prediction-time)")
    args = ap.parse_args()
    cfg = load_config(args.config)
    plain = _without_prediction(cfg)
    predicted = [a for a, p in zip(resolve_axes(cfg).names, resolve_axes(cfg).prediction,
                                   strict=True) if p is not None]
    t0 = time.time()
    rows = []
    for name, axis, r, vel in signals():
        on = run(cfg, axis, r, vel)
        off = run(plain, axis, r, vel)
        rows.append({"signal": name, "axis": axis, "predicted": axis in predicted,
                     "with": on, "without": off})
        print(f"{name:<26} {axis:<10} delay {off['delay_ms']:6.1f} -> {on['delay_ms']:6.1f} ms"
              f"  overshoot {off['overshoot_pct']:5.1f} -> {on['overshoot_pct']:5.1f} %"
              f"  HF acc {off['hf_acc_rms']:.3g} -> {on['hf_acc_rms']:.3g}"
              f"  limited {off['limited_pct']:.2f} -> {on['limited_pct']:.2f} %", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    info = {"machine": machine(), "config": args.config, "seconds": time.time() - t0,
            "predicted_axes": predicted, "rows": rows}
    (out / "prediction_time.json").write_text(json.dumps(info, indent=1))
    lines = [f"Config `{args.config}` (predicted axes: {', '.join(predicted) or 'none'}); "
             f"{info['machine']}; {info['seconds']:.0f} s.", "",
             "| signal | axis | delay without -> with (ms) | overshoot without -> with (% of "
             "range) | added by prediction (points) | HF acc without -> with | limited "
             "without -> with (%) |", "|---|---|---|---|---|---|---|"]
    for row in rows:
        w, o = row["with"], row["without"]
        lines.append(f"| {row['signal']} | {row['axis']} | {o['delay_ms']:.1f} -> "
                     f"{w['delay_ms']:.1f} | {o['overshoot_pct']:.1f} -> {w['overshoot_pct']:.1f}"
                     f" | {w['overshoot_pct'] - o['overshoot_pct']:+.1f} | "
                     f"{o['hf_acc_rms']:.3g} -> {w['hf_acc_rms']:.3g} | "
                     f"{o['limited_pct']:.2f} -> {w['limited_pct']:.2f} |")
    text = "\n".join(lines)
    (out / "prediction_time.md").write_text(text + "\n")
    if not args.no_write:
        write_section(args.section, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
