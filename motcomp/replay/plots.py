"""Figures of a replay (``motcomp replay --out DIR``): one PNG per moving driven axis.

Top: ten seconds around the most active part of the session -- the reference, the recorded
command, the replayed command(s), the simulated platform response to them and the recorded
feedback.  Bottom: over the whole session, the largest difference between the replayed and the
recorded command in each bin (log scale), or, without recorded outputs, the commands.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from motcomp.core.axes import AXES, unit
from motcomp.record.session import Session
from motcomp.replay.analysis import MIN_MOTION, SETTLE_S, held_commands
from motcomp.replay.offline import ReplayRun

__all__ = ["write_plots"]

ZOOM_S = 10.0


def write_plots(out_dir: Path, session: Session, runs: list[ReplayRun]) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from motcomp.sim.platform import simulate_axis

    out_dir.mkdir(parents=True, exist_ok=True)
    base = runs[0]
    plan, res = base.plan, base.result
    ref = held_commands(plan, res.ref)  # catch-up rows: the reference last sent
    t = plan.t_s
    rate = 1e9 / plan.period_ns
    paths = []
    rec = session.outputs
    rec_rows = np.flatnonzero(plan.output >= 0)
    for a, name in enumerate(AXES):
        if not base.axes.driven[a] or np.ptp(ref[:, a]) < MIN_MOTION:
            continue
        n_zoom = int(ZOOM_S * rate)
        if t.size > n_zoom:
            step = max(n_zoom // 4, 1)
            starts = np.arange(0, t.size - n_zoom, step)
            act = [np.ptp(ref[s:s + n_zoom, a]) for s in starts]
            s0 = int(starts[int(np.argmax(act))])
        else:
            s0 = 0
        z = slice(s0, min(s0 + n_zoom, t.size))
        fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(12, 7.5))
        ax1.plot(t[z], ref[z, a], "k", lw=1.2, label="reference")
        if rec is not None and rec_rows.size:
            rz = rec_rows[(rec_rows >= z.start) & (rec_rows < z.stop)]
            ax1.plot(t[rz], rec.pos[plan.output[rz], a], color="0.6", ls="--", lw=1,
                     label="recorded command")
        for i, run in enumerate(runs):
            cmd = held_commands(run.plan, run.result.u)[:, a]
            y = simulate_axis(run.axes.plants[a], cmd, rate)
            tt = run.plan.t_s
            zz = (tt >= t[z.start]) & (tt <= t[z.stop - 1])
            ax1.plot(tt[zz], cmd[zz], f"C{2 * i}", lw=1, label=f"command: {run.label}")
            ax1.plot(tt[zz], y[zz], f"C{2 * i + 1}", lw=1, label=f"platform model: {run.label}")
        fb = session.feedback
        wall = _wall_of_first_row(session, base)
        if fb is not None and len(fb) and wall is not None:
            t_fb = fb.t - wall
            sel = (t_fb >= t[z.start]) & (t_fb <= t[z.stop - 1]) & fb.valid
            ax1.plot(t_fb[sel], fb.pos[sel, a], "C4", lw=1, alpha=0.8, label="recorded feedback")
        ax1.set_title(f"{name}: {ZOOM_S:g} s of {session.name}")
        ax1.set_xlabel("time (s)")
        ax1.set_ylabel(unit(name))
        ax1.grid(True, alpha=0.3)
        ax1.legend(loc="best", fontsize=7)
        if rec is not None and rec_rows.size:
            d = np.abs(res.u[rec_rows, a] - rec.pos[plan.output[rec_rows], a])
            bins = max(1, rec_rows.size // 2000)
            m = d[: d.size // bins * bins].reshape(-1, bins).max(axis=1)
            tb = t[rec_rows][: d.size // bins * bins].reshape(-1, bins)[:, 0]
            ax2.semilogy(tb, np.maximum(m, 1e-18), "C0", lw=1)
            ax2.set_ylabel(f"max |replayed - recorded| ({unit(name)})\n(equal: drawn at 1e-18)")
            if plan.warm:  # the report leaves it out: the replay's state is settling there
                ax2.axvspan(float(t[0]), float(t[0]) + SETTLE_S, color="0.85",
                            label=f"warm start: not compared (the first {SETTLE_S:g} s)")
                ax2.legend(loc="upper right", fontsize=7)
        else:
            bins = max(1, t.size // 4000)
            ax2.plot(t[::bins], ref[::bins, a], "k", lw=1, label="reference")
            ax2.plot(t[::bins], held_commands(plan, res.u)[::bins, a], "C0", lw=1, label="command")
            ax2.legend(loc="upper right", fontsize=7)
            ax2.set_ylabel(unit(name))
        ax2.set_xlabel("time (s)")
        ax2.grid(True, alpha=0.3)
        fig.tight_layout()
        path = out_dir / f"replay_{name}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths


def _wall_of_first_row(session: Session, run: ReplayRun) -> float | None:
    """Wall time (s) of the plan's first row, from the recorded output it maps to."""
    rows = np.flatnonzero(run.plan.output >= 0)
    if session.outputs is None or not rows.size:
        return None
    r = int(rows[0])
    return float(session.outputs.t[run.plan.output[r]]) - float(run.plan.t_s[r])
