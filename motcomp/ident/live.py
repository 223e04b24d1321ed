"""An identification run through the running stack: ``motcomp identify --live``.

Steps, each on the real processes (the service must run with ``[admin] enabled = true``, and no
other motion source may publish meanwhile)::

    0  the host's probe: the service's own loop over ``probe_s`` (its status read twice); a
       service missing more than ``max_missed_share`` of its deadlines now would starve the
       run, whose identification is then refused: said before anything moves
    2  bypass the axis (compensation off, its prediction too): the platform receives the
       excitation itself
    3  record inputs, outputs, feedback and status (motcomp.record.recorder) to an MCAP file
    4  play the excitation (motcomp.ident.excitation, a multisine by default) on the service's
       input at 1 kHz on wall time, at a fraction of the axis' limits the limiter leaves alone
    5  restore the axis' previous mode (bypass off again if it was compensated), whatever
       happened in 3-4
    6  identify from the recording (the service's output in force against the feedback), over
       the window the excitation played in; the report counts the ticks the limiter acted on

Why a fraction of the limits (default 0.5): the excitation's samples meet the limits, but the
service reconstructs its input between frames (docs/WIRE.md) and a sender's timing jitter adds
acceleration of the order of the signal's own; at 0.9 of the limits the limiter acted on most
ticks, at 0.5 on none (docs/IDENTIFICATION.md).
"""

from __future__ import annotations

import gc
import logging
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from motcomp.core.axes import AXES
from motcomp.errors import DataError, ServiceError
from motcomp.ident.excitation import AxisRange, excitation
from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, open_session
from motcomp.progress import Progress
from motcomp.record.recorder import RecordOptions, record
from motcomp.record.session import DEFAULT_KEYS

__all__ = ["LiveOptions", "LiveRun", "probe_host", "run_live"]

log = logging.getLogger("motcomp.ident")


@dataclass
class LiveOptions:
    """What :func:`run_live` plays and records."""

    axis: str
    out: Path
    """The recording (MCAP)."""
    kind: str = "multisine"
    duration_s: float = 40.0
    usage: float = 0.5
    """Fraction of the tightest limit the excitation reaches."""
    band_hz: float | None = None
    seed: int = 0
    admin_key: str = "motcomp/admin"
    status_key: str = DEFAULT_KEYS["status"]
    input_key: str = DEFAULT_KEYS["input"]
    keys: list[str] = field(default_factory=lambda: list(DEFAULT_KEYS.values()))
    timeout_s: float = 3.0
    probe_s: float = 3.0
    """How long the service's loop is watched before the run (step 0)."""
    max_missed_share: float | None = 0.05
    """Step 0 refuses when the service misses more of its deadlines (None: no check)."""
    quiet: bool = False
    """No progress of the excitation on stderr (:class:`~motcomp.progress.Progress`)."""


@dataclass
class LiveRun:
    """What happened: the recording, the excitation's window and the limiter's activity."""

    path: Path
    window_unix_s: tuple[float, float]
    """Start and end of the excitation (wall clock, s since the epoch)."""
    was_bypassed: bool
    excitation: dict[str, Any]
    frames_sent: int
    frames_skipped: int = 0
    """Samples not sent: their instants passed while the sender was stalled (a busy host)."""


def _ask(session: Any, key: str, body: dict[str, Any] | None, timeout_s: float) -> Any:
    raw = first_reply(session, key, msgpack.packb(body) if body is not None else None,
                      timeout_s)
    return msgpack.unpackb(raw, raw=False)


def _pct(share: float | None) -> str:
    return "(unknown)" if share is None else f"{100 * share:.1f} %"


def _limits(status: dict[str, Any], axis: str) -> AxisRange:
    """The axis' limits from the config the service runs (its file), else the preset's."""
    from motcomp.config import load_config, resolve_axes

    path = (status.get("config") or {}).get("path")
    if isinstance(path, str) and Path(path).is_file():
        lim = resolve_axes(load_config(path)).limits
        i = AXES.index(axis)
        return AxisRange(float(lim.p_min[i]), float(lim.p_max[i]), float(lim.v_max[i]),
                         float(lim.a_max[i]))
    from motcomp.presets import load_preset

    lim = load_preset("rails" if axis.startswith("rails") else "hexapod").limits
    return AxisRange(float(lim.p_min[0]), float(lim.p_max[0]), float(lim.v_max[0]),
                     float(lim.a_max[0]))


def probe_host(first: dict[str, Any], second: dict[str, Any]) -> dict[str, float | None]:
    """The deadlines the service's loop (and the platform's, where its status says) missed
    between two of the service's status frames: ``{"service": share, "platform": share}``
    (None where unknown)."""
    out: dict[str, float | None] = {}
    for who, a, b in (("service", first, second),
                      ("platform", first.get("platform") or {}, second.get("platform") or {})):
        try:
            missed = float(b["missed_ticks"]) - float(a["missed_ticks"])
            ticks = float(b["ticks"]) - float(a["ticks"])
        except (KeyError, TypeError, ValueError):
            out[who] = None
            continue
        out[who] = missed / (missed + ticks) if missed + ticks > 0 else None
    return out


def run_live(opts: LiveOptions, endpoints: ZenohEndpoints) -> LiveRun:
    """Steps 0-5 of the module docstring; returns the recording to identify (step 6).

    Raises
    ------
    ServiceError
        If the service does not answer, does not drive the axis, or refuses the bypass.
    DataError
        If the host's probe (step 0) finds the service missing more than
        ``opts.max_missed_share`` of its deadlines: the message says what the host must give.
    """
    from motcomp.sim.source import Trajectory, publish

    def say(text: str) -> None:  # each step as it starts: nothing is silent for seconds
        if not opts.quiet:
            print(f"live: {text}", file=sys.stderr, flush=True)

    with open_session(endpoints) as session:
        status = _ask(session, opts.status_key, None, opts.timeout_s)
        if opts.max_missed_share is not None and opts.probe_s > 0:
            say(f"watching the service for {opts.probe_s:g} s before anything moves (it must "
                f"keep {100 * (1 - opts.max_missed_share):g} % of its deadlines)")
            time.sleep(opts.probe_s)
            later = _ask(session, opts.status_key, None, opts.timeout_s)
            shares = probe_host(status, later)
            service = shares["service"]
            log.info("host probe over %.1f s: the service missed %s of its deadlines, the "
                     "platform %s", opts.probe_s, _pct(service), _pct(shares["platform"]))
            if service is not None and service > opts.max_missed_share:
                raise DataError(
                    f"the service missed {100 * service:.1f} % of its deadlines over the last "
                    f"{opts.probe_s:g} s (the platform {_pct(shares['platform'])}), more than "
                    f"{100 * opts.max_missed_share:g} %: an identification run now would carry "
                    "the host's stalls and be refused, so nothing was excited.  The host must "
                    "give the service's loop its CPU: stop other work on it, or give the "
                    "service a core of its own and real-time priority (docs/DEPLOYMENT.md); "
                    "--force runs it anyway")
            status = later
        if opts.axis not in status.get("driven", []):
            raise ServiceError(f"the service does not drive {opts.axis} (driven: "
                               f"{', '.join(status.get('driven', [])) or 'none'})")
        pred = (status.get("prediction") or {}).get(opts.axis) or {}
        # compensation off: the PID bypassed and no prediction acting on the axis
        was_bypassed = (opts.axis in status.get("bypass", [])
                        and pred.get("state", "off") == "off")
        limits = _limits(status, opts.axis)
        exc = excitation(opts.kind, opts.axis, limits, duration_s=opts.duration_s,
                         band_hz=opts.band_hz, seed=opts.seed, usage=opts.usage)
        if not was_bypassed:
            reply = _ask(session, f"{opts.admin_key}/bypass", {"on": True, "axes": [opts.axis]},
                         opts.timeout_s)
            if not reply.get("ok"):
                from motcomp.cli.admin import NOT_NOW

                error = str(reply.get("error"))
                raise ServiceError(f"the service refused to bypass {opts.axis}: "
                                   f"{NOT_NOW.get(error, error)}")
            log.info("%s bypassed for the identification run", opts.axis)
        say(f"{opts.axis} bypassed (compensation off); recording to {opts.out}, then a "
            f"{opts.duration_s:g} s {opts.kind} at {opts.usage:g} of its limits")
        stop = threading.Event()
        rec_opts = RecordOptions(out=opts.out, keys=opts.keys, status_key=opts.status_key,
                                 status_timeout_s=opts.timeout_s)
        result: dict[str, Any] = {}

        def recorder() -> None:
            try:
                result["summary"] = record(rec_opts, endpoints, stop)
            except BaseException as e:  # reported below
                result["error"] = e

        thread = threading.Thread(target=recorder, name="motcomp-live-record", daemon=True)
        try:
            time.sleep(0.5)  # the bypass fade (loop.bypass_fade_s) before the recording
            thread.start()
            time.sleep(1.0)  # the recorder's subscriptions reach the peers
            traj = Trajectory(rate_hz=exc.rate_hz, pos={opts.axis: np.asarray(exc.cmd)})
            # the recorder's thread allocates a frame's objects at every message: the cyclic
            # collector's full pass then stalls this process, the excitation's sender, for
            # tens of ms (72 ms measured, at the same instant of every run), which the service
            # bridges by holding its input and the limiter catches up after -- ending the
            # fit's window there.  Nothing here makes cycles: the collector waits for the end
            gc.collect()
            gc.disable()
            try:
                t0 = time.time()
                with Progress(f"excitation on {opts.axis}", traj.duration_s, quiet=opts.quiet,
                              unit="s") as bar:
                    stats = publish(traj, endpoints, opts.input_key, wait_peer_s=opts.timeout_s,
                                    progress=bar.update)
                t1 = time.time()
            finally:
                gc.enable()
            # the recording says where the excitation lies: `identify FILE` finds it again
            rec_opts.extra_info.update(excitation_axis=opts.axis,
                                       excitation_window=f"{t0!r} {t1!r}")
            time.sleep(0.5)  # the platform's last response and its feedback
        finally:
            stop.set()
            thread.join(timeout=30)
            if not was_bypassed:
                reply = _ask(session, f"{opts.admin_key}/bypass",
                             {"on": False, "axes": [opts.axis]}, opts.timeout_s)
                if reply.get("ok"):
                    log.info("%s compensated again", opts.axis)
                else:
                    log.error("could not restore compensation on %s: %s", opts.axis,
                              reply.get("error"))
    if "error" in result:
        raise ServiceError(f"recording failed: {result['error']}") from result["error"]
    return LiveRun(opts.out, (t0, t1), was_bypassed, exc.summary(), stats.sent, stats.skipped)
