"""Forged sequence jumps (issue 24, item 6): a forward step of ``seq`` larger than
:data:`~motcomp.core.tick.MAX_SEQ_STEP` while the input is live is rejected (``jump``), counted,
and locks nobody out; once the input is stale it is a restarted sender (docs/WIRE.md,
"Sequence")."""

from __future__ import annotations

import math

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
