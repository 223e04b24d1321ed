"""One tick of the compensator, the whole per-tick policy in one pure function: :func:`step`.

The service (:mod:`motcomp.runtime.service`), the offline and real-time replays
(:mod:`motcomp.replay`) and the synthetic sessions (:mod:`motcomp.replay.synth`) all call it,
and nothing else of the tick, so a replay computes with the very code that ran::

     catch-up (skipped deadlines, below; before the frame, which is taken at now_ns)
        |
     payloads (every input frame since the last tick, oldest first)
        |
        v
     parse and check: size, msgpack, schema, types, axes, finite, range, seq
        |  rejected: counted under its reason (REJECT_REASONS), changes nothing
        v
     ReferenceShaper.on_input                   motcomp.core.shaper: start-up, stale, hold,
        |                                       rejoin, parking, linear reconstruction
     now --> ReferenceShaper.reference --> r --> Prediction.step --> r' --> Compensator.step --> u
                                         (motcomp.core.predictor:  (motcomp.core.compensator:
                                          prefilter, band monitor,  PID, internal model,
                                          fallback)                 limiter)
                                                                    |
               EnvelopeGuard.apply (motcomp.core.envelope: the hardware envelope) <--------+
                    |
                    v
                 saturation verdict, flags --> TickOutput(seq, src_seq, u, flags, limited, mode)

No I/O, no clock, no threads: time comes in as ``now_ns`` (the tick's instant on the loop's
clock), bytes come in, a :class:`TickOutput` goes out; the caller encodes and sends it.

Rules for edge cases
--------------------
* Any payload: :func:`step` never raises because of it.  A frame larger than
  ``max_frame_bytes`` is rejected unread (``oversize``); msgpack-python decodes the rest (its
  unpacker keeps an explicit stack, bounded at 1024 levels: deeper is ``decode``); the checks
  that follow are one flat pass that never recurses into a value, and every error text is
  bounded (:data:`MAX_ERROR_CHARS`).  An exception of any other kind while handling the frame
  is counted as ``internal`` and the tick goes on.  A rejected frame changes no state but the
  counters.
* Input: a tick reads every frame that arrived since the previous one, oldest first (the
  reconstruction uses every sample, a burst after a sender's stall included), except until a
  frame is accepted: then it reads its newest only (the backlog of a sender that started first
  is not history).
* Sequence: ``seq`` must increase (``duplicate``, ``old``), except after the input was stale,
  when any ``seq`` is accepted (a restarted sender).  A step forward of at most
  :data:`MAX_SEQ_STEP` counts the skipped frames as ``superseded``; a larger one while the input
  is live is rejected (``jump``): frames sent meanwhile could not be missed in less than the
  stale time, so it is another sender (or a forged frame) that would lock the live one out;
  once the input is stale it is accepted as a restart (a regress of more than a million counts
  nothing as superseded: a restart).  Likewise a ``t`` (``smooth`` reconstruction) outside the
  instants a live sender's next sample can have (:meth:`ReferenceShaper.next_t_bound
  <motcomp.core.shaper.ReferenceShaper.next_t_bound>`: not before its newest sample, and not
  after the instant the frame was taken, on the sender's clock, by more than
  ``stale_after_s``: no sample lands before it is computed) is rejected (``jump``) while the
  input is live.  After a stall of the loop, each frame is judged at the deadline it had
  landed by (catch-up, below): the loop's stall is not an input loss.
* Catch-up: when the caller missed deadlines (``skipped`` > 0, a stall of its thread), the
  frames that landed meanwhile are taken first (the shaper plays each sample at its own
  instant, so the deadlines missed see the samples they would have seen; a stamped one at
  the deadline its ``t`` says it had landed by, one without ``t`` timed by the instant it was
  drained, never before it landed), then the
  compensator is stepped at the ``min(skipped, MAX_CATCH_UP)`` deadlines just before
  ``now_ns``, with the reference of each and no output, so that its discrete dynamics stay on
  the real time grid instead of seeing the reference jump several samples at once (their
  difference would reach the command as a derivative kick).  Every step, sent or not, goes
  through the limiter and the envelope guard: the limits hold at every deadline of the grid,
  and so between two consecutive outputs however many periods apart (docs/WIRE.md, "The
  limits across missed ticks").  A stall longer than ``MAX_CATCH_UP`` periods is caught up
  over its last ones.  One output per call, never a burst.
* Input loss (the shaper's mode ``stale`` or ``parking``, catch-up steps included): at the first
  such tick every driven axis gets a window (:meth:`Compensator.open_window
  <motcomp.core.compensator.Compensator.open_window>`): the hull of its command ``p``, its braking
  point ``p + v |v| / (2 a_max)`` (``v`` the command's velocity) and the reference, widened by
  each later reference and the reach of its motion (the ramp to neutral is never blocked nor
  braked: :meth:`~motcomp.core.compensator.Compensator.widen_window`); its limiter brakes at the
  window's edge as at an end stop, its target is the shaper's reference (the PID starts over at
  rest on it, the prediction is held off at once; both run on, unused, as in bypass) and, once
  braked, its speed is at most the ramp's (``ramp_speed``). So no axis, compensated, predicted or
  bypassed, travels beyond ``v^2 / (2 a_max)`` in the direction of its velocity at the loss, or
  beyond the held reference where that lies further (plus rounding), it only returns towards the
  held reference during the hold, and it ramps to neutral at the ramp's speed
  (tests/test_input_loss.py). The window is removed when the input is live again (``rejoin``:
  compensation switches back on as out of a bypass, from the command being sent:
  :class:`~motcomp.core.compensator.Compensator`).
* Envelope: every command of the compensator (catch-up steps included) goes through the
  envelope guard (:mod:`motcomp.core.envelope`, ``TickParams.envelope``, built from the
  config's hardware envelope by :func:`motcomp.config.tick_params`), a no-op while the limiter
  works; an axis it changes is flagged ``envelope:<axis>`` and counted
  (:attr:`TickState.envelope_clamps`, per axis :attr:`TickState.envelope_acted`).
* Saturation verdict (flag ``sat:<axis>``, ``limited``): a position or velocity bound acted
  (holding the end of the range for a target beyond it included), or the command departs from
  its target by more than ``saturation_tolerance`` on a 20 ms exponential average; the limiter
  absorbing zero-mean jitter is not a saturation.
* Prediction (axes with a ``prediction``): used while the input is live (the shaper's mode
  ``""``, or ``rejoin``: the blend into live input after a start or a resume, so that the
  prediction has faded in by the time the blend ends), the config's ``predict`` is true and
  compensation is on (:func:`set_bypass` turns it off with the
  PID; an axis the config bypasses keeps its prediction when compensation is turned back on);
  otherwise, and while the band monitor finds the reference outside the band, it falls back to
  the plain reference, bumplessly (:mod:`motcomp.core.predictor`), except on an input loss:
  then the compensator takes the plain reference at once (the window below; the limiter
  smooths the step).  A change of its parameters (a reload) is taken at the next tick,
  bumplessly.
* Flags, in this order: the shaper's mode (``rejoin``, ``stale``, ``parking``) if any, then
  ``sat:<axis>`` per limited axis, then ``envelope:<axis>`` per axis the envelope guard
  changed (also marked limited), then ``bypass:<axis>`` per driven axis in bypass, then
  ``fallback:<axis>`` per axis whose prediction the band monitor holds off (not while the
  shaper's mode or a switch-off does), then ``nopredict:<axis>`` per axis whose configured
  prediction is turned off with compensation (:func:`set_bypass`; what a replay needs to tell
  it from the PID's bypass, which a config may set on a predicted axis).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgpack
from mypy_extensions import mypyc_attr

from motcomp.core.axes import AXES, AXIS_INDEX
from motcomp.core.compensator import Compensator
from motcomp.core.envelope import EnvelopeGuard, EnvelopeParams
from motcomp.core.native import frozen_reduce
from motcomp.core.predictor import MonitorParams, Prediction, PredictorParams
from motcomp.core.saturation import POS, VEL
from motcomp.core.shaper import ReferenceShaper, ShaperParams
from motcomp.errors import FrameError

__all__ = [
    "MAX_CATCH_UP",
    "MAX_ERROR_CHARS",
    "MAX_SEQ_STEP",
    "REJECT_REASONS",
    "TickOutput",
    "TickParams",
    "TickState",
    "is_parked",
    "park",
    "parse_input",
    "prediction_status",
    "set_bypass",
    "step",
    "warm_start",
]

MAX_SEQ_STEP = 1000
"""A larger forward step of ``seq`` is not taken as frames the sender sent meanwhile, and is
rejected (``jump``) while the input is live."""
REJECT_REASONS: tuple[str, ...] = ("oversize", "decode", "schema", "type", "axis", "nonfinite",
                                   "range", "duplicate", "old", "jump", "internal")
"""Why an input frame was rejected (the status counts each)."""
MAX_CATCH_UP = 2000
"""Longest stall (in periods) whose deadlines are computed afterwards: a 200 ms stall costs the
next tick about 200 reference and compensator steps (3-6 ms at 1 kHz, docs/BENCHMARKS.md),
whose own overrun is caught up by the tick after."""
MAX_ERROR_CHARS = 200
"""Longest text of a rejected frame's error (status ``last_reject``)."""
_INPUT_KEYS = frozenset({"seq", "t", "pos"})
_HARD_BITS = POS | VEL
_SAT_FLAGS = tuple(f"sat:{a}" for a in AXES)
_ENVELOPE_FLAGS = tuple(f"envelope:{a}" for a in AXES)
_BYPASS_FLAGS = tuple(f"bypass:{a}" for a in AXES)
_FALLBACK_FLAGS = tuple(f"fallback:{a}" for a in AXES)
_NOPREDICT_FLAGS = tuple(f"nopredict:{a}" for a in AXES)
_unpackb = msgpack.unpackb


@dataclass(frozen=True)
class TickParams:
    """Everything a tick needs besides its state; swapped whole on a reload."""

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return frozen_reduce(self)

    rate_hz: float
    shaper: ShaperParams
    saturation_tolerance: float = 1e-4
    """Departure (axis units, 20 ms average) from the target that counts as saturated."""
    max_frame_bytes: int = 4096
    """Longest input frame read; a larger one is rejected (``oversize``)."""
    prediction: tuple[PredictorParams | None, ...] = ()
    """Per axis (:data:`AXES` order), the predictive prefilter; empty or None: none."""
    predict: tuple[bool, ...] = ()
    """Per axis, whether the prefilter is used (the config's ``predict``)."""
    monitor: MonitorParams = MonitorParams()  # noqa: RUF009 (frozen, immutable)
    """The prediction's band monitor and fallback."""
    envelope: EnvelopeParams | None = None
    """The hardware envelope every command is held in (:mod:`motcomp.core.envelope`);
    :func:`motcomp.config.tick_params` always sets it (None: no guard, a bare core test)."""

    @property
    def period_ns(self) -> int:
        return round(1e9 / self.rate_hz)

    @property
    def verdict_alpha(self) -> float:
        """Weight of the newest sample in the verdict's 20 ms average."""
        return min(1.0, 1.0 / (0.02 * self.rate_hz))


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class TickOutput:
    """What one tick sends: the command ``u`` in :data:`AXES` order and what goes with it.
    (A plain class, not a dataclass: compiled, a dataclass' generated ``__init__`` would run
    interpreted at every tick.)"""

    seq: int
    """Counts the outputs (catch-up steps send nothing)."""
    src_seq: int
    """``seq`` of the last valid input frame (-1 before the first)."""
    u: list[float]
    flags: list[str]
    limited: list[bool]
    mode: str
    """``""`` when live and settled, else ``rejoin``, ``stale`` or ``parking``."""
    rx_ns: int
    """How long after the tick's instant its input frames were taken (ns; 0: at it): what a
    replay needs to time them as the tick did (output frames carry it as ``rx``)."""

    def __init__(self, seq: int, src_seq: int, u: list[float], flags: list[str],
                 limited: list[bool], mode: str, rx_ns: int = 0) -> None:
        self.seq = seq
        self.src_seq = src_seq
        self.u = u
        self.flags = flags
        self.limited = limited
        self.mode = mode
        self.rx_ns = rx_ns

    def __eq__(self, other: object) -> bool:
        return isinstance(other, TickOutput) and (
            (self.seq, self.src_seq, self.u, self.flags, self.limited, self.mode, self.rx_ns)
            == (other.seq, other.src_seq, other.u, other.flags, other.limited, other.mode,
                other.rx_ns))

    def __repr__(self) -> str:
        return (f"TickOutput(seq={self.seq!r}, src_seq={self.src_seq!r}, u={self.u!r}, "
                f"flags={self.flags!r}, limited={self.limited!r}, mode={self.mode!r}, "
                f"rx_ns={self.rx_ns!r})")


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class TickState:
    """Everything that changes from tick to tick: the compensator, the shaper, the counters."""

    def __init__(self, comp: Compensator, driven: Sequence[bool]) -> None:
        n = comp.n
        self.comp = comp
        self.shaper = ReferenceShaper(n)
        self.last_seq: int | None = None
        self.received = 0
        self.accepted = 0
        self.rejected_by_reason = dict.fromkeys(REJECT_REASONS, 0)
        self.last_reject = ""
        self.src_seq = -1
        self.superseded = 0
        self.sat = [0] * n
        self.acted = [0] * n
        """Ticks on which the limiter changed the command of each axis (any bound, any
        amount; :attr:`sat` counts only the saturation verdict)."""
        self.ticks = 0
        self.mode = "startup"
        self.moving = 0
        """Bit ``i`` set: axis ``i``'s compensation was changing at a step of the last tick, its
        catch-up steps included (:attr:`Compensator.moving` or :attr:`Prediction.moving`)."""
        self._dev_lp = [0.0] * n
        self.bypass_flags: list[str] = []
        self._driven = tuple(driven)
        self.pred = Prediction([None] * n, MonitorParams(), comp.rate_hz)
        """The prefilters (:mod:`motcomp.core.predictor`), configured from the params at the
        first tick and after a reload."""
        self._pred_src: tuple[PredictorParams | None, ...] | None = None
        self._pred_wanted = [False] * n
        self._pred_params_predict: tuple[bool, ...] = ()
        self._comp_off = [False] * n
        self._ref = [0.0] * n
        self.nopredict_flags: list[str] = []
        self.guard = EnvelopeGuard(n)
        """The envelope guard's state (:mod:`motcomp.core.envelope`)."""
        self._windowed = False  # the compensator holds the input-loss window (_window)
        _set_bypass_flags(self)

    @property
    def envelope_clamps(self) -> int:
        """Outputs (catch-up steps included) on which the envelope guard changed the command:
        0 unless the limiter or what feeds it has a bug."""
        return self.guard.clamps

    @property
    def envelope_acted(self) -> list[int]:
        """Per axis, the outputs on which the envelope guard changed it."""
        return list(self.guard.acted)

    @property
    def prediction_off(self) -> list[bool]:
        """Per axis, prediction turned off with compensation (:func:`set_bypass`)."""
        return list(self._comp_off)

    @property
    def rejected(self) -> int:
        return sum(self.rejected_by_reason.values())

    def _reject(self, reason: str, text: str) -> None:
        self.rejected_by_reason[reason] += 1
        text = f"{reason}: {text}"
        self.last_reject = (text if len(text) <= MAX_ERROR_CHARS
                            else text[:MAX_ERROR_CHARS - 3] + "...")


def step(state: TickState, p: TickParams, now_ns: int,
         payload: bytes | Sequence[bytes] | None = None, skipped: int = 0,
         arrived_ns: int | None = None) -> TickOutput:
    """One tick at the instant ``now_ns`` (ns, the loop's clock) with the input frames that
    arrived since the last tick, oldest first (one frame, a sequence, or None), taken at
    ``arrived_ns`` (default ``now_ns``; never before they landed); ``skipped`` deadlines were
    missed before it.  See the module docstring; never raises because of a payload."""
    now = now_ns / 1e9
    arrived = now if arrived_ns is None or arrived_ns < now_ns else arrived_ns / 1e9
    shaper, sp = state.shaper, p.shaper
    if p.prediction is not state._pred_src:
        _sync_prediction(state, p)
    env = p.envelope
    frames: Sequence[bytes] = ()
    if payload is not None:
        if isinstance(payload, bytes | bytearray | memoryview):
            frames = (bytes(payload),)
        elif state.last_seq is None:  # no frame accepted yet: a backlog is not history
            frames = payload[-1:]
        else:
            frames = payload
    moving = 0
    if skipped > 0:  # the deadlines missed: computed on the grid, nothing sent
        period = p.period_ns
        parsed = [_parse(state, p, frame) for frame in frames]
        k = 0
        for j in range(min(skipped, MAX_CATCH_UP), 0, -1):
            d = (now_ns - j * period) / 1e9
            while k < len(parsed) and shaper.landed_by(parsed[k][1], d):
                # at the deadline it had landed by; a frame whose landing its t cannot bound
                # (no t, no transit known yet) is timed by the instant it was drained: never
                # before it landed
                item = parsed[k]
                _take(state, p, d, d if shaper.landing_known(item[1]) else arrived, item)
                k += 1
            r, m = shaper.reference(sp, d)
            if m or state._windowed:
                _window(state, sp, r, m)
            u_c = state.comp.step(_predicted(state, r, m))
            moving |= state.comp.moving | state.pred.moving
            if env is not None:
                state.guard.apply(env, u_c)
        for item in parsed[k:]:
            _take(state, p, now, arrived, item)
    else:
        for frame in frames:
            _take(state, p, now, arrived, _parse(state, p, frame))
    ref, mode = shaper.reference(sp, now)
    comp = state.comp
    if mode or state._windowed:
        _window(state, sp, ref, mode)
    u = comp.step(_predicted(state, ref, mode))
    state.moving = moving | comp.moving | state.pred.moving
    guarded = env is not None and state.guard.apply(env, u)
    flags = [mode] if mode else []
    limited = [False] * len(u)
    sat, lp, dev, acted = state.sat, state._dev_lp, comp.deviation, state.acted
    tol = p.saturation_tolerance
    alpha = p.verdict_alpha
    keep = 1.0 - alpha
    for i, f in enumerate(comp.flags):
        d = dev[i]
        if not f and d == 0.0 and lp[i] == 0.0:  # the common case: nothing to average
            continue
        if f:
            acted[i] += 1
        lp[i] = alpha * d + keep * lp[i]
        # no flag but a deviation: the target lay beyond the range, the command holds its end
        if f & _HARD_BITS or (f and abs(lp[i]) > tol) or (not f and d != 0.0):
            sat[i] += 1
            limited[i] = True
            flags.append(_SAT_FLAGS[i])
    if guarded:
        _envelope_flags(state, flags, limited)
    flags.extend(state.bypass_flags)
    if state.pred.idx:
        for i, fallen in enumerate(state.pred.fallen_back()):
            if fallen:
                flags.append(_FALLBACK_FLAGS[i])
        flags.extend(state.nopredict_flags)
    out = TickOutput(state.ticks, state.src_seq, u, flags, limited, mode,
                     0 if arrived_ns is None or arrived_ns < now_ns else arrived_ns - now_ns)
    state.ticks += 1
    state.mode = mode or "running"
    return out


def _window(state: TickState, sp: ShaperParams, ref: list[float], mode: str) -> None:
    """The input-loss window (module docstring): opened when the input stops being live
    (``stale``, ``parking``), widened by the reference while it is not, closed when it is."""
    comp = state.comp
    if mode == "stale" or mode == "parking":
        if state._windowed:
            comp.widen_window(ref)
        else:
            # the last plain reference: the prediction is held off at once (_predicted)
            comp.open_window(state._driven, ref, sp.ramp_speed, state._ref)
            state.pred.hold_off()  # as the window takes the plain reference: at once
            state._windowed = True
    elif state._windowed:
        comp.close_window()
        state._windowed = False


def _envelope_flags(state: TickState, flags: list[str], limited: list[bool]) -> None:
    """Flag (and mark limited) the axes the envelope guard changed this tick."""
    guard = state.guard
    for i, stamp in enumerate(guard.acted_at):
        if stamp == guard.applied:
            limited[i] = True
            flags.append(_ENVELOPE_FLAGS[i])


def _sync_prediction(state: TickState, p: TickParams) -> None:
    """Take the params' prediction (first tick, reload), bumplessly.  A prefilter designed for
    another rate raises :class:`~motcomp.errors.ConfigError`: the config refuses one before a
    tick sees it."""
    n = state.comp.n
    params = tuple(p.prediction) + (None,) * (n - len(p.prediction))
    state.pred.set_params(params, p.monitor, state._ref)
    state._pred_src = p.prediction
    predict = tuple(p.predict) + (False,) * (n - len(p.predict))
    state._pred_params_predict = predict
    _set_pred_wanted(state)
    _set_bypass_flags(state)


def _set_pred_wanted(state: TickState) -> None:
    """Prediction wanted per axis: configured, ``predict`` on, compensation not turned off."""
    predict = state._pred_params_predict
    off = state._comp_off
    state._pred_wanted = [bool(i < len(predict) and predict[i]) and not off[i]
                          and state.pred.params[i] is not None for i in range(state.comp.n)]


def _predicted(state: TickState, ref: list[float], mode: str) -> list[float]:
    """The reference through the prediction (unchanged without one)."""
    state._ref = ref
    pred = state.pred
    if not pred.idx:
        return ref
    # as wanted while the input is live or blending into it; held off on its loss
    out = pred.step(ref, not mode or mode == "rejoin", state._pred_wanted)
    return ref if state._windowed else out  # input lost: the plain reference (module docstring)


_Parsed = tuple[int, float | None, dict[int, float] | None, FrameError | None]
"""A frame as read: ``(seq, t, pos, None)``, or ``(0, None, None, why it was rejected)``."""


def _parse(state: TickState, p: TickParams, payload: bytes) -> _Parsed:
    """Read one frame (:func:`parse_input`); never raises."""
    sp = p.shaper
    try:
        seq, t, pos = parse_input(payload, sp.reach_lo, sp.reach_hi, p.max_frame_bytes)
    except FrameError as exc:
        return 0, None, None, exc
    except Exception as exc:  # a bug must not stop the loop: counted as internal
        return 0, None, None, FrameError("internal", f"{type(exc).__name__}: "
                                                     f"{str(exc)[:MAX_ERROR_CHARS]}")
    return seq, t, pos, None


def _take(state: TickState, p: TickParams, now: float, arrived: float, frame: _Parsed) -> None:
    """Check one frame read by :func:`_parse` and hand it to the shaper; a rejection is
    counted, never raised."""
    state.received += 1
    shaper, sp = state.shaper, p.shaper
    seq, t, pos, error = frame
    try:
        if error is not None or pos is None:
            raise error or FrameError("internal", "no values")
        last = state.last_seq
        if last is not None and not 0 < seq - last <= MAX_SEQ_STEP \
                and not shaper.is_stale(sp, now):
            if seq > last:
                raise FrameError("jump", f"seq {seq} is {seq - last} ahead of {last} (more than "
                                         f"{MAX_SEQ_STEP}) while the input is live")
            raise FrameError("duplicate" if seq == last else "old", f"seq {seq} after {last}")
        if t is not None and sp.reconstruction == "smooth":
            bound = shaper.next_t_bound(sp, now, arrived)
            if bound is not None and not bound[0] <= t <= bound[1]:
                lo, hi = bound
                raise FrameError("jump", f"t {t!r} is {t - hi if t > hi else t - lo:+.6g} s "
                                         f"beyond [{lo:.6f}, {hi:.6f}], the instants a live "
                                         "sender's next sample can have")
        step_ = seq - last if last is not None and 0 < seq - last <= MAX_SEQ_STEP else 1
        shaper.on_input(sp, pos, now, t, step_, arrived)
    except FrameError as exc:
        state._reject(exc.reason, str(exc))
        return
    except Exception as exc:  # a bug must not stop the loop: count it
        state._reject("internal", f"{type(exc).__name__}: {str(exc)[:MAX_ERROR_CHARS]}")
        return
    state.last_seq = seq
    state.accepted += 1
    gap = seq - state.src_seq - 1
    if state.src_seq >= 0 and 0 < gap < 1_000_000:  # a regress is a source restart
        state.superseded += gap
    state.src_seq = seq


def parse_input(payload: bytes, lo: Sequence[float], hi: Sequence[float],
                max_bytes: int = 4096) -> tuple[int, float | None, dict[int, float]]:
    """``(seq, t, {axis index: value})`` of an input frame ``{"seq", "t"?, "pos"}``
    (docs/WIRE.md) whose values lie within ``[lo, hi]`` per axis.

    Raises
    ------
    FrameError
        ``reason`` one of :data:`REJECT_REASONS`; the message names the key and the value.
    """
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise FrameError("decode", f"payload is {_describe(payload)}, not bytes")
    size = len(payload)
    if size > max_bytes:
        raise FrameError("oversize", f"frame of {size} bytes exceeds the cap of {max_bytes}")
    try:
        obj = _unpackb(payload, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        raise FrameError("decode", f"not a msgpack frame: {str(exc)[:80]}") from None
    if obj.__class__ is not dict:
        raise FrameError("decode", f"frame is {_describe(obj)}, not a map")
    for key in obj:
        if key not in _INPUT_KEYS:
            raise FrameError("schema", f"unknown key {_describe(key)} in input frame")
    if "seq" not in obj or "pos" not in obj:
        raise FrameError("schema", f"input frame lacks {'seq' if 'seq' not in obj else 'pos'}")
    seq = obj["seq"]
    if seq.__class__ is not int:
        raise FrameError("type", f"seq must be an int, got {_describe(seq)}")
    t = obj.get("t")
    if t is not None:
        if t.__class__ is not float:
            if t.__class__ is not int:
                raise FrameError("type", f"t must be a number, got {_describe(t)}")
            t = float(t)
        if not math.isfinite(t):
            raise FrameError("nonfinite", f"t is {t!r}")
    pos = obj["pos"]
    if pos.__class__ is not dict:
        raise FrameError("type", f"pos must be a map, got {_describe(pos)}")
    if not pos:
        raise FrameError("schema", "pos is empty")
    out: dict[int, float] = {}
    index = AXIS_INDEX
    for axis, value in pos.items():
        i = index.get(axis) if axis.__class__ is str else None
        if i is None:
            raise FrameError("axis", f"unknown axis {_describe(axis)} in pos")
        if value.__class__ is not float:
            if value.__class__ is not int:
                raise FrameError("type", f"pos.{axis} must be a number, got {_describe(value)}")
            value = float(value)
        if not lo[i] <= value <= hi[i]:
            if not math.isfinite(value):
                raise FrameError("nonfinite", f"pos.{axis} is {value!r}")
            raise FrameError("range", f"pos.{axis} = {value!r} is outside "
                                      f"[{lo[i]:.6g}, {hi[i]:.6g}]")
        out[i] = value
    return seq, t, out


def _describe(x: object) -> str:
    """A short description of any value, without recursing into it."""
    if x is None or isinstance(x, bool | float):
        return repr(x)
    if isinstance(x, int):
        return str(x) if -10**30 < x < 10**30 else f"an int of {x.bit_length()} bits"
    if isinstance(x, str | bytes):
        return repr(x[:40]) + ("..." if len(x) > 40 else "")
    try:
        return f"a {type(x).__name__} of {len(x)} items"  # type: ignore[arg-type]
    except Exception:
        return f"a {type(x).__name__}"


# --- between ticks: bypass, parking ----------------------------------------------------------
def set_bypass(state: TickState, mask: Sequence[object],
               prediction_off: Sequence[object] | None = None) -> list[str]:
    """PID off (True) or on (False) per axis, bumplessly; entries of undriven axes are ignored.
    ``prediction_off`` (default: ``mask``) turns the axes' prediction off (True) or back on, as
    far as the config uses it.  Returns the axes in bypass."""
    comp = state.comp
    new = [bool(m) if d else bool(b) for m, d, b in zip(mask, state._driven, comp.bypass,
                                                       strict=True)]
    comp.set_bypass(new)
    off = mask if prediction_off is None else prediction_off
    state._comp_off = [bool(o) if d else True for o, d in zip(off, state._driven, strict=True)]
    _set_bypass_flags(state)
    _set_pred_wanted(state)
    return [a for a, b in zip(AXES, comp.bypass, strict=True) if b]


def prediction_status(state: TickState) -> dict[str, dict[str, object]]:
    """Per axis with a prediction: ``state`` -- ``predicting``, ``fallback`` (the band monitor
    holds it off), ``held`` (wanted, but the input is lost -- stale, parking -- or not yet
    calm for ``resume_after_s`` after a start, a resume or a fallback) or ``off`` (``predict =
    false``, or compensation turned off) --, the prediction's share ``weight`` (0-1), the
    monitor's ``ratio`` and the count of ``fallbacks`` it caused."""
    pred = state.pred
    on = pred.predicting()
    fallen = pred.fallen_back()
    out: dict[str, dict[str, object]] = {}
    for i in pred.idx:
        if not state._pred_wanted[i]:
            what = "off"
        else:
            what = "predicting" if on[i] else "fallback" if fallen[i] else "held"
        out[AXES[i]] = {"state": what, "weight": pred.weight[i], "ratio": pred.ratio[i],
                        "fallbacks": pred.fallbacks[i]}
    return out


def _set_bypass_flags(state: TickState) -> None:
    state.bypass_flags = [_BYPASS_FLAGS[i] for i, (b, d) in enumerate(zip(
        state.comp.bypass, state._driven, strict=True)) if b and d]
    state.nopredict_flags = [_NOPREDICT_FLAGS[i] for i, p in enumerate(state.pred.params)
                             if p is not None and state._driven[i] and state._comp_off[i]]


def warm_start(state: TickState, p: TickParams, position: Sequence[float]) -> None:
    """Start mid-run (a replay of a recording that begins after the service started): the
    compensator at rest at ``position``, and each wanted prediction predicting, its prefilter
    at rest there -- as near to the service's state as a recording tells."""
    state.comp.reset(position)  # no window: the next tick opens one if the input is not live
    state._windowed = False
    state.guard.reset(position)
    _sync_prediction(state, p)
    state._ref = [float(x) for x in position]
    state.pred.warm(state._ref, state._pred_wanted)


def park(state: TickState, p: TickParams, now_ns: int) -> None:
    """Stop requested: ramp every axis to neutral from the next tick on, ignoring input."""
    state.shaper.park(p.shaper, now_ns / 1e9)


def is_parked(state: TickState) -> bool:
    """Parking requested and finished: the reference at neutral, the command at rest."""
    if not state.shaper.parked:
        return False
    st = state.comp.state()
    g = state.guard
    return bool(max(abs(x) for x in (*st.u, *g.u)) < 1e-6
                and max(abs(x) for x in (*st.v, *g.v)) < 1e-4)
