"""Synthetic sessions on virtual time, through the service's own tick, written as recordings.

For tests and benchmarks: a motion source publishing at its own (slightly drifting) clock, a
transport with random transit times, the tick (:func:`motcomp.core.tick.step`, what the service
runs) on its deadline grid with stalls (catch-up), bypass switches, silent gaps (stale input),
partial frames, bad frames and parking, and a recorder that receives every frame shortly after
it was sent (and may start late or lose outputs).  The platform's feedback is simulated with
:func:`~motcomp.sim.platform.simulate_axis` from the config's plant models.  Everything is a
function of the seed.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np

from motcomp.config import ServiceConfig, config_hash, new_tick, resolve_axes
from motcomp.core.axes import AXES, AXIS_INDEX
from motcomp.core.fpmode import subnormals_flushed
from motcomp.core.tick import is_parked, park, set_bypass, step
from motcomp.io.wire import encode_feedback, encode_input, encode_output
from motcomp.record.recorder import SessionWriter
from motcomp.record.session import DEFAULT_KEYS

__all__ = ["SynthOptions", "motion", "synthesize"]

WALL0 = 1_750_000_000.0
MONO0_NS = 123_456_789_012_345


@dataclass
class SynthOptions:
    duration_s: float = 10.0
    source_hz: float = 1000.0
    seed: int = 0
    transit_us: tuple[float, float] = (60.0, 400.0)
    """Uniform range of the source -> service transit time."""
    drift: float = 2e-5
    """The source's clock runs this much fast."""
    axes: tuple[str, ...] = AXES
    amplitude: float = 1.0
    stalls: list[tuple[float, int]] = field(default_factory=list)
    """``(time_s, periods)``: the loop overruns by that many periods."""
    gaps: list[tuple[float, float]] = field(default_factory=list)
    """``(start_s, length_s)``: the source is silent."""
    restart_after_gaps: bool = False
    """After each gap the sender starts its ``seq`` over at 0 (a restarted sender)."""
    bypass: list[tuple[float, bool, tuple[str, ...]]] = field(default_factory=list)
    """``(time_s, on, axes)``: an admin bypass request."""
    steps: list[tuple[float, str, float]] = field(default_factory=list)
    """``(time_s, axis, metres)``: a step added to the motion (makes the limiter act)."""
    partial_every: int = 0
    """Every n-th frame carries only the rails (0: never)."""
    bad_every: int = 0
    """Every n-th frame is followed by a bad frame (0: never)."""
    no_t_every: int = 0
    """Every n-th frame has no ``t`` (0: never)."""
    record_from_s: float = 0.0
    """The recorder starts this late (a warm start for the replay)."""
    lose_outputs: list[tuple[float, int]] = field(default_factory=list)
    """``(time_s, count)``: outputs the recorder did not receive."""
    park_at_s: float | None = None
    status: bool = True
    clock_in_status: bool = True
    feedback: bool = True
    excite: list[tuple[str, str, float, float]] = field(default_factory=list)
    """``(axis, kind, start_s, length_s)``: the axis plays an identification excitation
    (:func:`motcomp.ident.excitation.excitation`, ``noise``, ``sweep`` or ``multisine``, seeded,
    within 80 % of the config's limits of the axis, neutral at both ends) instead of
    :func:`motion`."""
    feedback_gaps: list[tuple[float, float]] = field(default_factory=list)
    """``(start_s, length_s)``: the platform sends no feedback."""
    service_misses: list[float] = field(default_factory=list)
    """Source instants (s): the first sample sent at or after each never reaches the service
    (its link dropped it); the recorder gets it."""
    recorder_stalls: list[tuple[float, float]] = field(default_factory=list)
    """``(start_s, length_s)`` on the loop's timeline: the recorder's host stalls it, and what
    it would have received meanwhile it receives at the stall's end, in order."""


def motion(t: np.ndarray, axis: str, amplitude: float = 1.0) -> np.ndarray:
    """A smooth test motion per axis, within each axis' limits (m or rad)."""
    i = AXIS_INDEX[axis]
    f = 0.13 + 0.07 * i
    env = np.clip(t / 2.0, 0, 1) ** 2
    base = np.sin(2 * math.pi * f * t) ** 3 + 0.4 * np.sin(2 * math.pi * 2.3 * f * t + i)
    scale = 0.25 if axis.startswith("rails") else 0.05
    return amplitude * scale * env * base


def synthesize(path: str | Path, cfg: ServiceConfig, opts: SynthOptions) -> dict[str, object]:
    """Write the recording of a synthetic session; returns facts about it (tick count...).
    The ticks compute with subnormals flushed to zero, as the service's loop does (its status
    says so, as the service's does)."""
    rng = np.random.default_rng(opts.seed)
    period = round(1e9 / cfg.loop.rate_hz)
    n_src = int(opts.duration_s * opts.source_hz)
    t_src = np.arange(n_src) / opts.source_hz
    keep = np.ones(n_src, bool)
    for start, length in opts.gaps:
        keep &= ~((t_src >= start) & (t_src < start + length))
    sig = {a: motion(t_src, a, opts.amplitude) for a in opts.axes}
    if opts.excite:
        _excite(sig, t_src, cfg, opts)
    for ts, axis, size in opts.steps:
        sig[axis] = sig[axis] + size * (t_src >= ts)
    # sender times (its own drifting clock) and arrival at the service (loop clock, ns)
    t_sender = WALL0 + 0.2 + t_src * (1 + opts.drift)
    transit = rng.uniform(*opts.transit_us, n_src) * 1e3
    arrival = MONO0_NS + np.round((0.2 + t_src) * 1e9 + transit).astype(np.int64)
    frames: list[tuple[int, bytes, bool]] = []  # (arrival ns, payload, the service gets it)
    sent = np.flatnonzero(keep)
    missed = {int(sent[np.searchsorted(sent, np.searchsorted(t_src, ts))])
              for ts in opts.service_misses}
    first = np.zeros(n_src, np.int64)  # the index of the sender run's first sample
    if opts.restart_after_gaps:
        starts = np.flatnonzero(keep & ~np.concatenate([[True], keep[:-1]]))
        first[starts] = starts
        first = np.maximum.accumulate(first)
    for k in np.flatnonzero(keep).tolist():
        seq = k - int(first[k])
        carried = (("rails_x", "rails_y") if opts.partial_every and k % opts.partial_every == 0
                   else opts.axes)
        pos = {a: float(sig[a][k]) for a in carried if a in sig}
        if opts.no_t_every and k % opts.no_t_every == 0:
            payload = msgpack.packb({"seq": seq, "pos": pos})
        else:
            payload = encode_input(seq, float(t_sender[k]), pos)
        frames.append((int(arrival[k]), payload, k not in missed))
        if opts.bad_every and k % opts.bad_every == 0:
            bad = [msgpack.packb({"seq": seq, "pos": {"rails_x": float("nan")}}), b"\xc1",
                   msgpack.packb({"seq": seq + 1, "pos": {"rails_q": 0.0}})][
                k // opts.bad_every % 3]
            frames.append((int(arrival[k]) + 1000, bad, True))
    frames.sort(key=lambda f: f[0])
    # the loop's deadlines: a grid with stalls
    grid0 = MONO0_NS - 37_000
    n_ticks = int((opts.duration_s + 1.0) * cfg.loop.rate_hz)
    m = np.arange(1, n_ticks + 1, dtype=np.int64)
    for ts, skip in opts.stalls:
        m[m * period > (ts + 0.2) * 1e9] += skip
    deadlines = grid0 + m * period
    params, state = new_tick(cfg)
    bypass_at = sorted(opts.bypass)
    fi = 0
    parked_from = None
    out_msgs: list[tuple[int, bytes]] = []
    superseded: list[int] = []  # the service's count after each tick
    episodes: list[int] = []  # the shaper's stale episodes after each tick
    with subnormals_flushed() as flushed:  # the loop's mode
        for j, dl in enumerate(deadlines.tolist()):
            t_rel = (dl - MONO0_NS) / 1e9 - 0.2
            while bypass_at and bypass_at[0][0] <= t_rel:
                _, on, names = bypass_at.pop(0)
                set_bypass(state, [on if a in names else b
                                   for a, b in zip(AXES, state.comp.bypass, strict=True)])
            payloads = []  # every frame that arrived since the last tick, as the service reads
            while fi < len(frames) and frames[fi][0] <= dl:
                if frames[fi][2]:
                    payloads.append(frames[fi][1])
                fi += 1
            skipped = int((dl - deadlines[j - 1]) // period - 1) if j else 0
            out = step(state, params, dl, payloads, skipped)
            superseded.append(state.superseded)
            episodes.append(state.shaper.stale_episodes)
            out_msgs.append((dl, encode_output(out.seq, WALL0 + (dl - MONO0_NS) / 1e9, out.src_seq,
                                               out.u, out.flags)))
            if opts.park_at_s is not None and parked_from is None and t_rel >= opts.park_at_s:
                parked_from = j
                park(state, params, dl)
            elif parked_from is not None and is_parked(state):
                break
    n_out = len(out_msgs)
    # what the recorder receives (wall ns)
    def wall_ns(mono: int) -> int:
        return round(WALL0 * 1e9) + (mono - MONO0_NS)

    msgs: list[tuple[int, str, bytes]] = []
    for arr, payload, _ in frames:
        msgs.append((wall_ns(arr) + 20_000, DEFAULT_KEYS["input"], payload))
    lost: set[int] = set()
    for ts, count in opts.lose_outputs:
        j0 = int((ts + 0.2) * cfg.loop.rate_hz)
        lost.update(range(j0, j0 + count))
    for j, (dl, payload) in enumerate(out_msgs):
        if j not in lost:
            msgs.append((wall_ns(dl) + 150_000, DEFAULT_KEYS["output"], payload))
    if opts.feedback and out_msgs:
        msgs += _feedback(cfg, out_msgs, wall_ns, opts.feedback_gaps)
    if opts.status:
        axes = resolve_axes(cfg)
        st: dict[str, object] = {
            "config": {"hash": config_hash(cfg), "version": 1, "path": None},
            "rate_hz": cfg.loop.rate_hz, "ticks": state.ticks,
            "driven": [a for a, d in zip(AXES, axes.driven, strict=True) if d],
            "saturation": dict(zip(AXES, state.sat, strict=True)),
            "realtime": f"synthetic session; {flushed}"}
        st["clock"] = ({"wall0": WALL0, "mono0_ns": MONO0_NS,
                        "grid0_ns": None if cfg.loop.sync_to_input else grid0,
                        "period_ns": period} if opts.clock_in_status else None)
        counts = {"received": state.received, "accepted": state.accepted,
                  "rejected_by_reason": dict(state.rejected_by_reason)}
        for s in range(int(opts.duration_s) + 1):
            st["t"] = WALL0 + s + 0.5
            j = min(int((s + 0.5) * cfg.loop.rate_hz), len(superseded) - 1)  # its tick
            st["frames"] = {**counts, "superseded": superseded[j] if j >= 0 else 0}
            st["stale_episodes"] = episodes[j] if j >= 0 else 0
            msgs.append((round((WALL0 + s + 0.5) * 1e9), DEFAULT_KEYS["status"],
                         msgpack.packb(st)))
    for start, length in opts.recorder_stalls:
        s0, s1 = round((WALL0 + 0.2 + start) * 1e9), round((WALL0 + 0.2 + start + length) * 1e9)
        msgs = [(s1 if s0 <= ns < s1 else ns, key, payload) for ns, key, payload in msgs]
    msgs.sort(key=lambda x: x[0])
    t_rec = round((WALL0 + 0.2 + opts.record_from_s) * 1e9) if opts.record_from_s else 0
    cfg_json = json.dumps(cfg.model_dump(mode="json")).encode()
    with SessionWriter(path, list(DEFAULT_KEYS.values()), {"config_hash": config_hash(cfg)},
                       cfg_json, flush_s=0, fsync=False) as w:
        for log_ns, key, payload in msgs:
            if log_ns >= t_rec:
                w.write(key, log_ns, payload)
    return {"ticks": n_out, "frames": len(frames), "messages": len(msgs),
            "deadlines": deadlines[:n_out]}


def _excite(sig: dict[str, np.ndarray], t_src: np.ndarray, cfg: ServiceConfig,
            opts: SynthOptions) -> None:
    from motcomp.ident.excitation import AxisRange, excitation

    lim = resolve_axes(cfg).limits
    for axis, *_ in opts.excite:
        sig[axis] = np.zeros_like(t_src)
    for n, (axis, kind, start, length) in enumerate(opts.excite):
        i = AXIS_INDEX[axis]
        exc = excitation(kind, axis, AxisRange(float(lim.p_min[i]), float(lim.p_max[i]),
                                               float(lim.v_max[i]), float(lim.a_max[i])),
                         duration_s=length, rate_hz=opts.source_hz, seed=opts.seed + n,
                         usage=0.8)
        k0 = round(start * opts.source_hz)
        k1 = min(k0 + exc.cmd.size, t_src.size)
        sig[axis][k0:k1] += exc.cmd[:k1 - k0]


def _feedback(cfg: ServiceConfig, out_msgs: list[tuple[int, bytes]], wall_ns: object,
              gaps: Sequence[tuple[float, float]] = ()) -> list[tuple[int, str, bytes]]:
    from motcomp.core.models import simulate_axis
    from motcomp.io.wire import decode_output

    axes = resolve_axes(cfg)
    u = np.array([[decode_output(p)["pos"][a] for a in AXES] for _, p in out_msgs])
    y = np.column_stack([simulate_axis(axes.plants[i], u[:, i], cfg.loop.rate_hz)
                         for i in range(len(AXES))])
    # y[j] is the position at tick j; the acceleration is measured there too (the central
    # second difference), as motcomp hil does
    acc = np.zeros_like(y)
    h = 1.0 / cfg.loop.rate_hz
    acc[1:-1] = (y[2:] - 2 * y[1:-1] + y[:-2]) / (h * h)
    out = []
    yl, al = y.tolist(), acc.tolist()
    for j, (dl, _) in enumerate(out_msgs):
        t_rel = (dl - MONO0_NS) / 1e9 - 0.2
        if any(start <= t_rel < start + length for start, length in gaps):
            continue
        t = WALL0 + (dl - MONO0_NS) / 1e9 + 3e-4
        out.append((wall_ns(dl) + 400_000, DEFAULT_KEYS["feedback"],  # type: ignore[operator]
                    encode_feedback(t, dict(zip(AXES, yl[j], strict=True)),
                                    dict(zip(AXES, al[j], strict=True)))))
    return out
