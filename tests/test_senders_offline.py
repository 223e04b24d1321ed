"""Sender classes as docs/WIRE.md allows them, through the service's tick offline: what reaches
the platform is the motion the values describe, whatever the sender's instants, number format
and clock.

Each sender here is written from the contract (a frame ``{"seq", "t", "pos"}`` in msgpack, ``t``
the instant of the sample), not with the project's own source: a 0.4 m slalom at 0.31 Hz on
rails_y (or a 5 cm heave at 0.5 Hz on hex_z), evaluated by each sender at its own instants and
stamped its own way, reaching the loop 0.3-0.9 ms later.  Against the same motion from a sender on
an exact grid (the floor), over the motion after its first 3 s: the limiter never acts, the
command's acceleration RMS above 5 Hz stays within 2x and its jerk RMS within 3x (the issue's
targets).  The ``linear`` reconstruction (no band limit, no t-as-truth interpolation) shows that
the cases are not trivial: it fails them.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import msgpack
import numpy as np
import pytest

from motcomp.config import ServiceConfig, load_config, new_tick, resolve_axes
from motcomp.core.axes import AXIS_INDEX
from motcomp.core.quality import command_quality
from motcomp.core.tick import set_bypass, step
from motcomp.resources import config_file

T0 = 1_795_000_000.123456  # the senders' epoch origin
DURATION_S = 10.0
SKIP_S = 2.0

MOTIONS = {"rails_y": (0.4, 0.31), "hex_z": (0.05, 0.5)}
"""Amplitude and frequency of each axis' weave: a slalom (motcomp.design.timedomain.slalom's
shape: 1 s at rest, half a period's minimum-jerk fade in, the weave, a fade out)."""


def _motion(axis: str, tau: float) -> float:
    amp, f = MOTIONS[axis]
    tw, fade = tau - 1.0, 0.5 / f
    weave = DURATION_S - 2.0 - 2.0 * fade
    if not 0.0 <= tw <= weave + 2.0 * fade:
        return 0.0
    x = min(tw / fade, (weave + 2.0 * fade - tw) / fade, 1.0)
    env = x ** 3 * (10.0 - 15.0 * x + 6.0 * x * x)
    return amp * env * math.sin(2.0 * math.pi * f * tw)


def _frame(seq: int, t: float | None, axis: str, value: float, float32: bool = False) -> bytes:
    head: dict[str, object] = {"seq": seq} if t is None else {"seq": seq, "t": t}
    packer = msgpack.Packer(use_single_float=float32)
    return (msgpack.Packer().pack_map_header(len(head) + 1)
            + b"".join(msgpack.packb(k) + msgpack.packb(v) for k, v in head.items())
            + msgpack.packb("pos") + packer.pack({axis: value}))


def _sine(axis: str, tau: float) -> float:
    """The live benchmark's motion (tools/wire_senders.py): a pure sine, nothing above its
    frequency, so that whatever the command carries above 5 Hz is the sender's doing."""
    amp, f = MOTIONS[axis]
    return amp * math.sin(2.0 * math.pi * f * tau)


def _sender(kind: str, axis: str, rng: np.random.Generator, rate_hz: float = 1000.0,
            motion: Callable[[str, float], float] = _motion,
            late_share: float = 0.0) -> list[tuple[float, bytes]]:
    """(arrival on the loop's clock, frame) of one sender class (``rate_hz``: the grids);
    ``late_share`` of the frames 1.5-4 ms later still, holding up the ones behind them (one
    link: frames arrive in order)."""
    out: list[tuple[float, bytes]] = []
    tau, k = 0.0, 0
    while tau < DURATION_S:
        late = 3e-4 + rng.uniform(0.0, 6e-4)
        if late_share and rng.uniform() < late_share:
            late += rng.uniform(1.5e-3, 4e-3)
        if kind == "grid":  # exact values on a regular grid, stamped with its instants
            t, v = tau, motion(axis, tau)
        elif kind == "float32":  # the same values sent as float32
            t, v = tau, float(np.float32(motion(axis, tau)))
        elif kind == "epoch":  # t = t0 + k / rate in epoch seconds, the value computed at it
            t = T0 + tau
            v = motion(axis, t - T0)
        elif kind == "wallclock":  # computed at the wall time it stamps: late by 100-300 us
            t = T0 + tau + rng.uniform(1e-4, 3e-4)
            v = motion(axis, t - T0)
            late = rng.uniform(5e-5, 1.5e-4)
        elif kind == "varstep":  # a variable-step solver, 0.5-2 ms steps, epoch stamps
            t = T0 + tau
            v = motion(axis, t - T0)
        elif kind == "float32_rounded":  # float32 values at k/rate, stamped in epoch seconds
            t, v = T0 + tau, float(np.float32(motion(axis, tau)))
        elif kind in ("epoch_rounded", "varstep_rounded"):  # the value at the exact instant,
            t, v = T0 + tau, motion(axis, tau)  # stamped in epoch seconds: rounding is noise
        elif kind == "no_t":
            t, v = None, motion(axis, tau)
        else:
            raise AssertionError(kind)
        sample = tau if t is None else (t - T0 if t > T0 - 1 else t)
        out.append((sample + late, _frame(k, t, axis, v, float32=kind.startswith("float32"))))
        k += 1
        tau = (tau + rng.uniform(5e-4, 2e-3) if kind.startswith("varstep") else
               k / (rate_hz if kind in GRIDS else 1000.0))
    if late_share:
        for n in range(1, len(out)):
            out[n] = (max(out[n][0], out[n - 1][0]), out[n][1])
    out.sort(key=lambda a: a[0])
    return out


GRIDS = ("grid", "float32", "epoch", "epoch_rounded", "float32_rounded")
"""The classes whose ``rate_hz`` is theirs (the others sample about every ms)."""


def _run(cfg: ServiceConfig, kind: str, axis: str, bypass: bool, rate_hz: float = 1000.0,
         motion: Callable[[str, float], float] = _motion,
         late_share: float = 0.0) -> tuple[float, float, float]:
    """(share of ticks the limiter acted on, HF acc RMS, jerk RMS) of the command over the
    motion after SKIP_S."""
    axes = resolve_axes(cfg)
    params, state = new_tick(cfg, axes)
    if bypass:
        set_bypass(state, list(axes.driven))
    i = AXIS_INDEX[axis]
    frames = _sender(kind, axis, np.random.default_rng(7), rate_hz, motion, late_share)
    n = int(DURATION_S * 1000) - 5
    u, acted = np.empty(n), np.zeros(n, dtype=bool)
    j = 0
    for k in range(n):
        now = k * 1e-3
        payload = []
        while j < len(frames) and frames[j][0] <= now:
            payload.append(frames[j][1])
            j += 1
        before = state.acted[i]
        out = step(state, params, 10**9 + k * 1_000_000, payload)
        u[k] = out.u[i]
        acted[k] = state.acted[i] != before
    part = slice(int(SKIP_S * 1000), n)
    q = command_quality(u[part], 1000.0)
    return float(acted[part].mean()), q.hf_acc_rms, q.jerk_rms


def _cfg(reconstruction: str = "smooth") -> ServiceConfig:
    cfg = load_config(config_file("motcomp.toml"))
    return cfg.model_copy(update={"input": cfg.input.model_copy(
        update={"reconstruction": reconstruction})})


KINDS = ["float32", "epoch", "wallclock", "varstep", "no_t"]


@pytest.mark.slow
@pytest.mark.parametrize("bypass", [False, True], ids=["compensated", "bypassed"])
@pytest.mark.parametrize("axis", ["rails_y", "hex_z"])
def test_every_sender_class_reaches_the_grid_senders_floor(axis: str, bypass: bool) -> None:
    cfg = _cfg()
    share0, hf0, jerk0 = _run(cfg, "grid", axis, bypass)
    assert share0 == 0.0
    for kind in KINDS:
        share, hf, jerk = _run(cfg, kind, axis, bypass)
        assert share == 0.0, kind
        assert hf <= 2.0 * hf0, (kind, hf, hf0)
        assert jerk <= 3.0 * jerk0, (kind, jerk, jerk0)


@pytest.mark.slow
@pytest.mark.parametrize("rate_hz", [1000.0, 250.0, 60.0])
@pytest.mark.parametrize("axis", ["rails_y", "hex_z"])
def test_values_on_a_grid_its_epoch_stamps_round_are_read_on_that_grid(axis: str,
                                                                       rate_hz: float) -> None:
    """The commonest vehicle model: values computed at ``k/rate``, stamped ``t0 + k/rate`` in
    epoch seconds (0.24 us coarse), here on a pure sine.  Read at the stamps, the rounding is
    position noise the compensator amplifies (HF 0.016 m/s^2 on the compensated rails, 1 600
    times the floor); the values show that they lie on the grid, and there they are read: the
    command is the exact-stamp sender's, within 2x above 5 Hz and 3x in jerk (float32 values
    as well: their own rounding is then what is left, bounded by the chain's designed figure,
    docs/WIRE.md).  A sender whose values are computed at the rounded stamps (``epoch``) keeps
    its stamps as the instants, and is as exact.  At 60 Hz a window of the evidence spans
    0.12 s and float32's own rounding is half the stamps' on the rails: the values take about
    6 s to decide there, most of this run, and that case is left out of the bound."""
    cfg = _cfg()
    for bypass in (False, True):
        _, hf0, jerk0 = _run(cfg, "grid", axis, bypass, rate_hz, _sine)
        for kind in ("epoch_rounded", "epoch"):
            share, hf, jerk = _run(cfg, kind, axis, bypass, rate_hz, _sine)
            assert share == 0.0
            assert hf <= 2.0 * hf0, (kind, bypass, hf, hf0)
            assert jerk <= 3.0 * jerk0, (kind, bypass, jerk, jerk0)
        if rate_hz < 100.0:
            continue  # float32 at 60 Hz: about 6 s of the 8 to decide (docstring)
        share, hf, jerk = _run(cfg, "float32_rounded", axis, bypass, rate_hz, _sine)
        floor = _run(cfg, "float32", axis, bypass, rate_hz, _sine)  # exact stamps
        assert share == 0.0
        assert hf <= 1.1 * floor[1] and jerk <= 1.1 * floor[2], (bypass, hf, jerk, floor)


@pytest.mark.slow
def test_late_frames_do_not_amplify_a_float32_senders_rounding() -> None:
    """5 % of the frames 1.5-4 ms late (past the 1.7 ms playback lag: each one bridged by
    extrapolation) from a float32 sender on the compensated rails' sine: the rounding does not
    grow at the bridges beyond what it costs on time, the command's HF acceleration within 2x
    and its jerk within 1.5x of the same sender's on time (1.6x and 1.2x; docs/WIRE.md, "Late
    frames").  With every slope difference faded out and the knots' slopes over one period,
    as before, 7.9x and 2.6x."""
    cfg = _cfg()
    share, hf, jerk = _run(cfg, "float32", "rails_y", False, 1000.0, _sine, late_share=0.05)
    _, hf0, jerk0 = _run(cfg, "float32", "rails_y", False, 1000.0, _sine)
    assert share == 0.0
    assert hf <= 2.0 * hf0 and jerk <= 1.5 * jerk0, (hf, hf0, jerk, jerk0)


@pytest.mark.slow
def test_a_variable_step_solvers_stamp_rounding_is_not_amplified_at_late_samples() -> None:
    """Values at a variable-step solver's exact instants, stamped in epoch seconds: the
    stamps' rounding (0.24 us x the speed) is noise, and each sample the playback has already
    bridged brings a slope difference that noise explains.  Faded, as every slope difference
    was, it read 12x the floor's HF acceleration and 10.5x its jerk on the compensated rails;
    within 4x and 6x now (3.1x and 4.3x; docs/WIRE.md, "Late frames")."""
    cfg = _cfg()
    _, hf0, jerk0 = _run(cfg, "grid", "rails_y", False)
    share, hf, jerk = _run(cfg, "varstep_rounded", "rails_y", False)
    assert share == 0.0
    assert hf <= 4.0 * hf0 and jerk <= 6.0 * jerk0, (hf, hf0, jerk, jerk0)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["float32", "wallclock"])
def test_without_the_cure_the_same_senders_make_the_command_chatter(kind: str) -> None:
    """The ``linear`` reconstruction, as the contract's worst case: the limiter acts, or the
    command's jerk is many times the floor's."""
    cfg = _cfg("linear")
    jerk0 = _run(_cfg(), "grid", "rails_y", False)[2]
    share, _, jerk = _run(cfg, kind, "rails_y", False)
    assert share > 0.005 or jerk > 10.0 * jerk0, (kind, share, jerk, jerk0)


TABLE = [("exact values on a 1 kHz grid, sent 0.3-0.9 ms late (the floor)", "grid", 1000.0),
         ("the same values as float32", "float32", 1000.0),
         ("`t = t0 + k/rate` in epoch seconds, the value computed at it", "epoch", 1000.0),
         ("each value computed at the wall time it stamps (100-300 us after the grid)",
          "wallclock", 1000.0),
         ("no `t` (1 kHz)", "no_t", 1000.0),
         ("250 Hz grid", "grid", 250.0), ("100 Hz grid", "grid", 100.0),
         ("60 Hz grid", "grid", 60.0),
         ("values at `k/rate`, stamped `t0 + k/rate` in epoch seconds (the rounding is noise)",
          "epoch_rounded", 1000.0),
         ("variable steps of 0.5-2 ms, values at the exact step, stamped in epoch seconds "
          "(idem)", "varstep_rounded", 1000.0),
         ("variable steps of 0.5-2 ms, each value computed at its epoch stamp", "varstep",
          1000.0)]
"""The rows of docs/WIRE.md's offline table: (label, sender class, rate)."""


if __name__ == "__main__":  # docs/WIRE.md's table: python tests/test_senders_offline.py
    cfg = _cfg()
    print("| sender | rails_y, on | rails_y, bypassed | hex_z, on (predicted) | hex_z, bypassed |")
    print("|---|---|---|---|---|")
    for label, kind, rate in TABLE:
        cells = []
        for axis in ("rails_y", "hex_z"):
            for bypass in (False, True):
                share, hf, jerk = _run(cfg, kind, axis, bypass, rate)
                cells.append(f"{100 * share:.3g} %, {hf:.2g}, {jerk:.2g}")
        print(f"| {label} | " + " | ".join(cells) + " |", flush=True)
