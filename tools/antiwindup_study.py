"""Why the compensator uses model-recovery anti-windup, not back-calculation.

Runs the rails compensator (Ziegler-Nichols, 1 kHz, rails limits 2.6 m / 2 m/s / 6 m/s^2) two ways
on two inputs and writes docs/ANTIWINDUP.md:

* back-calculation: the internal model is fed with the saturated command inside the PID loop and
  the integrator is corrected by ``kt (u - v)`` (the textbook scheme);
* model recovery (production, :class:`motcomp.core.compensator.Compensator`): the PID's loop sees
  ``M v``; the model fed with ``u`` is the platform mirror.

Usage: ``python tools/antiwindup_study.py``
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from motcomp.core.compensator import Compensator
from motcomp.core.models import p1d_coefficients, simulate_axis
from motcomp.core.saturation import AxisLimits, axis_constants, limit_axis
from motcomp.core.tuning import tune
from motcomp.design.timedomain import swept_sine
from motcomp.presets import load_preset

DOC = Path(__file__).resolve().parent.parent / "docs" / "ANTIWINDUP.md"


def back_calculation(r: np.ndarray, model, gains, limits: AxisLimits) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The rejected scheme, written out plainly for the comparison."""
    h = 1e-3
    phi, g0, g1, d = p1d_coefficients(model, h)
    const = axis_constants(limits, h)[0]
    kp, kih = gains.kp, gains.ki * h
    ad, bd = gains.tf / (gains.tf + h), gains.kd / (gains.tf + h)
    kt = min(h / gains.tracking_time_s(), 1.0)
    integ = deriv = w_prev = x = u = vel = sp = sv = sa = 0.0
    hist = [0.0] * (d + 2)
    out = np.empty(r.size)
    for k, rk in enumerate(r):
        y = x
        w = rk - y
        deriv = ad * deriv + bd * (w - w_prev)
        w_prev = w
        v = kp * w + integ + deriv
        u, vel, sp, sv, sa, _ = limit_axis(v, u, vel, sp, sv, sa, const)
        integ += kih * w + kt * (u - v)
        hist.append(u)
        hist.pop(0)
        x = phi * y + g0 * hist[-d] + g1 * hist[-1 - d]
        out[k] = u
    return out


def main() -> None:
    rails = load_preset("rails")
    model = rails.model
    lim = rails.axis_limits("rails_y")
    gains = tune("zn", model).gains
    _, sweep = swept_sine(1000.0, 0.1, 3.0, 60.0, 0.0135)
    inputs = {
        "0.5 m step": np.full(5000, 0.5),
        "0.1-3 Hz sweep, 13.5 mm, then 3 s at rest": np.concatenate([sweep, np.zeros(3000)]),
    }
    rows = []
    worst: dict[str, float] = {}
    for name, r in inputs.items():
        for scheme in ("back-calculation", "model recovery"):
            if scheme == "back-calculation":
                u = back_calculation(r, model, gains, lim)
            else:
                u = Compensator([model], [gains], lim, 1000.0).run(r[:, None])[0][:, 0]
            y = simulate_axis(model, u, 1000.0, initial=0.0)
            tail = u[-1000:]
            if scheme == "back-calculation":
                worst["p2p"] = max(worst.get("p2p", 0.0), float(np.ptp(tail)))
                if name.endswith("step"):
                    worst["overshoot"] = (float(np.max(u)) / 0.5 - 1.0) * 100
            rows.append(f"| {name} | {scheme} | {np.max(np.abs(u)):.3f} | "
                        f"{np.ptp(tail):.2e} | {abs(y[-1] - r[-1]):.2e} |")
    text = "\n".join([
        "# Anti-windup: model recovery vs back-calculation",
        "",
        "The paper's compensator closes a PID around an internal model of the platform. With the",
        "actuator limits inside that loop (the model fed with the *saturated* command) and a",
        "high-gain tuning such as Ziegler-Nichols (Ms ~ 4.8, loop crossover ~ 20 Hz, 17.5 ms model",
        "delay), an acceleration limit behaves like a relay with delay: the loop falls into a",
        "limit cycle that outlives the input. Back-calculation only protects the integrator and",
        "does not prevent it. Model-recovery anti-windup (Zaccarian & Teel 2011; the IMC",
        "anti-windup of Zheng, Kothare & Morari 1994 for a stable plant) feeds the PID",
        "`M u + M (v - u) = M v`: its loop stays linear and stable whatever the limits do, the",
        "model driven by `u` still mirrors the platform, and a deficit left by saturation fades",
        "with the platform's own time constant.",
        "",
        "`python tools/antiwindup_study.py` (rails preset, ZN, 1 kHz,",
        "limits 2.6 m, 2 m/s, 6 m/s^2):",
        "",
        "| input | scheme | max command (m) | command peak-to-peak over the last 1 s (m) |"
        " final platform error (m) |",
        "|---|---|---|---|---|",
        *rows,
        "",
        "A settled compensator has a last-second peak-to-peak of ~0; with back-calculation the",
        f"command still swings by up to {worst['p2p']:.2f} m, at the acceleration limit, seconds",
        f"after the input has stopped, and the step overshoots by {worst['overshoot']:.0f} %.",
    ])
    DOC.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
