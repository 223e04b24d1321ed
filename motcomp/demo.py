"""``motcomp demo``: the whole system on one machine, no router, no hardware.

Starts three processes on loopback, each on its own port -- the simulated platform
(``motcomp hil``), the service (``motcomp run --config config/demo.toml``) and, twice, a motion
source (``motcomp source --signal demo``: a slalom on the rails' y axis, a 0.2-1 Hz sweep on
x, heave/roll/pitch on the hexapod) -- first with compensation off (bypass), then on, switched
live and bumplessly through the admin endpoint.  It records the setpoints, the platform's
feedback and the command the service sends the platform (``platform/setpoint``, with its
``seq``), and reports per axis, off vs on: the apparent delay (cross-correlation, sub-sample);
the command's HF acceleration RMS above 5 Hz and jerk RMS
(:func:`motcomp.core.quality.command_quality`) and the share of ticks it sits at the acceleration
limit, each beside the same figure of the ideal run (:func:`motcomp.sim.ideal.ideal_run`: the
config's tick fed the same motion perfectly timed, offline -- the floor); the saturation counts
and the loop statistics.  The PNG shows, per rails axis, the positions, the command and its
acceleration against the limit.  A compensated command can chatter at the acceleration limit
while the positions look perfect (the platform's lag filters it): hence the command figures.
The hexapod is delay-dominated (Tp1/Td = 0.08): its PID stays bypassed in both phases, and its
axes are compensated by prediction instead (the config's ``prediction``,
:mod:`motcomp.core.predictor`), off in the first phase, on in the second: one admin call per
phase turns compensation off (PID and prediction) on every driven axis, then back on.

Delays use the frames' own timestamps (sample time of the setpoints, tick time of the platform
feedback), so the recorder's polling does not blur them.  Command figures cover the motion (from the
first setpoint of a phase, for the trajectory's duration) on the service's tick grid: an output
frame's ``t`` is its tick's deadline, so its grid index is exact (own-clock pacing, as in the demo
config), from :data:`STARTUP_S` into the motion, or from where the service reported every prefilter
at full weight if that came later.  Grid ticks without a frame -- lost (a gap in
``seq``) or never sent (a deadline the service missed) -- are counted and left out: the spectral
figures are taken over the stretches between them, the ideal run's over the same stretches
(:func:`command_quality_over`; a linear bridge would add the command's own acceleration at each
missing tick), and the acceleration-limit share counts only second differences of three recorded
frames.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from motcomp.cli.admin import waiting_text
from motcomp.config import ServiceConfig, load_config, resolve_axes
from motcomp.core.axes import AXES, AXIS_INDEX, unit
from motcomp.core.quality import (
    AT_LIMIT_FRACTION,
    HF_ABOVE_HZ,
    CommandQuality,
    at_acc_limit,
    command_quality_over,
    estimate_delay,
    stretches,
)
from motcomp.errors import ConfigError, ServiceError
from motcomp.io.zenoh_io import (
    ZenohEndpoints,
    first_reply,
    free_tcp_port,
    loopback,
    open_session,
)
from motcomp.progress import Progress
from motcomp.resources import config_file
from motcomp.runtime.probe import loop_kept_from_cpu
from motcomp.sim.ideal import IdealRun, ideal_run
from motcomp.sim.source import Trajectory, builtin

__all__ = ["PHASES", "RAILS", "CommandFigures", "DemoResult", "OutputFrames",
           "report", "run_demo", "stop_processes"]

RAILS = ("rails_x", "rails_y")
SIGNAL_OF = {"rails_y": "slalom, 18 m cones at 40 km/h", "rails_x": "sweep 0.2-1 Hz",
             "hex_z": "heave 0.5 Hz", "hex_roll": "roll 0.25 Hz", "hex_pitch": "pitch 0.35 Hz"}
PHASES = ("off", "on")


@dataclass
class _Trace:
    t: list[float] = field(default_factory=list)
    pos: dict[str, list[float]] = field(default_factory=dict)
    seq: list[int] = field(default_factory=list)
    sat: dict[str, list[float]] = field(default_factory=dict)
    """Per axis, the ``t`` of the frames flagged ``sat:<axis>`` (output frames)."""

    def add(self, t: float, pos: dict[str, float], seq: int = -1,
            flags: Any = ()) -> None:
        self.t.append(t)
        self.seq.append(seq)
        for a, v in pos.items():
            self.pos.setdefault(a, []).append(v)
        for f in flags if isinstance(flags, list) else ():
            if isinstance(f, str) and f.startswith("sat:"):
                self.sat.setdefault(f[4:], []).append(t)

    def flagged(self, axis: str, t0: float, t1: float) -> int:
        """Frames flagged ``sat:<axis>`` with ``t`` in ``[t0, t1]``."""
        t = np.asarray(self.sat.get(axis, []))
        return int(((t >= t0) & (t <= t1)).sum())

    def window(self, axis: str, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(self.t)
        v = np.asarray(self.pos.get(axis, [np.nan] * len(self.t)))
        sel = (t >= t0) & (t <= t1)
        return t[sel], v[sel]


@dataclass(frozen=True)
class CommandFigures:
    """The command of one axis over one phase's motion: live (recorded from the service's
    output) and in the ideal run (the floor).  Accelerations in the axis' unit per s^2, jerks
    per s^3; shares in [0, 1]."""

    live: CommandQuality
    ideal: CommandQuality
    at_limit: float
    """Share of the ticks whose |acceleration| is within 1 % of the axis' limit
    (:data:`motcomp.core.quality.AT_LIMIT_FRACTION`), counted on the recorded command."""
    ideal_at_limit: float
    """The same count on the ideal run's command."""
    ideal_acted: float
    """Share of the ticks on which the ideal run's limiter changed the command (any bound): the
    tick's own count, to check the command-side count against."""

    @property
    def hf_ratio(self) -> float:
        """HF acceleration RMS of the live command over the ideal run's (inf if that is 0)."""
        if self.ideal.hf_acc_rms > 0:
            return self.live.hf_acc_rms / self.ideal.hf_acc_rms
        return math.inf if self.live.hf_acc_rms > 0 else 1.0


@dataclass(frozen=True)
class OutputFrames:
    """The service's output frames over one phase's motion, on its tick grid."""

    ticks: int
    """Deadlines in the window."""
    recorded: int
    """Ticks whose frame was recorded."""
    lost: int
    """Frames sent but not recorded: the gaps in ``seq``."""
    unsent: int
    """Ticks without a frame nor a gap in ``seq``: deadlines the service missed."""


@dataclass
class DemoResult:
    """What the demo measured (delays in s, per axis and phase)."""

    delays: dict[str, dict[str, float]]
    saturation: dict[str, dict[str, int]]
    """Ticks the service flagged saturated, per axis and phase (its counters, the whole phase:
    the motion and the second after it, when the input stops)."""
    command: dict[str, dict[str, CommandFigures]]
    """The command's smoothness, live and ideal, per axis and phase."""
    frames: dict[str, OutputFrames]
    """The output frames over the motion, per phase."""
    acc_limit: dict[str, float]
    """The acceleration limit of each axis in the config (m/s^2 or rad/s^2)."""
    motion: dict[str, tuple[float, float]]
    """Per phase, the motion's span (wall time, s): first setpoint, plus the trajectory's
    duration; the command figures cover it."""
    stale: dict[str, int]
    """Stale-input episodes of the service (no valid frame for ``loop.stale_after_s``), per
    phase: each holds the reference, then blends back, which adds to the delay measured."""
    status: dict[str, Any]
    hil_status: dict[str, Any]
    exit_codes: dict[str, int]
    figure: Path | None
    phases: dict[str, tuple[float, float]]
    panels: tuple[str, ...] = ()
    """The figure's panels, ``"<axis> <quantity> (<unit>)"``, also written into the PNG's
    ``Description``."""
    figures_from: dict[str, float] = field(default_factory=dict)
    """Per phase, where the command figures start (s into the motion): :data:`STARTUP_S`, or
    later where the service's prefilters reached full weight later."""
    unmeasured: dict[str, str] = field(default_factory=dict)
    """Why a delay could not be measured, by ``"<axis> <phase>"`` (its delay is NaN)."""
    saturation_motion: dict[str, dict[str, int]] = field(default_factory=dict)
    """Of :attr:`saturation`, the recorded output frames flagged over the motion."""
    saturation_stop: dict[str, dict[str, int]] = field(default_factory=dict)
    """The recorded output frames flagged after the motion, as its input stopped."""


def stop_text(res: DemoResult) -> str:
    """The saturation flags after each phase's motion, when its input stopped (recorded
    output frames)."""
    after = {a: per for a, per in res.saturation_stop.items() if any(per.values())}
    if not after:
        return ""
    counts = ", ".join(f"{a} " + " / ".join(str(per.get(ph, 0)) for ph in PHASES)
                       for a, per in after.items())
    return ("  After the motion, as the input stopped (recorded frames, "
            f"{' / '.join(PHASES)}): {counts}: the input lost, a compensated axis returns to "
            "the held reference, at its acceleration limit for a few ticks where its command "
            "was off that reference (docs/DEPLOYMENT.md, \"What happens when the input stops\").")


def _spawn(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    fh = log.open("wb")
    return subprocess.Popen([sys.executable, "-m", "motcomp", *args], stdout=fh,
                            stderr=subprocess.STDOUT, env=env)


def _drain(sub: Any, trace: _Trace, count: list[int]) -> None:
    while (s := sub.try_recv()) is not None:
        try:
            frame = msgpack.unpackb(s.payload.to_bytes())
            trace.add(float(frame["t"]), frame["pos"], int(frame.get("seq", -1)),
                      frame.get("flags", ()))
            count[0] += 1
        except (ValueError, KeyError, TypeError, msgpack.UnpackException):
            pass


def _resampled_delay(ref: _Trace, out: _Trace, axis: str, t0: float, t1: float
                     ) -> tuple[float, str]:
    """The apparent delay of ``axis`` over ``[t0, t1]`` (s), or NaN and why it was not
    measured."""
    tr, r = ref.window(axis, t0, t1)
    to, y = out.window(axis, t0, t1)
    if tr.size < 100 or to.size < 100 or np.ptp(r) == 0:
        return float("nan"), "too few samples of the motion or of the feedback"
    grid = np.arange(max(tr[0], to[0]), min(tr[-1], to[-1]), 1e-3)
    try:
        return estimate_delay(np.interp(grid, tr, r), np.interp(grid, to, y), 1000.0,
                              max_lag_s=1.0), ""
    except ConfigError as exc:  # the feedback does not follow the motion within the lags
        return float("nan"), str(exc)


@dataclass
class _Command:
    """The recorded command of one phase's motion on the service's tick grid."""

    t: np.ndarray
    """Grid instants (wall time, s)."""
    u: dict[str, np.ndarray]
    """Per axis; ticks without a frame bridged linearly."""
    have: np.ndarray
    """Whether a frame was recorded for each tick."""
    frames: OutputFrames


def _command_grid(cmd: _Trace, t_start: float, n: int, rate_hz: float) -> _Command | None:
    """The ``n`` ticks of the command from the first tick at or after ``t_start``; None if no
    frame falls in that window (see the module docstring)."""
    t = np.asarray(cmd.t)
    after = np.flatnonzero(t >= t_start - 0.5 / rate_hz)
    if after.size == 0:
        return None
    t0 = float(t[after[0]])
    k = np.rint((t - t0) * rate_hz).astype(np.int64)
    sel = (k >= 0) & (k < n)
    if not sel.any():
        return None
    ks = k[sel]
    have = np.zeros(n, dtype=bool)
    have[ks] = True
    idx = np.flatnonzero(have)
    ds = np.diff(np.asarray(cmd.seq)[sel])
    lost = int(np.clip(ds - 1, 0, None).sum())
    holes = n - idx.size
    frames = OutputFrames(n, int(idx.size), lost, max(0, holes - lost))
    u: dict[str, np.ndarray] = {}
    grid = np.arange(n)
    for axis, values in cmd.pos.items():
        col = np.full(n, np.nan)
        col[ks] = np.asarray(values)[sel]  # (a repeated tick: the last frame wins)
        u[axis] = np.interp(grid, idx, col[idx])
    return _Command(t0 + grid / rate_hz, u, have, frames)


def stop_processes(procs: dict[str, subprocess.Popen[bytes]]) -> dict[str, int]:
    """SIGTERM to every process still running (the service parks), then their exit codes; one
    that does not exit within 30 s is killed (-9)."""
    for p in procs.values():
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    codes = {}
    for name, p in procs.items():
        try:
            codes[name] = p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
            codes[name] = -9
    return codes


def _acceleration(u: np.ndarray, rate_hz: float) -> np.ndarray:
    """Second difference of a command on the tick grid (unit/s^2), as the limiter bounds it:
    ``acc[k]`` belongs to tick ``k + 2``."""
    return np.diff(u, 2) * rate_hz ** 2


def _at_limit_share(u: np.ndarray, rate_hz: float, a_max: float,
                    have: np.ndarray | None = None) -> float:
    """Share of the ticks at the acceleration limit (:func:`~motcomp.core.quality.at_acc_limit`),
    over the ticks whose difference stencil has three recorded frames."""
    at = at_acc_limit(u, rate_hz, a_max)
    ok = np.ones(at.size, dtype=bool) if have is None else have[:-2] & have[1:-1] & have[2:]
    if not ok.any():
        return float("nan")
    return float(np.mean(at[ok]))


def _phase_config(cfg: ServiceConfig, off: bool) -> ServiceConfig:
    """``cfg`` as the demo's admin call sets it in a phase: compensation off (``off``: every
    axis bypassed, prediction off) or the config's own."""
    if not off:
        return cfg
    axes = {a: ax.model_copy(update={"bypass": True, "predict": False})
            for a, ax in cfg.axes.items()}
    return cfg.model_copy(update={"axes": axes})


STARTUP_S = 1.5
"""The command figures leave out at least each phase's first seconds: the service blends from the
held reference to the new input (``loop.rejoin_s``) and fades the prefilters back in
(``prediction.resume_after_s``, ``fade_in_s``) -- and, where a phase uses prediction, they start
only once the service reports every prefilter at full weight (:func:`_full_weight`): the
monitor's calm time follows the live input, so the fade's instant varies from run to run."""
IDEAL_GAP_S = 1.0
"""The ideal run of the compensated phase starts after a stale gap this long (the live phase
follows the first one: its motion rejoins a held reference, then prediction fades in)."""
STATUS_POLL_S = 0.2
"""The demo asks the service's status this often during a phase (prefilter weights)."""


def _full_weight(status: dict[str, Any]) -> bool:
    """Every prefilter the service uses is predicting at full weight (False: none in use)."""
    pred = [v for v in (status.get("prediction") or {}).values()
            if isinstance(v, dict) and v.get("state") != "off"]
    return bool(pred) and all(v.get("state") == "predicting" and v.get("weight", 0) >= 1.0
                              for v in pred)


def _ideal_runs(cfg: ServiceConfig, traj: Trajectory) -> dict[str, IdealRun]:
    """The ideal run of each phase: the demo's motion, perfectly timed, through the config's
    tick with the phase's bypass."""
    return {ph: ideal_run(_phase_config(cfg, ph == "off"), traj.pos, traj.rate_hz,
                          gap_s=0.0 if ph == "off" else IDEAL_GAP_S)
            for ph in PHASES}


def _command_figures(grid: _Command, ideal: IdealRun, axis: str, a_max: float,
                     start_s: float = STARTUP_S) -> CommandFigures:
    rate = ideal.rate_hz
    n = min(grid.have.size, ideal.u[axis].size)
    u_live, u_ideal = grid.u[axis][:n], ideal.u[axis][:n]
    have = grid.have[:n].copy()
    have[:round(start_s * rate)] = False  # the phase's start-up (STARTUP_S)
    parts = stretches(have)  # the recorded ticks, the ideal over the same ones
    return CommandFigures(
        live=command_quality_over(u_live, parts, rate, HF_ABOVE_HZ),
        ideal=command_quality_over(u_ideal, parts, rate, HF_ABOVE_HZ),
        at_limit=_at_limit_share(u_live, rate, a_max, have),
        ideal_at_limit=_at_limit_share(u_ideal, rate, a_max),
        ideal_acted=float(np.mean(ideal.acted[axis][:n])))


def run_demo(out_dir: Path, quiet: bool = False, keep_logs: bool = True) -> DemoResult:
    """Run the demo (about 35 s) and return its measurements; see the module docstring."""
    import zenoh

    out_dir.mkdir(parents=True, exist_ok=True)
    logs = out_dir / "logs"
    logs.mkdir(exist_ok=True)
    p_hil, p_svc, p_me, p_src = (free_tcp_port() for _ in range(4))
    cfg_path = config_file("demo.toml")
    cfg = load_config(cfg_path)
    traj = builtin("demo")
    procs: dict[str, subprocess.Popen[bytes]] = {}
    say = (lambda m: None) if quiet else (lambda m: print(m, flush=True))
    setpoints, feedback, commands = _Trace(), _Trace(), _Trace()
    counts = [0]
    phases: dict[str, tuple[float, float]] = {}
    saturation: dict[str, dict[str, int]] = {}
    stale: dict[str, int] = {}
    faded: dict[str, float] = {}  # per phase: first status with every prefilter at full weight
    status: dict[str, Any] = {}
    hil_status: dict[str, Any] = {}
    say(f"motcomp demo: platform simulator on :{p_hil}, service on :{p_svc}, recorder on :{p_me}")
    try:
        procs["hil"] = _spawn(["hil", "-l", loopback(p_hil)], logs / "hil.log")
        procs["service"] = _spawn(["run", "--config", str(cfg_path), "-l", loopback(p_svc), "-e",
                                   loopback(p_hil)], logs / "service.log")
        ep = ZenohEndpoints(connect=(loopback(p_hil), loopback(p_svc)), listen=(loopback(p_me),))
        with open_session(ep) as session:
            sub_sp = session.declare_subscriber(cfg.input.key,
                                                zenoh.handlers.FifoChannel(200_000))
            sub_fb = session.declare_subscriber(cfg.feedback.key,
                                                zenoh.handlers.FifoChannel(200_000))
            sub_out = session.declare_subscriber(cfg.output.key,
                                                 zenoh.handlers.FifoChannel(200_000))
            sub_hs = session.declare_subscriber("platform/status", zenoh.handlers.RingChannel(1))

            def admin(cmd: str, body: dict[str, Any]) -> dict[str, Any]:
                out: dict[str, Any] = msgpack.unpackb(first_reply(
                    session, f"motcomp/admin/{cmd}", msgpack.packb(body), 3.0))
                if not out.get("ok"):
                    raise ServiceError(f"admin {cmd}: {out.get('error')}")
                return out

            def wait_ready(timeout: float = 30.0) -> None:
                t_end = time.monotonic() + timeout
                while time.monotonic() < t_end:
                    for name, p in procs.items():
                        if p.poll() is not None:
                            raise ServiceError(f"{name} exited with {p.returncode}; see "
                                               f"{logs / (name + '.log')}")
                    try:
                        st = msgpack.unpackb(first_reply(session, "motcomp/status", None, 1.0))
                        if st.get("ticks", 0) > 0 and sub_fb.try_recv() is not None:
                            return
                    except Exception:  # not up yet
                        pass
                    time.sleep(0.2)
                raise ServiceError(f"service or platform not ready within {timeout:.0f} s")

            wait_ready()

            def counters() -> tuple[dict[str, int], int, bool]:
                """Saturation counts, stale episodes begun so far, stale now."""
                st = msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))
                return (dict(st.get("saturation", {})), int(st.get("stale_episodes", 0)),
                        st.get("mode") == "stale")

            duration = traj.duration_s

            def drain() -> None:
                _drain(sub_sp, setpoints, counts)
                _drain(sub_fb, feedback, counts)
                _drain(sub_out, commands, counts)

            seq = 0
            for phase in PHASES:
                bypass = phase == "off"
                admin("bypass", {"on": bypass})  # every driven axis / those compensated
                sat0, stale0, _ = counters()
                say(f"phase {phase}: compensation {'OFF (bypass)' if bypass else 'ON'} "
                    f"(rails: PID; hexapod: prediction), {duration:.1f} s of motion "
                    f"({duration + 2.0:.1f} s with the source's start and the platform settling)")
                t0 = time.time()
                src = _spawn(["source", "--signal", "demo", "--seq-start", str(seq), "-e",
                              loopback(p_svc), "-e", loopback(p_me), "-l", loopback(p_src),
                              "--lead-in", "0.5"], logs / f"source-{phase}.log")
                with Progress(f"phase {phase}", duration + 2.0, quiet=quiet, unit="s") as bar:
                    polled = 0.0
                    while src.poll() is None:
                        time.sleep(0.05)
                        drain()
                        bar.update(time.time() - t0)
                        if phase not in faded and time.monotonic() - polled >= STATUS_POLL_S:
                            polled = time.monotonic()
                            with contextlib.suppress(Exception):  # a late reply: next poll
                                if _full_weight(msgpack.unpackb(first_reply(
                                        session, "motcomp/status", None, 0.5))):
                                    faded[phase] = time.time()
                    t_end = time.time() + 1.0
                    while time.time() < t_end:  # let the platform settle, keep recording
                        time.sleep(0.05)
                        drain()
                        bar.update(time.time() - t0)
                if src.returncode != 0:
                    raise ServiceError(f"motion source failed; see {logs}/source-{phase}.log")
                phases[phase] = (t0, time.time())
                sat1, stale1, stale_now = counters()
                for axis, n in sat1.items():
                    saturation.setdefault(axis, {})[phase] = n - sat0.get(axis, 0)
                # (the input goes stale once the source has stopped: not during the motion)
                stale[phase] = stale1 - stale0 - stale_now
                seq += round(duration * 1000) + 1
            status = msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))
            hs = sub_hs.try_recv()
            hil_status = msgpack.unpackb(hs.payload.to_bytes()) if hs is not None else {}
            for s in (sub_sp, sub_fb, sub_out, sub_hs):
                s.undeclare()
    finally:
        codes = stop_processes(procs)
    delays: dict[str, dict[str, float]] = {}
    unmeasured: dict[str, str] = {}
    axes = [a for a in AXES if a in setpoints.pos]
    for axis in axes:
        delays[axis] = {}
        for ph, span in phases.items():
            delays[axis][ph], why = _resampled_delay(setpoints, feedback, axis, *span)
            if why:
                unmeasured[f"{axis} {ph}"] = why
    say("ideal runs (the config's tick fed the same motion perfectly timed, offline)")
    ideal = _ideal_runs(cfg, traj)
    limits = resolve_axes(cfg).limits
    acc_limit = {a: float(limits.a_max[AXIS_INDEX[a]]) for a in axes}
    n_ticks = ideal["off"].t.size
    motion: dict[str, tuple[float, float]] = {}
    grids: dict[str, _Command] = {}
    for ph, (t0, t1) in phases.items():
        ts = np.asarray(setpoints.t)
        inside = ts[(ts >= t0) & (ts <= t1)]
        if inside.size == 0:
            continue
        motion[ph] = (float(inside[0]), float(inside[0]) + traj.duration_s)
        grid = _command_grid(commands, motion[ph][0], n_ticks, cfg.loop.rate_hz)
        if grid is not None:
            grids[ph] = grid
    figures_from = {ph: max(STARTUP_S, faded[ph] - motion[ph][0] if ph in faded else 0.0)
                    for ph in grids}
    command = {axis: {ph: _command_figures(grids[ph], ideal[ph], axis, acc_limit[axis],
                                           figures_from[ph])
                      for ph in grids} for axis in axes}
    frames = {ph: g.frames for ph, g in grids.items()}
    fig, panels = _figure(setpoints, feedback, grids, ideal, motion, delays, acc_limit, command,
                          out_dir / "demo.png")
    saturation_motion = {axis: {ph: commands.flagged(axis, *motion[ph]) for ph in motion}
                         for axis in axes}
    saturation_stop = {axis: {ph: commands.flagged(axis, math.nextafter(motion[ph][1], math.inf),
                                                   phases[ph][1]) for ph in motion}
                       for axis in axes}
    result = DemoResult(delays, saturation, command, frames, acc_limit, motion, stale, status,
                        hil_status, codes, fig, phases, panels, figures_from, unmeasured,
                        saturation_motion, saturation_stop)
    if not keep_logs:
        for f in logs.iterdir():
            f.unlink()
        logs.rmdir()
    return result


def _g(x: float) -> str:
    if not math.isfinite(x):
        return "n/a"
    return f"{x:.0f}" if abs(x) >= 1000 else f"{x:.3g}"


def _ratio(x: float) -> str:
    if math.isnan(x):
        return "n/a"
    return f"{x:.1f}" if x < 1000 else ">999"


def _ms(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{x * 1e3:5.1f}ms"


def _pct(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{100 * x:.2f}"


def report(res: DemoResult) -> str:
    """The table printed at the end of the demo."""
    nan = float("nan")
    lines = ["", *_wrap("Per axis, compensation off and on: the apparent delay of the platform "
                        "(setpoint -> feedback), and the command it receives (platform/setpoint), "
                        "live and in the ideal run (the config's tick fed the same motion "
                        "perfectly timed, offline: the floor).  [u]: the axis' unit.", indent=""),
             "",
             f"{'':<39}{'HF acc RMS >5 Hz':^24}  {'jerk RMS':^15}  {'at acc limit [%]':^17}  "
             f"{'sat':>5}",
             f"{'':<39}{'[u/s^2]':^24}  {'[u/s^3]':^15}  {'from the command*':^17}  "
             f"{'flags':>5}",
             f"{'axis [u]':<15} {'phase':<5} {'delay':>7} {'gained':>7}  {'live':>8} {'ideal':>8} "
             f"{'ratio':>6}  {'live':>7} {'ideal':>7}  {'live':>8} {'ideal':>8}  {'':>5}",
             "-" * _WIDTH]
    for axis, d in res.delays.items():
        for ph in PHASES:
            delay = d.get(ph, nan)
            gained = _ms(d.get("off", nan) - delay) if ph == "on" else ""
            c = res.command.get(axis, {}).get(ph)
            live_hf = ideal_hf = ratio = live_j = ideal_j = at = ideal_at = nan
            if c is not None:
                live_hf, ideal_hf, ratio = c.live.hf_acc_rms, c.ideal.hf_acc_rms, c.hf_ratio
                live_j, ideal_j = c.live.jerk_rms, c.ideal.jerk_rms
                at, ideal_at = c.at_limit, c.ideal_at_limit
            name = f"{axis} [{unit(axis)}]" if ph == PHASES[0] else ""
            lines.append(
                f"{name:<15} {ph:<5} {_ms(delay):>7} {gained:>7}  {_g(live_hf):>8} "
                f"{_g(ideal_hf):>8} {_ratio(ratio):>6}  {_g(live_j):>7} {_g(ideal_j):>7}  "
                f"{_pct(at):>8} {_pct(ideal_at):>8}  "
                f"{res.saturation_motion.get(axis, {}).get(ph, 0):>5}")
    for key, why in res.unmeasured.items():
        lines.extend(_wrap(f"{key}: delay not measured ({why})."))
    starved = loop_kept_from_cpu(res.status)
    if starved:
        lines.extend(_wrap(f"NOT A QUIET HOST'S FIGURES: {starved}.  The delays and the "
                           "command's figures above carry those stalls; the README's are a "
                           "host's that holds the rate (docs/DEPLOYMENT.md, \"Missed "
                           "deadlines\")."))
    predicted = [a for a in res.delays if a in (res.status.get("prediction") or {})]
    bypassed = set(res.status.get("bypass") or [])
    alone = [a for a in predicted if a in bypassed]
    series = [a for a in predicted if a not in bypassed]
    how = "".join([f"  {', '.join(series)}: the PID with a predictive prefilter in series."
                   if series else "",
                   f"  {', '.join(alone)}: compensated by prediction alone (PID bypassed: "
                   "delay-dominated)." if alone else ""])
    motions = "; ".join(f"{a} {SIGNAL_OF[a]}" for a in res.delays if a in SIGNAL_OF)
    limits = ", ".join(f"{a} {v:g} {unit(a)}/s^2" for a, v in res.acc_limit.items())
    acted = ", ".join(f"{a} {_pct(c['on'].ideal_acted)} %" for a, c in res.command.items()
                      if a in RAILS and "on" in c)
    st = res.status
    loop = st.get("loop", {})
    fr = st.get("frames", {})
    out = [res.frames.get(ph) for ph in PHASES]

    start = " / ".join(f"{res.figures_from[ph]:.1f}" if ph in res.figures_from else "n/a"
                       for ph in PHASES)

    def per_phase(attr: str) -> str:
        return " / ".join(str(getattr(f, attr)) if f is not None else "n/a" for f in out)

    lines += ["", *_wrap(f"motion: {motions}."),
              *_wrap("delay: setpoint -> feedback by cross-correlation (sub-sample); gained: "
                     "off - on." + how),
              *_wrap(f"HF acc, jerk: RMS of the command's acceleration above {HF_ABOVE_HZ:g} Hz "
                     "and of its jerk (motcomp.core.quality.command_quality) over the motion "
                     f"from {start} s in, off / on (the phase's start-up: the rejoin blend, and "
                     "with prediction until the service reported every prefilter at full "
                     "weight), on the service's tick grid; ratio: live HF acc over the ideal "
                     f"run's (the compensated one starting after a {IDEAL_GAP_S:g} s stale gap, "
                     "as the live phase does)."),
              *_wrap(f"* at acc limit: share of the ticks whose |acceleration| (second difference "
                     f"of the command) is within {100 * (1 - AT_LIMIT_FRACTION):g} % of the "
                     f"axis' limit ({limits}): counted from the command, not from the output "
                     "flags, which mark the saturation verdict below rather than each tick the "
                     "acceleration bound acts."
                     + (f"  The ideal run's limiter acted on (any bound, compensation on): "
                        f"{acted}." if acted else "")),
              *_wrap("sat flags: ticks at which the service's limiter kept an axis' command "
                     "within its limits or away from the compensated target (flag sat:<axis>), "
                     "over the motion, from the recorded output frames.  The compensator "
                     "amplifies the high frequencies of its input (20x above 10 Hz on the "
                     "example rails), so irregular input timing -- stalls and jitter of the "
                     "processes on a busy machine -- reaches the acceleration limit: the ideal "
                     "columns show what evenly timed input gives." + stop_text(res)),
              *_wrap(f"Command frames over the motion, off / on: {per_phase('ticks')} ticks, "
                     f"{per_phase('recorded')} recorded, {per_phase('lost')} lost (gaps in seq), "
                     f"{per_phase('unsent')} not sent (missed deadlines); the spectral figures "
                     "are taken over the stretches between them, live and ideal alike, the "
                     "acceleration-limit share leaves them out."),
              "", f"Service loop: {st.get('rate_hz', 0):g} Hz, {st.get('ticks', 0)} ticks, "
                  f"{st.get('missed_ticks', 0)} missed{waiting_text(st)}; tick compute p50 "
                  f"{loop.get('compute_p50_us', nan):.0f} us, p99 "
                  f"{loop.get('compute_p99_us', nan):.0f} us (whole tick with zenoh's "
                  f"calls p99 {loop.get('tick_p99_us', nan):.0f} us); lateness p99.9 "
                  f"{loop.get('late_p999_us', nan):.0f} us (last "
                  f"{st.get('loop_window_s', 10):g} s)",
              f"Input frames: {fr.get('received', 0)} received, {fr.get('accepted', 0)} accepted,"
              f" {fr.get('rejected', 0)} rejected; stale-input episodes off / on: "
              f"{res.stale.get('off', 0)} / {res.stale.get('on', 0)}"
              + (" (each holds the reference, then blends back: the delay of that phase "
                 "includes it)" if any(res.stale.values()) else ""),
              f"Platform hard-limit violations: "
              f"{sum(res.hil_status.get('violations', {}).values())}",
              f"Exit codes: {res.exit_codes}"]
    if res.figure is not None:
        lines.append(f"Traces: {res.figure}")
    return "\n".join(lines)


_WIDTH = 106
"""Width of the report's table."""


def _wrap(text: str, width: int = _WIDTH, indent: str = "  ") -> list[str]:
    import textwrap

    return textwrap.wrap(text, width, subsequent_indent=indent)


def _figure(sp: _Trace, fb: _Trace, grids: dict[str, _Command], ideal: dict[str, IdealRun],
            motion: dict[str, tuple[float, float]], delays: dict[str, dict[str, float]],
            acc_limit: dict[str, float], command: dict[str, dict[str, CommandFigures]],
            path: Path) -> tuple[Path | None, tuple[str, ...]]:
    """Per rails axis (a column): positions, the command, its acceleration against the limit;
    a last row of hexapod positions.  Time from each phase's first setpoint, so the phases
    overlay.  Returns the path and the panels' names (also in the PNG's ``Description``)."""
    if not motion or not sp.t:
        return None, ()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rails: list[str] = [a for a in ("rails_y", "rails_x") if a in sp.pos]
    hexa: list[str] = [a for a in SIGNAL_OF if a.startswith("hex_") and a in sp.pos]
    rows = (3 if rails else 0) + (1 if hexa else 0)
    # a grid of len(rails) x len(hexa) columns: each rails panel spans len(hexa) of them, each
    # hexapod panel len(rails), so both rows fill the figure's width
    n_r, n_h = max(len(rails), 1), max(len(hexa), 1)
    fig = plt.figure(figsize=(max(7.5 * len(rails), 5.0 * len(hexa), 7.5), 3.1 * rows))
    gs = fig.add_gridspec(rows, n_r * n_h)
    grid = [[fig.add_subplot(gs[r, c * n_h:(c + 1) * n_h]) for c in range(len(rails))]
            for r in range(3 if rails else 0)]
    hex_row = [fig.add_subplot(gs[rows - 1, c * n_r:(c + 1) * n_r]) for c in range(len(hexa))]
    color = {"off": "C0", "on": "C3"}
    span = max(m[1] - m[0] for m in motion.values())
    panels: list[str] = []

    def finish(ax: Any, axis: str, what: str, ylabel: str, title: str) -> None:
        ax.set_title(f"{axis}: {title}", fontsize=10)
        ax.set_xlabel("time from the motion's start (s)")
        ax.set_ylabel(ylabel)
        ax.set_xlim(-0.5, span + 1.0)
        lo, hi = ax.get_ylim()
        ax.set_ylim(lo, hi + 0.3 * (hi - lo))  # room for the legend above the traces
        labels = ax.get_legend_handles_labels()[1]
        ax.legend(loc="upper center", fontsize=7.5, framealpha=0.9,
                  ncol=len(labels) if sum(map(len, labels)) < 90 else 2)
        ax.grid(True, alpha=0.3)
        panels.append(f"{axis} {what} ({ylabel.split('(')[-1].rstrip(')')})")

    def positions(ax: Any, axis: str) -> None:
        ph0 = next(iter(motion))
        ts, r = sp.window(axis, *_phase_span(motion[ph0]))
        ax.plot(ts - motion[ph0][0], r, "k", lw=1.4, label="setpoint")
        for ph, (m0, m1) in motion.items():
            tf, y = fb.window(axis, *_phase_span((m0, m1)))
            d = delays.get(axis, {}).get(ph, float("nan"))
            lag = f"{round(d * 1e3) + 0:d} ms" if math.isfinite(d) else "delay not measured"
            ax.plot(tf - m0, y, color[ph], lw=1, label=f"platform, {ph} ({lag})")
        finish(ax, axis, "position", f"position ({unit(axis)})",
               "setpoint and platform feedback")

    for col, axis in enumerate(rails):
        u_unit = unit(axis)
        positions(grid[0][col], axis)
        ax = grid[1][col]
        for ph, g in grids.items():
            ax.plot(g.t - motion[ph][0], g.u[axis], color[ph], lw=1, label=f"command, {ph}")
        finish(ax, axis, "command", f"command ({u_unit})", "command sent to the platform")
        ax = grid[2][col]
        for ph in ("on", "off"):
            if ph not in grids:
                continue
            g = grids[ph]
            acc = _acceleration(g.u[axis], ideal[ph].rate_hz)
            acc[~(g.have[:-2] & g.have[1:-1] & g.have[2:])] = np.nan
            c = command.get(axis, {}).get(ph)
            share = f" ({100 * c.at_limit:.1f} % at limit)" if c is not None else ""
            ax.plot(g.t[2:] - motion[ph][0], acc, color[ph], lw=0.6 if ph == "on" else 1.0,
                    label=f"command, {ph}{share}")
        if "on" in ideal:
            run = ideal["on"]
            ax.plot(run.t[2:], _acceleration(run.u[axis], run.rate_hz), "0.15", lw=1.0,
                    label="ideal run, on (floor)")
        a_max = acc_limit[axis]
        for sign in (1, -1):
            ax.axhline(sign * a_max, color="k", ls="--", lw=1,
                       label=f"limit \u00b1{a_max:g} {u_unit}/s^2" if sign > 0 else None)
        ax.set_ylim(-1.2 * a_max, 1.2 * a_max)
        finish(ax, axis, "acceleration", f"acceleration ({u_unit}/s^2)",
               "command acceleration (second difference on the tick grid)")
    for col, axis in enumerate(hexa):
        positions(hex_row[col], axis)
    fig.tight_layout()
    fig.savefig(path, dpi=100, metadata={"Description": "; ".join(panels)})
    plt.close(fig)
    return path, tuple(panels)


def _phase_span(m: tuple[float, float]) -> tuple[float, float]:
    """The window drawn around a phase's motion (s, wall time)."""
    return m[0] - 0.5, m[1] + 1.0


if __name__ == "__main__":  # pragma: no cover
    res = run_demo(Path(tempfile.mkdtemp()))
    print(report(res))
