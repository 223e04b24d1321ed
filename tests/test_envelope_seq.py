"""Forged sequence jumps (issue 24, item 6): a forward step of ``seq`` larger than
:data:`~motcomp.core.tick.MAX_SEQ_STEP` while the input is live is rejected (``jump``), counted,
and locks nobody out; once the input is stale it is a restarted sender (docs/WIRE.md,
"Sequence")."""

from __future__ import annotations

import math
from typing import Any

from motcomp.config import load_config, new_tick
from motcomp.core.axes import AXES
from motcomp.core.tick import MAX_SEQ_STEP, REJECT_REASONS, TickOutput, step
from motcomp.io.wire import encode_input
from motcomp.resources import config_file

MS = 1_000_000  # ns
H = 1e-3
Y = AXES.index("rails_y")
CFG = load_config(config_file("motcomp.toml"))
STALE_TICKS = round(CFG.loop.stale_after_s / H)


def legit(k: int, seq: int | None = None) -> bytes:
    """The live sender's frame at tick ``k`` (seq ``k`` unless given)."""
    return encode_input(k if seq is None else seq, k * H,
                        {"rails_y": 0.2 * math.sin(2 * math.pi * 0.5 * k * H)})


def test_jump_is_a_reject_reason() -> None:
    assert "jump" in REJECT_REASONS  # the status counts every reason


def test_forged_jump_while_live_is_rejected_and_changes_nothing() -> None:
    """A second sender's frames with ``seq = 2**63`` (and on) between the live sender's: every
    one rejected as ``jump``, the live sender never locked out, the command exactly that of the
    run without them."""
    params, state = new_tick(CFG)
    _, twin = new_tick(CFG)
    outs: list[TickOutput] = []
    twin_outs: list[TickOutput] = []
    forged = 0
    for k in range(3000):
        frames = [legit(k)]
        if 1000 <= k < 1100:
            frames.append(encode_input(2**63 + forged, k * H, {"rails_y": 2.0}))
            forged += 1
        outs.append(step(state, params, k * MS, frames))
        twin_outs.append(step(twin, params, k * MS, [legit(k)]))
    assert state.rejected_by_reason["jump"] == forged == 100
    assert state.rejected == forged and state.accepted == 3000 and state.src_seq == 2999
    assert state.last_reject.startswith(f"jump: seq {2**63 + 99} is ")
    assert "while the input is live" in state.last_reject
    assert [o.u for o in outs] == [o.u for o in twin_outs]


def test_step_up_to_max_seq_step_is_taken_beyond_it_rejected() -> None:
    params, state = new_tick(CFG)
    for k in range(500):
        step(state, params, k * MS, legit(k))
    step(state, params, 500 * MS, legit(500, 499 + MAX_SEQ_STEP))  # frames lost meanwhile
    assert state.superseded == MAX_SEQ_STEP - 1 and state.rejected == 0
    step(state, params, 501 * MS, legit(501, 499 + 2 * MAX_SEQ_STEP + 1))
    assert state.rejected_by_reason["jump"] == 1 and state.src_seq == 499 + MAX_SEQ_STEP


def test_jump_after_the_input_went_stale_is_a_restart() -> None:
    """The live sender stops; after the stale time any ``seq`` is accepted (a restarted
    sender, or one whose counter jumped), not counted as a jump."""
    params, state = new_tick(CFG)
    for k in range(1000):
        step(state, params, k * MS, legit(k))
    k = 1000 + STALE_TICKS + 5
    for j in range(10):
        step(state, params, (k + j) * MS, legit(k + j, 10**12 + j))
    assert state.rejected == 0 and state.src_seq == 10**12 + 9


def test_sender_that_jumps_while_live_is_taken_once_stale() -> None:
    """A sender whose own counter jumps (by more than MAX_SEQ_STEP) while live is rejected for
    the stale time, then taken up again as a restarted sender."""
    params, state = new_tick(CFG)
    for k in range(1000):
        step(state, params, k * MS, legit(k))
    for k in range(1000, 1200):
        step(state, params, k * MS, legit(k, k + 10**6))
    assert state.rejected_by_reason["jump"] in (STALE_TICKS - 1, STALE_TICKS)
    assert state.rejected == state.rejected_by_reason["jump"]
    assert state.src_seq == 1199 + 10**6


# --- the bound on a live sender's ``t`` (docs/WIRE.md, "Input frames") ----------------------

T0 = 1.7e9
"""The senders' clock: epoch seconds."""
TRANSIT_NS = 700_000


def stamped(seq: int, t: float, value: float = 0.1) -> bytes:
    return encode_input(seq, T0 + t, {"rails_y": value})


def run_landings(frames: list[tuple[int, bytes]], ticks: int) -> tuple[list[TickOutput], Any]:
    """The tick at 1 kHz taking each frame at the first tick at or after its landing (ns)."""
    params, state = new_tick(CFG)
    frames = sorted(frames, key=lambda f: f[0])
    outs, i = [], 0
    for k in range(1, ticks):
        batch = []
        while i < len(frames) and frames[i][0] <= k * MS:
            batch.append(frames[i][1])
            i += 1
        outs.append(step(state, params, k * MS, batch, 0, k * MS + 20_000))
    return outs, state


def test_a_frame_sent_late_at_a_restart_does_not_lock_out_the_fresh_ones() -> None:
    """A 100 Hz stamped sender stalls 200 ms between computing a sample and sending it, and
    skips the samples due meanwhile (as docs/WIRE.md asks): the input goes stale, the late frame
    restarts the timeline with a transit 200 ms too long, and every fresh frame after it is
    taken -- before, each read as 150-190 ms from the future (``jump``) until the input went
    stale again (5 frames here; 17-468 frames per run from real senders on a loaded host)."""
    frames = []
    seq = 0
    for k in range(1000):
        t_ns = k * 10 * MS
        if 500 < k < 520:
            continue  # due while the sender was stalled: skipped
        sent = t_ns + (200 * MS if k == 500 else 0)
        frames.append((sent + TRANSIT_NS, stamped(seq, t_ns / 1e9, 0.1 * math.sin(k / 50))))
        seq += 1
    _, state = run_landings(frames, 10_000)
    assert state.rejected == 0, state.last_reject
    assert state.accepted == len(frames)
    # the offset rests on the fresh frames, not on the late one's 200 ms: each is taken at the
    # first tick after it lands (1 ms after its t, the ticks and the samples on whole ms) and
    # 20 us later, the drain (the offset counts from the timeline's base, T0 + 5 s)
    pb = state.shaper.playback
    assert pb.settled() and pb.offset is not None
    transit = pb.offset - (state.shaper.timeline.base() - T0)
    assert abs(transit - 1.02e-3) < 1e-6, transit  # (the epoch stamps' ulp: 0.24 us)


def test_a_forged_t_ahead_is_rejected_and_moves_nothing() -> None:
    """A second sender's frames between a 1 kHz stamped sender's, with a ``seq`` ahead of the
    live one's and a ``t`` ahead of its clock -- by an hour, by ``stale_after_s`` and 10 ms --
    are each rejected (``jump``) and the command is that of the run without them; right after
    a restart (the offset not settled) a ``t`` going back is still rejected."""
    stale = CFG.loop.stale_after_s
    live = [(k * MS + TRANSIT_NS, stamped(k, k * H, 0.2 * math.sin(k * H))) for k in range(3000)]
    forged = [(k * MS + TRANSIT_NS + 1, stamped(k + 50, k * H + ahead, 2.0))
              for k, ahead in ((1200, 3600.0), (1500, stale + 0.01), (1800, 3600.0))]
    outs, state = run_landings(live + forged, 3000)
    twin, _ = run_landings(live, 3000)
    assert state.rejected_by_reason["jump"] == state.rejected == len(forged), state.last_reject
    assert [o.u for o in outs] == [o.u for o in twin]
    # a restart (after the stale time), then a t going back within the first bin
    restart = [(3200 * MS, stamped(5000, 10.0)), (3205 * MS, stamped(5001, 10.005)),
               (3210 * MS, stamped(5002, 9.9))]
    _, state = run_landings(live + restart, 3300)
    assert state.rejected_by_reason["jump"] == 1 and "beyond" in state.last_reject
    assert not state.shaper.playback.settled()
