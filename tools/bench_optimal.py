"""Benchmark of the optimised tuning: writes the "optimal" section of docs/BENCHMARKS.md and the
Pareto figure docs/optimal_pareto_rails.png.

    python tools/bench_optimal.py [--repeats N] [--baseline DIR]

Everything is recomputed: rails nominal and robust designs against the rules, the Pareto
frontier, the <= 6 dB experiment, the command-bound trade-off, the uncertainty-set table, the
time-domain runs with saturation, the hexapod, and the time ``motcomp design`` takes for the
example config's designs (``--repeats`` runs each, medians of CPU and wall time; with
``--baseline DIR``, another checkout's ``motcomp`` -- the code before a change -- runs each
command too, interleaved with this one's, so that both see the same load).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _bench import DOC, machine, write_section

from motcomp.core.models import ProcessModel
from motcomp.core.pid import PIDGains
from motcomp.core.tuning import RULE_NAMES, RULES, tune
from motcomp.design.frequency import evaluate
from motcomp.design.optimal import (
    Constraints,
    Uncertainty,
    command_excess_db,
    member_table,
    optimise,
)
from motcomp.design.pareto import pareto, pareto_figure, pareto_markdown
from motcomp.design.timedomain import simulate_compensated, slalom, swept_sine
from motcomp.presets import load_preset

RAILS = load_preset("rails")
HEXAPOD = load_preset("hexapod")
FIGURE = DOC.parent / "optimal_pareto_rails.png"


def timed(label: str, fn, *args, **kwargs):  # type: ignore[no-untyped-def]
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    dt = time.perf_counter() - t0
    print(f"{label}: {dt:.1f} s", flush=True)
    return out, dt


def row(name: str, g: PIDGains, plant: ProcessModel, rate: float = 1000.0,
        extra: str = "") -> str:
    m = plant.to_p1d()
    ev = evaluate(g, m, plant, rate_hz=rate)
    ex = command_excess_db(g, m, rate, (0.1, 2.0))
    return (f"| {name} | {ev.max_residual_delay_ms:.2f} | {ev.peak_gain_db:+.2f} at "
            f"{ev.peak_gain_hz:.1f} Hz | {ev.gain_error_db:.2f} | {ex:+.2f} | "
            f"{ev.peak_command_gain:.0f} | {ev.ms:.2f} |{extra}")


HEAD = ("| design | max residual delay 0.1-2 Hz (ms) | peak gain (dB) | in-band gain error (dB) | "
        "command over inverse (dB) | max abs(F) | Ms |")


ROOT = Path(__file__).resolve().parent.parent
DESIGNS = (
    ("rails, default bounds", ("design", "--plant", "rails", "--rule", "optimal")),
    ("rails, the example config's chain",
     ("design", "--plant", "rails", "--rule", "optimal", "--input-lag-ms", "2.8", "--prediction",
      "on", "--band", "0.03", "2", "--chain-hf-gain", "20")),
    ("hexapod, the example config's prefilter",
     ("design", "--plant", "hexapod", "--axis", "hex_x", "--rule", "optimal", "--peak-db", "6",
      "--hf-gain", "7", "--step-rise-s", "0.4", "--prediction-order", "40",
      "--prediction-pole-hz", "1", "--input-lag-ms", "2.8", "--input-band-hz", "64")),
)
"""The commands timed (``motcomp ... --json --quiet``): config/motcomp.toml's designs."""


def run_design(tree: Path, args: tuple[str, ...]) -> tuple[float, float]:
    """Wall and CPU seconds of one ``motcomp`` run from checkout ``tree``."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "motcomp", *args, "--json", "--quiet"], cwd=tree,
                       env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"{tree}: motcomp {' '.join(args)} failed: {p.stderr.strip()}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def design_times(repeats: int, baseline: Path | None, label: str) -> list[str]:
    """The design-time table: medians over ``repeats`` runs (interleaved with ``baseline``)."""
    trees = [("this checkout", ROOT)] + ([(label, baseline)] if baseline else [])
    lines = ["### Design time", "",
             f"`motcomp design ... --json --quiet`, {repeats} runs of each; medians (CPU: user "
             "+ system of the process, which the host's load changes little; wall: what the "
             "user waits, which it changes a lot)"
             + (f"; {label} interleaved with this checkout's runs" if baseline else "") + ".",
             "",
             "| design | " + " | ".join(f"{name}: CPU, wall (s)" for name, _ in trees)
             + " | load average |", "|---|" + "---|" * len(trees) + "---|"]
    for label, args in DESIGNS:
        runs: dict[str, list[tuple[float, float]]] = {name: [] for name, _ in trees}
        loads = []
        for _ in range(repeats):
            for name, tree in trees:
                loads.append(os.getloadavg()[0])
                runs[name].append(run_design(tree, args))
                print(f"{label}, {name}: wall {runs[name][-1][0]:.1f} s, CPU "
                      f"{runs[name][-1][1]:.1f} s", flush=True)
        cells = [f"{statistics.median(c for _, c in runs[name]):.1f}, "
                 f"{statistics.median(w for w, _ in runs[name]):.1f}" for name, _ in trees]
        lines.append(f"| {label} | " + " | ".join(cells)
                     + f" | {min(loads):.1f}-{max(loads):.1f} |")
    return [*lines, ""]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3, help="runs of each timed design")
    ap.add_argument("--baseline", type=Path, help="another checkout to time beside this one")
    ap.add_argument("--baseline-label", default="baseline", help="its name in the table")
    args = ap.parse_args()
    rails = RAILS.model
    lines: list[str] = [f"Machine: {machine()}.", "",
                        "`python tools/bench_optimal.py`; all designs at 1 kHz unless stated, "
                        "evaluated with `design.frequency.evaluate` (dense grid, discrete loop, "
                        "poles). Default bounds: peak <= 8 dB, in-band gain error <= 1 dB, "
                        "command <= +0.5 dB over the exact inverse in band, max|F| <= 60, "
                        "Ms <= 4 (docs/TUNING.md).", ""]

    # --- rails nominal ----------------------------------------------------------------------
    optimise(rails)  # once untimed: the first call imports SciPy's optimiser
    nominal, t_nom = timed("rails nominal", optimise, rails)
    plain, t_plain = timed("rails plain", optimise, rails, setpoint_weights=False)
    loose = Constraints(command_excess_db=1.0)
    plain_loose, _ = timed("rails plain, loose", optimise, rails, constraints=loose,
                           setpoint_weights=False)
    lines += ["### Rails, nominal model", "", HEAD + " time (s) |",
              "|---|---|---|---|---|---|---|---|"]
    lines.append(row("optimal (b, c)", nominal.gains, rails, extra=f" {t_nom:.1f} |"))
    lines.append(row("optimal, plain PID", plain.gains, rails, extra=f" {t_plain:.1f} |"))
    lines.append(row("optimal, plain PID, command bound only +1 dB", plain_loose.gains, rails,
                     extra=" |"))
    for rule in RULES:
        lines.append(row(RULE_NAMES[rule], tune(rule, rails).gains, rails, extra=" - |"))
    g = nominal.gains
    lines += ["", f"Optimal gains: kp = {g.kp:.4g}, ki = {g.ki:.4g} 1/s, kd = {g.kd:.4g} s, "
                  f"tf = {g.tf:.4g} s, b = {g.b:.4g}, c = {g.c:.4g}.", ""]

    # --- Pareto ------------------------------------------------------------------------------
    par, t_par = timed("pareto", pareto, rails, None, 1000.0, (1.0, 3.0, 6.0, 8.0, 10.0))
    pareto_figure(par, FIGURE)
    table = pareto_markdown(par).split("\n", 2)[2]
    lines += ["### Pareto frontier (rails, 1 kHz)", "",
              f"`motcomp pareto --plant rails --input-band-hz 0 --out DIR` ({t_par:.0f} s; "
              f"without the input's band limit); figure: "
              f"[{FIGURE.name}]({FIGURE.name}).", "", table.strip(), ""]

    # --- the <= 6 dB experiment ---------------------------------------------------------------
    lines += ["### Peak <= 6 dB: which extra degree of freedom", "", HEAD,
              "|---|---|---|---|---|---|---|"]
    six = Constraints(peak_db=6.0)
    six_loose = Constraints(peak_db=6.0, command_excess_db=1.0)
    for label, kwargs in (
            ("plain PID, 1 kHz", {"constraints": six, "setpoint_weights": False}),
            ("plain PID, 1 kHz, command bound only +1 dB",
             {"constraints": six_loose, "setpoint_weights": False}),
            ("plain PID, 2 kHz", {"constraints": six, "setpoint_weights": False,
                                  "rate_hz": 2000.0}),
            ("plain PID, 2 kHz, command bound only +1 dB",
             {"constraints": six_loose, "setpoint_weights": False, "rate_hz": 2000.0}),
            ("setpoint weights b, c, 1 kHz", {"constraints": six}),
            ("setpoint weights b, c, 2 kHz", {"constraints": six, "rate_hz": 2000.0})):
        d, _ = timed(f"6 dB {label}", optimise, rails, **kwargs)
        lines.append(row(label, d.gains, rails, rate=float(kwargs.get("rate_hz", 1000.0))))
    lines.append("")

    # --- command bounds ----------------------------------------------------------------------
    lines += ["### Command bounds: residual delay (ms) at peak <= 8 dB", "",
              "| max abs(F) | command over inverse | nominal design | robust design (worst "
              "excess over the floor) | 0.1-3 Hz sweep, saturated samples (ZN: see below) |",
              "|---|---|---|---|---|"]
    for gain in (30.0, 60.0, 130.0):
        for excess in (0.5, 1.0):
            c = Constraints(max_command_gain=gain, command_excess_db=excess)
            dn, _ = timed(f"bounds {gain} {excess}", optimise, rails, constraints=c)
            dr, _ = timed(f"bounds {gain} {excess} robust", optimise, rails, constraints=c,
                          uncertainty=Uncertainty())
            sat = sweep(dn.gains, 3.0)[0]
            worst = max(m.excess_ms for m in dr.members)
            lines.append(f"| {gain:g} | {excess:+g} dB | "
                         f"{dn.evaluation.max_residual_delay_ms:.2f} | {worst:.2f} | {sat} |")
    lines.append("")

    # --- robust ------------------------------------------------------------------------------
    robust, t_rob = timed("rails robust", optimise, rails, uncertainty=Uncertainty())
    members = Uncertainty().members(rails)
    nominal_on_set = member_table(nominal.gains, rails, members, 1000.0, (0.1, 2.0))
    lines += ["### Rails over the uncertainty set (K +-10 %, Td +-5 ms, Tp1 +-20 %)", "",
              f"Robust design ({t_rob:.1f} s): kp = {robust.gains.kp:.4g}, ki = "
              f"{robust.gains.ki:.4g}, kd = {robust.gains.kd:.4g}, tf = {robust.gains.tf:.4g}, "
              f"b = {robust.gains.b:.4g}, c = {robust.gains.c:.4g}; nominal residual "
              f"{robust.evaluation.max_residual_delay_ms:.2f} ms at "
              f"{robust.evaluation.peak_gain_db:+.2f} dB.", "",
              "Floor: the largest phase delay of P/M over the band, what an exact inverse of the "
              "internal model would leave; no feedforward compensator removes it.", "",
              "| member | floor (ms) | robust: residual (ms) | robust: excess (ms) | robust: peak "
              "(dB) | nominal design: peak (dB) | ZN: residual (ms) | ZN: peak (dB) |",
              "|---|---|---|---|---|---|---|---|"]
    for m, mn in zip(robust.members, nominal_on_set, strict=True):
        lines.append(f"| {m.label} | {m.floor_ms:.1f} | {m.residual_ms:.1f} | "
                     f"{m.excess_ms:+.2f} | {m.peak_gain_db:+.2f} | {mn.peak_gain_db:+.2f} | "
                     f"{m.zn_residual_ms:.1f} | {m.zn_peak_gain_db:+.2f} |")
    lines += ["", f"Worst member: robust peak {max(m.peak_gain_db for m in robust.members):+.2f}"
                  f" dB (nominal design {max(m.peak_gain_db for m in nominal_on_set):+.2f} dB, ZN "
                  f"{max(m.zn_peak_gain_db or 0 for m in robust.members):+.2f} dB); robust excess "
                  f"over the floor at most {max(m.excess_ms for m in robust.members):.2f} ms.", ""]

    # --- time domain -------------------------------------------------------------------------
    lines += ["### Time domain with saturation (rails_y limits: 2.6 m, 2 m/s, 6 m/s^2)", "",
              "Overload sweeps: amplitude at 80 % of the limits for the *plain* sweep at its top "
              "frequency (what `motcomp evaluate` uses): every compensator must exceed the "
              "acceleration limit there. Compensable sweeps: the same scaled by |M(f1)|, so "
              "that an exact inverse would stay at 80 %.", "",
              "| design | slalom: delay off -> on (ms), reduction | 0.1-3 Hz overload: delay, "
              "saturated samples | 0.1-2 Hz overload | 0.1-3 Hz compensable | 0.1-2 Hz "
              "compensable |", "|---|---|---|---|---|---|"]
    for label, g in (("ZN", tune("zn", rails).gains), ("optimal", nominal.gains),
                     ("optimal, robust", robust.gains)):
        _, r = slalom(1000.0)
        s = simulate_compensated(r, g, rails, None, RAILS.axis_limits("rails_y"), 1000.0)
        cells = [f"{s.delay_off_s * 1e3:.1f} -> {s.delay_on_s * 1e3:.1f}, "
                 f"{s.reduction_s * 1e3:.1f} (sat. {s.saturated_samples_on})"]
        for scale in (False, True):
            for f1 in (3.0, 2.0):
                n, d = sweep(g, f1, scale)
                cells.append(f"{d * 1e3:.1f} ms, {n}")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("")

    # --- hexapod -----------------------------------------------------------------------------
    hx = HEXAPOD.model
    hm = hx.to_p1d()
    lines += ["### Hexapod (P2UZD platform, internal P1D: Tp1/Td = "
              f"{hm.Tp1 / hm.Td:.3f})", "", HEAD + " recommendation |",
              "|---|---|---|---|---|---|---|---|"]
    for rule in RULES:
        lines.append(row(RULE_NAMES[rule], tune(rule, hm).gains, hx, extra=" - |"))
    hex_design, _ = timed("hexapod 8 dB", optimise, hx)
    hex_3db, _ = timed("hexapod 3 dB", optimise, hx, constraints=Constraints(peak_db=3.0))
    hex_robust, _ = timed("hexapod robust", optimise, hx, uncertainty=Uncertainty())
    for label, d in (("optimal, peak <= 8 dB", hex_design), ("optimal, peak <= 3 dB", hex_3db),
                     ("optimal, robust", hex_robust)):
        verdict = "bypass" if d.recommend_bypass else "compensate"
        lines.append(row(label, d.gains, hx, extra=f" {verdict} |"))
    ev = hex_design.evaluation
    lines += ["", f"Uncompensated: {ev.uncorrected_max_delay_ms:.1f} ms max over 0.1-2 Hz "
                  f"({ev.uncorrected_phase_delay_ms['0.2']:.1f} ms at 0.2 Hz), in-band gain error "
                  f"{ev.uncorrected_gain_error_db:.2f} dB.", "",
              "Report of `motcomp design --plant hexapod --rule optimal`:", "",
              *[f"> {w}" for w in hex_design.warnings], ""]
    lines += design_times(args.repeats, args.baseline, args.baseline_label)
    write_section("optimal", "\n".join(lines))
    print(f"wrote the optimal section of {DOC} and {FIGURE}")
    return 0


def sweep(g: PIDGains, f1: float, compensable: bool = False) -> tuple[int, float]:
    """Saturated samples and delay of the compensated rails on a 0.1-f1 Hz sweep."""
    lim = RAILS.axis_limits("rails_y")
    amp = 0.8 * min(2.6, 2.0 / (2 * np.pi * f1), 6.0 / (2 * np.pi * f1) ** 2)
    if compensable:
        amp *= float(np.abs(RAILS.model.freqresp(f1))[0])
    _, r = swept_sine(1000.0, 0.1, f1, 60.0, amp)
    res = simulate_compensated(r, g, RAILS.model.to_p1d(), None, lim, 1000.0)
    return res.saturated_samples_on, res.delay_on_s


if __name__ == "__main__":
    sys.exit(main())
