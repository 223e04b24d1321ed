"""``motcomp demo``: the whole system on one machine, no router, no hardware.

Starts three processes on loopback, each on its own port -- the simulated platform
(``motcomp hil``), the service (``motcomp run --config config/demo.toml``) and, twice, a motion
source (``motcomp source --signal demo``: a slalom on the rails' y axis, a 0.2-1 Hz sweep on
x, heave/roll/pitch on the hexapod) -- first with compensation off (bypass), then on, switched
live and bumplessly through the admin endpoint.  It records the setpoints and the platform's
feedback, and reports the apparent delay of each axis (cross-correlation, sub-sample) off vs on,
the saturation counts and the loop statistics, and writes a PNG of the traces.  The hexapod
stays bypassed in both phases: it is delay-dominated (Tp1/Td = 0.08) and the tuning rules
refuse it.

Delays use the frames' own timestamps (sample time of the setpoints, tick time of the platform
feedback), so the recorder's polling does not blur them.
"""

from __future__ import annotations

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

from motcomp.core.axes import AXES
from motcomp.core.quality import estimate_delay
from motcomp.errors import ServiceError
from motcomp.io.zenoh_io import (
    ZenohEndpoints,
    first_reply,
    free_tcp_port,
    loopback,
    open_session,
)
from motcomp.progress import Progress
from motcomp.resources import config_file

__all__ = ["DemoResult", "run_demo"]

RAILS = ("rails_x", "rails_y")
SIGNAL_OF = {"rails_y": "slalom, 18 m cones at 40 km/h", "rails_x": "sweep 0.2-1 Hz",
             "hex_z": "heave 0.5 Hz", "hex_roll": "roll 0.25 Hz", "hex_pitch": "pitch 0.35 Hz"}


@dataclass
class _Trace:
    t: list[float] = field(default_factory=list)
    pos: dict[str, list[float]] = field(default_factory=dict)

    def add(self, t: float, pos: dict[str, float]) -> None:
        self.t.append(t)
        for a, v in pos.items():
            self.pos.setdefault(a, []).append(v)

    def window(self, axis: str, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(self.t)
        v = np.asarray(self.pos.get(axis, [np.nan] * len(self.t)))
        sel = (t >= t0) & (t <= t1)
        return t[sel], v[sel]


@dataclass
class DemoResult:
    """What the demo measured (delays in s, per axis and phase)."""

    delays: dict[str, dict[str, float]]
    saturation: dict[str, dict[str, int]]
    """Ticks the service flagged saturated, per axis and phase."""
    stale: dict[str, int]
    """Stale-input episodes of the service (no valid frame for ``loop.stale_after_s``), per
    phase: each holds the reference, then blends back, which adds to the delay measured."""
    status: dict[str, Any]
    hil_status: dict[str, Any]
    exit_codes: dict[str, int]
    figure: Path | None
    phases: dict[str, tuple[float, float]]


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
            trace.add(float(frame["t"]), frame["pos"])
            count[0] += 1
        except (ValueError, KeyError, TypeError, msgpack.UnpackException):
            pass


def _resampled_delay(ref: _Trace, out: _Trace, axis: str, t0: float, t1: float) -> float:
    tr, r = ref.window(axis, t0, t1)
    to, y = out.window(axis, t0, t1)
    if tr.size < 100 or to.size < 100 or np.ptp(r) == 0:
        return float("nan")
    grid = np.arange(max(tr[0], to[0]), min(tr[-1], to[-1]), 1e-3)
    return estimate_delay(np.interp(grid, tr, r), np.interp(grid, to, y), 1000.0, max_lag_s=1.0)


def run_demo(out_dir: Path, quiet: bool = False, keep_logs: bool = True) -> DemoResult:
    """Run the demo (about 30 s) and return its measurements; see the module docstring."""
    import zenoh

    out_dir.mkdir(parents=True, exist_ok=True)
    logs = out_dir / "logs"
    logs.mkdir(exist_ok=True)
    p_hil, p_svc, p_me, p_src = (free_tcp_port() for _ in range(4))
    cfg = config_file("demo.toml")
    procs: dict[str, subprocess.Popen[bytes]] = {}
    say = (lambda m: None) if quiet else (lambda m: print(m, flush=True))
    setpoints, feedback = _Trace(), _Trace()
    counts = [0]
    phases: dict[str, tuple[float, float]] = {}
    saturation: dict[str, dict[str, int]] = {}
    stale: dict[str, int] = {}
    status: dict[str, Any] = {}
    hil_status: dict[str, Any] = {}
    say(f"motcomp demo: platform simulator on :{p_hil}, service on :{p_svc}, recorder on :{p_me}")
    try:
        procs["hil"] = _spawn(["hil", "-l", loopback(p_hil), "--log-level", "warning"],
                              logs / "hil.log")
        procs["service"] = _spawn(["run", "--config", str(cfg), "-l", loopback(p_svc), "-e",
                                   loopback(p_hil)], logs / "service.log")
        ep = ZenohEndpoints(connect=(loopback(p_hil), loopback(p_svc)), listen=(loopback(p_me),))
        with open_session(ep) as session:
            sub_sp = session.declare_subscriber("sim/motion/setpoint",
                                                zenoh.handlers.FifoChannel(200_000))
            sub_fb = session.declare_subscriber("platform/feedback",
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
            from motcomp.sim.source import builtin

            def counters() -> tuple[dict[str, int], int, bool]:
                """Saturation counts, stale episodes begun so far, stale now."""
                st = msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))
                return (dict(st.get("saturation", {})), int(st.get("stale_episodes", 0)),
                        st.get("mode") == "stale")

            duration = builtin("demo").duration_s
            seq = 0
            for phase, bypass in (("off", True), ("on", False)):
                admin("bypass", {"on": bypass, "axes": list(RAILS)})
                sat0, stale0, _ = counters()
                say(f"phase {phase}: compensation {'OFF (bypass)' if bypass else 'ON'} on the "
                    f"rails, {duration:.1f} s of motion")
                t0 = time.time()
                src = _spawn(["source", "--signal", "demo", "--seq-start", str(seq), "-e",
                              loopback(p_svc), "-e", loopback(p_me), "-l", loopback(p_src),
                              "--lead-in", "0.5"], logs / f"source-{phase}.log")
                with Progress(f"phase {phase}", duration + 2.0, quiet=quiet) as bar:
                    while src.poll() is None:
                        time.sleep(0.05)
                        _drain(sub_sp, setpoints, counts)
                        _drain(sub_fb, feedback, counts)
                        bar.update(time.time() - t0)
                    t_end = time.time() + 1.0
                    while time.time() < t_end:  # let the platform settle, keep recording
                        time.sleep(0.05)
                        _drain(sub_sp, setpoints, counts)
                        _drain(sub_fb, feedback, counts)
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
            for s in (sub_sp, sub_fb, sub_hs):
                s.undeclare()
    finally:
        for name in ("service", "hil"):
            p = procs.get(name)
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
        codes = {}
        for name, p in procs.items():
            try:
                codes[name] = p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                codes[name] = -9
    delays: dict[str, dict[str, float]] = {}
    axes = [a for a in AXES if a in setpoints.pos]
    for axis in axes:
        delays[axis] = {ph: _resampled_delay(setpoints, feedback, axis, *span)
                        for ph, span in phases.items()}
    fig = _figure(setpoints, feedback, phases, delays, out_dir / "demo.png")
    result = DemoResult(delays, saturation, stale, status, hil_status, codes, fig, phases)
    if not keep_logs:
        for f in logs.iterdir():
            f.unlink()
        logs.rmdir()
    return result


def report(res: DemoResult) -> str:
    """The table printed at the end of the demo."""
    lines = ["", "Apparent delay of the platform (setpoint -> feedback, cross-correlation):", "",
             f"{'axis':<10} {'motion':<32} {'off':>9} {'on':>9} {'gained':>9}  "
             "limited off / on", "-" * 90]
    bypassed = set(res.status.get("bypass", []))
    for axis, d in res.delays.items():
        off, on = d.get("off", float("nan")), d.get("on", float("nan"))
        note = "  (bypass: delay-dominated)" if axis in bypassed else ""
        sat = res.saturation.get(axis, {})
        lines.append(f"{axis:<10} {SIGNAL_OF.get(axis, ''):<32} {off * 1e3:7.1f}ms "
                     f"{on * 1e3:7.1f}ms {(off - on) * 1e3:7.1f}ms  "
                     f"{sat.get('off', 0):>6} / {sat.get('on', 0):<6}{note}")
    st = res.status
    loop = st.get("loop", {})
    fr = st.get("frames", {})
    lines += ["", "limited: ticks at which the service's limiter kept an axis' command within its "
                  "limits or away from the",
              "compensated target (flag sat:<axis>).  The compensator amplifies the high "
                  "frequencies of its input (up to 60x",
              "with the example tuning), so irregular input timing -- stalls and jitter of the "
                  "processes on a busy machine --",
              "reaches the acceleration limit; with evenly timed input there is none.",
              "", f"Service loop: {st.get('rate_hz', 0):g} Hz, {st.get('ticks', 0)} ticks, "
                  f"{st.get('missed_ticks', 0)} missed; tick compute p50 "
                  f"{loop.get('compute_p50_us', float('nan')):.0f} us, p99 "
                  f"{loop.get('compute_p99_us', float('nan')):.0f} us (whole tick with zenoh's "
                  f"calls p99 {loop.get('tick_p99_us', float('nan')):.0f} us); lateness p99.9 "
                  f"{loop.get('late_p999_us', float('nan')):.0f} us (last "
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


def _figure(sp: _Trace, fb: _Trace, phases: dict[str, tuple[float, float]],
            delays: dict[str, dict[str, float]], path: Path) -> Path | None:
    if not phases or not sp.t:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes = [a for a in ("rails_y", "rails_x", "hex_roll") if a in sp.pos]
    fig, grid = plt.subplots(len(axes), 2, figsize=(12, 3.2 * len(axes)), squeeze=False)
    for row, axis in enumerate(axes):
        for col, phase in enumerate(("off", "on")):
            if phase not in phases:
                continue
            ax = grid[row][col]
            t0, t1 = phases[phase]
            ts, r = sp.window(axis, t0, t1)
            tf, y = fb.window(axis, t0, t1)
            ax.plot(ts - t0, r, "k", lw=1.2, label="setpoint")
            d = delays.get(axis, {}).get(phase, float("nan"))
            ax.plot(tf - t0, y, "C1" if phase == "on" else "C0", lw=1,
                    label=f"platform ({d * 1e3:.0f} ms)")
            ax.set_title(f"{axis}: compensation {phase}")
            ax.set_xlabel("time (s)")
            ax.legend(loc="upper right", fontsize=8)
            ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


if __name__ == "__main__":  # pragma: no cover
    res = run_demo(Path(tempfile.mkdtemp()))
    print(report(res))
