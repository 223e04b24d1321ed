"""Benchmark: what the platform receives from realistic input streams, over real zenoh.

For each sender (rate, timing jitter, stalls, with or without ``t``), signal (slalom, bandsweep,
lanechange) and mode (compensation on = the config as is; bypass = every driven axis bypassed,
a config copy with ``bypass = true`` on each), three processes run on loopback as in
``motcomp demo`` (free ports, multicast scouting off): ``motcomp hil``, ``motcomp run --config
<config>`` (both started once per sender and mode) and ``motcomp source`` (once per signal, with
``--jitter-us``, ``--stall-every-s``/``--stall-ms``, ``--no-t`` and a seed shared by the two
modes).  This process records the sender's frames (stamped as zenoh delivers them), the
service's output (``platform/setpoint``) and the platform's feedback, and computes per run, on
the axis the signal moves (each moves one):

* delay: the feedback behind the sent trajectory (``motcomp.core.quality.estimate_delay``),
  both on their own timestamps: the trajectory at its samples' nominal instants ``t0 + k /
  rate`` (``t0`` from ``motcomp source --json``: what the frames' ``t`` carry, or would carry
  without it), the feedback at its ticks' ``t``; resampled on a 1 ms grid as the demo does
  (for the lane change, their velocities: :data:`DELAY_ON_VELOCITY`);
* sat flags: the share of the output frames flagged ``sat:<axis>``;
* at acc limit: the share of ticks whose command acceleration -- second difference on the
  output ``seq`` grid -- is within 1 % of the axis' limit;
* HF acc, jerk: the command's acceleration RMS above 5 Hz and jerk RMS
  (``motcomp.core.quality.command_quality``);
* HF acc / ideal's on the same stretches: the live HF acceleration over that of the ideal run's
  command cut into the same stretches of the motion (below): a spectrum over a stretch of a
  second or so leaks some of the motion's own acceleration above 5 Hz, so the ideal run over
  the whole motion is not the floor of a run its missed deadlines cut up.

Lost output frames (gaps in ``seq``) and missed deadlines of the service (a step of more than
one period in the frames' ``t``) are counted and reported, never interpolated: the figures are
computed over the stretches between them (the RMS values weighted by length).  Beside each live
figure: the same of the ideal run (``motcomp.sim.ideal.ideal_run``: the config's tick fed the
same trajectory perfectly timed, offline; its delay through the hil's true model of the axis,
``motcomp.core.models.simulate_axis``) and of bypass.  Runs go in order repeat > sender > mode >
signal; with ``--repeats`` the tables show medians.  Writes the "motion" section of
docs/BENCHMARKS.md (not with ``--quick`` or ``--no-write``) and, into ``--out``, ``motion.json``
(every number of every run, and the config used) and ``motion.md`` (the section's text);
``--from-json`` re-renders a report from a ``motion.json``.

The tree is shared: the config and the code are frozen at the start -- the config's includes
merged into one file (checked to the same hash), motcomp/ and config/ copied -- and the child
processes run from those copies, so edits of the tree during the runs do not mix into them.

Usage: ``python tools/bench_motion.py [--config config/motcomp.toml] [--quick] [--out DIR]
[--signals slalom bandsweep lanechange] [--senders NAME ...] [--modes on bypass] [--repeats N]``
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import math
import os
import subprocess
import sys
import tempfile
import time
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from _bench import machine, process_cpu_s, write_section

from motcomp.config import ServiceConfig, config_hash, load_config, read_toml, resolve_axes
from motcomp.core.axes import AXES, AXIS_INDEX
from motcomp.core.models import simulate_axis
from motcomp.core.quality import (
    AT_LIMIT_FRACTION,
    HF_ABOVE_HZ,
    at_acc_limit,
    command_quality_over,
    estimate_delay,
)
from motcomp.demo import stop_processes
from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, free_tcp_port, loopback, open_session
from motcomp.jsonsafe import finite
from motcomp.sim.hil import default_truth
from motcomp.sim.ideal import ideal_run
from motcomp.sim.source import builtin

ROOT = Path(__file__).resolve().parent.parent
SIGNALS = ("slalom", "bandsweep", "lanechange")
DELAY_ON_VELOCITY = frozenset({"lanechange"})
"""Signals whose delay is taken on velocities: on the positions of a step-like move the
cross-correlation is almost flat around its peak (a pure P1D lag of Td + Tp1 = 203 ms reads
13 ms on the lane change's positions, 190 ms on its velocities)."""
MODES = ("on", "bypass")
RUN_OVERHEAD_S = 3.0
"""About what a run costs beyond its motion (the source's start-up and lead-in, the tail)."""
GROUP_OVERHEAD_S = 5.0
"""About what starting the platform and the service costs, once per sender and mode."""


@dataclass(frozen=True)
class Sender:
    """A motion source's timing: ``motcomp source`` options."""

    rate_hz: float
    jitter_us: float
    stalls: tuple[float, float, float] | None = None
    """(mean interval s, shortest ms, longest ms)."""
    with_t: bool = True

    def args(self) -> list[str]:
        out = ["--rate", f"{self.rate_hz:g}", "--jitter-us", f"{self.jitter_us:g}"]
        if self.stalls is not None:
            every, lo, hi = self.stalls
            out += ["--stall-every-s", f"{every:g}", "--stall-ms", f"{lo:g}-{hi:g}"]
        return out + ([] if self.with_t else ["--no-t"])

    def label(self) -> str:
        rate = "1 kHz" if self.rate_hz == 1000 else f"{self.rate_hz:g} Hz"
        out = f"{rate}, jitter {self.jitter_us:g} us"
        if self.stalls is not None:
            out += f", stalls {self.stalls[1]:g}-{self.stalls[2]:g} ms ~every {self.stalls[0]:g} s"
        return out


def _senders() -> dict[str, Sender]:
    base = {"1k-j300-stalls": Sender(1000.0, 300.0, (3.0, 2.0, 15.0)),
            "1k-j50": Sender(1000.0, 50.0),
            "250-j300": Sender(250.0, 300.0),
            "100-j300": Sender(100.0, 300.0),
            "60-j300": Sender(60.0, 300.0)}
    out = {}
    for name, s in base.items():
        out[name] = s
        out[f"{name}-no-t"] = Sender(s.rate_hz, s.jitter_us, s.stalls, with_t=False)
    return out


SENDERS = _senders()
QUICK = {"senders": ["1k-j300-stalls", "60-j300-no-t"], "signals": ["lanechange"]}


# --- processes --------------------------------------------------------------------------------
CODE = [ROOT]
"""Where the child processes import motcomp from: this tree, or the snapshot of it that
:func:`snapshot_code` made (then the only item)."""


def child_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(CODE[0]) + os.pathsep + env.get("PYTHONPATH", "")
    if CODE[0] != ROOT:
        env["MOTCOMP_CONFIG_DIR"] = str(CODE[0] / "config")
    return env


def snapshot_code(tmp: Path) -> str:
    """Copy motcomp's package and shipped files (``config/``) into ``tmp`` and run the child
    processes from there: edits of the tree during the benchmark do not reach them.  Returns
    the tree's commit, ``+`` if motcomp/ or config/ had changes not committed, and the
    fingerprint of the copy."""
    import shutil

    code = tmp / "code"
    skip = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(ROOT / "motcomp", code / "motcomp", ignore=skip)
    shutil.copytree(ROOT / "config", code / "config", ignore=skip)
    CODE[0] = code

    def git(*a: str) -> str:
        try:
            return subprocess.run(["git", "-C", str(ROOT), *a], capture_output=True, text=True,
                                  timeout=10).stdout.strip()
        except (OSError, subprocess.TimeoutExpired):
            return ""

    head = git("rev-parse", "--short", "HEAD") or "unknown commit"
    dirty = "+" if git("status", "--porcelain", "--", "motcomp", "config") else ""
    return f"{head}{dirty} (sources {code_fingerprint(code)})"


def spawn(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    with log.open("ab") as fh:
        return subprocess.Popen([sys.executable, "-m", "motcomp", *args], stdout=fh,
                                stderr=subprocess.STDOUT, env=child_env())


def toml_text(table: dict[str, Any], path: tuple[str, ...] = ()) -> str:
    """A TOML document of a parsed one (keys and values as ``tomllib`` gives them; every
    nested map as a table of its own)."""
    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, float):
            return repr(v)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return json.dumps(v)

    def key(k: str) -> str:
        return k if k.replace("_", "").replace("-", "").isalnum() else json.dumps(k)

    lines = [f"{key(k)} = {value(v)}" for k, v in table.items() if not isinstance(v, dict)]
    out = ([f"[{'.'.join(key(k) for k in path)}]"] if path and lines else []) + lines
    text = "\n".join(out) + ("\n" if out else "")
    for k, v in table.items():
        if isinstance(v, dict):
            text += toml_text(v, (*path, k))
    return text


def snapshot_config(cfg_path: Path, tmp: Path) -> Path:
    """The config as it is now, includes merged, in one file of ``tmp``: edits of the tree's
    config during the benchmark do not reach the services it starts later.

    Raises
    ------
    SystemExit
        If the snapshot does not validate to the same effective config (hash).
    """
    path = tmp / "config.toml"
    path.write_text(toml_text(read_toml(cfg_path)))
    want, got = config_hash(load_config(cfg_path)), config_hash(load_config(path))
    if want != got:
        raise SystemExit(f"snapshot of {cfg_path} differs from it (hash {got} != {want})")
    return path


def code_fingerprint(root: Path = ROOT) -> str:
    """Short hash of the Python sources of ``root``/motcomp."""
    h = hashlib.sha256()
    for f in sorted((root / "motcomp").rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def mode_config(cfg_path: Path, mode: str, tmp: Path) -> Path:
    """The config of a mode: as is (on), or a copy with every driven axis bypassed.

    Raises
    ------
    SystemExit
        If the copy leaves a driven axis compensated (a profile that sets bypass).
    """
    if mode == "on":
        return cfg_path
    cfg = load_config(cfg_path)
    axes = resolve_axes(cfg)
    driven = [a for a, d in zip(AXES, axes.driven, strict=True) if d]
    path = tmp / "bypass.toml"
    path.write_text(f"include = [{json.dumps(str(cfg_path.resolve()))}]\n"
                    + "".join(f"[axes.{a}]\nbypass = true\n" for a in driven))
    check = resolve_axes(load_config(path))
    left = [a for a, d, b in zip(AXES, check.driven, check.bypass, strict=True) if d and not b]
    if left:
        raise SystemExit(f"{path}: {', '.join(left)} still compensated (a profile sets bypass?)")
    return path


@dataclass
class Recording:
    """What this process received during one run (raw; decoded afterwards)."""

    inputs: list[tuple[float, bytes]]
    outputs: list[bytes]
    feedback: list[bytes]
    source: dict[str, Any]
    status_before: dict[str, Any]
    status_after: dict[str, Any]
    steal: float
    load: float
    """The 1-minute load average at the run's end."""
    cpu: dict[str, float] = field(default_factory=dict)
    """Each long-running process' share of one core over the run (%): ``service``, ``hil``."""


class Bench:
    """A platform simulator and a service (one config) and this process' zenoh session."""

    def __init__(self, cfg: ServiceConfig, cfg_path: Path, logs: Path, label: str) -> None:
        self.cfg, self.cfg_path, self.logs, self.label = cfg, cfg_path, logs, label
        self.p_hil, self.p_svc, self.p_me, self.p_src = (free_tcp_port() for _ in range(4))
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.seq = 0

    @contextmanager
    def running(self) -> Iterator[Bench]:
        import zenoh

        cfg = self.cfg
        try:
            self.procs["hil"] = spawn(["hil", "-l", loopback(self.p_hil), "--log-level",
                                       "warning"], self.logs / f"{self.label}-hil.log")
            self.procs["service"] = spawn(
                ["run", "--config", str(self.cfg_path), "-l", loopback(self.p_svc), "-e",
                 loopback(self.p_hil), "--log-level", "warning"],
                self.logs / f"{self.label}-service.log")
            ep = ZenohEndpoints(connect=(loopback(self.p_hil), loopback(self.p_svc)),
                                listen=(loopback(self.p_me),))
            with open_session(ep) as session:
                self.session = session
                self.inputs: list[tuple[float, bytes]] = []
                arrived = self.inputs.append
                clock = time.time
                subs = [session.declare_subscriber(
                    cfg.input.key, lambda s: arrived((clock(), s.payload.to_bytes())))]
                self.sub_out = session.declare_subscriber(cfg.output.key,
                                                          zenoh.handlers.FifoChannel(200_000))
                self.sub_fb = session.declare_subscriber(cfg.feedback.key,
                                                         zenoh.handlers.FifoChannel(200_000))
                subs += [self.sub_out, self.sub_fb]
                try:
                    self._wait_ready()
                    yield self
                finally:
                    for s in subs:
                        s.undeclare()
        finally:
            codes = stop_processes(self.procs)
            bad = {k: v for k, v in codes.items() if v != 0}
            if bad:
                print(f"  warning: exit codes {bad}; see {self.logs}", file=sys.stderr)

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = msgpack.unpackb(first_reply(self.session, self.cfg.status.key,
                                                          None, 3.0))
        return out

    def _wait_ready(self, timeout: float = 30.0) -> None:
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            for name, p in self.procs.items():
                if p.poll() is not None:
                    raise SystemExit(f"{name} exited with {p.returncode}; see {self.logs}")
            try:
                if self.status().get("ticks", 0) > 0 and self.sub_fb.try_recv() is not None:
                    return
            except Exception:  # not up yet
                pass
            time.sleep(0.2)
        raise SystemExit(f"service or platform not ready within {timeout:.0f} s; see {self.logs}")

    def _drain(self, outputs: list[bytes], feedback: list[bytes]) -> None:
        while (s := self.sub_out.try_recv()) is not None:
            outputs.append(s.payload.to_bytes())
        while (s := self.sub_fb.try_recv()) is not None:
            feedback.append(s.payload.to_bytes())

    def run(self, signal_name: str, sender: Sender, seed: int, duration_s: float,
            tick: Callable[[float], None] | None = None) -> Recording:
        """One run of the source; what was received from its start to its end plus a tail."""
        rec = self.record(
            [sys.executable, "-m", "motcomp", "source", "--signal", signal_name,
             *sender.args(), "--seed", str(seed), "--seq-start", str(self.seq), "--key",
             self.cfg.input.key, "-e", loopback(self.p_svc), "-e", loopback(self.p_me),
             "-l", loopback(self.p_src), "--lead-in", "0.3", "--json", "--quiet"],
            "motcomp source", tick)
        self.seq = int(rec.source["next_seq"]) + 1
        return rec

    def record(self, command: list[str], name: str,
               tick: Callable[[float], None] | None = None) -> Recording:
        """Run the sender ``command`` (its last line on stdout a JSON summary: the
        recording's ``source``) to its end; what was received from its start to its end plus
        a tail.

        Raises
        ------
        SystemExit
            If the sender exits with an error (``name`` says which).
        """
        outputs: list[bytes] = []
        feedback: list[bytes] = []
        self._drain([], [])
        self.inputs.clear()
        before = self.status()
        host0 = cpu_times()
        cpu0 = {k: process_cpu_s(p.pid) for k, p in self.procs.items()}
        w0 = time.monotonic()
        log = self.logs / f"{self.label}-source.log"
        with log.open("ab") as err:
            src = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=err, env=child_env())
            t0 = time.monotonic()
            while src.poll() is None:
                time.sleep(0.05)
                self._drain(outputs, feedback)
                if tick is not None:
                    tick(time.monotonic() - t0)
            t_end = time.monotonic() + 0.5  # the last frames in flight
            while time.monotonic() < t_end:
                time.sleep(0.05)
                self._drain(outputs, feedback)
        out = src.stdout.read().decode() if src.stdout is not None else ""
        if src.returncode != 0:
            raise SystemExit(f"{name} exited with {src.returncode}; see {log}")
        stats = json.loads(out.strip().splitlines()[-1])
        host = [b - a for a, b in zip(host0, cpu_times(), strict=True)]
        wall = time.monotonic() - w0
        cpu = {k: 100 * (process_cpu_s(p.pid) - cpu0[k]) / wall for k, p in self.procs.items()}
        return Recording(list(self.inputs), outputs, feedback, stats, before, self.status(),
                         100 * host[7] / max(sum(host), 1), os.getloadavg()[0], cpu)


def cpu_times() -> list[int]:
    """The machine's aggregate CPU times (user, nice, system, idle, iowait, irq, softirq, steal)."""
    return [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]]


# --- analysis ---------------------------------------------------------------------------------
def segments(seq: np.ndarray, t: np.ndarray, rate_hz: float) -> list[slice]:
    """Runs of consecutive output frames: ``seq`` steps by 1 and ``t`` by one period."""
    cut = (np.diff(seq) != 1) | (np.abs(np.diff(t) * rate_hz - 1.0) > 0.5)
    edges = np.concatenate([[0], np.flatnonzero(cut) + 1, [seq.size]])
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(edges) if b > a]


def frame_gaps(seq: np.ndarray, t: np.ndarray, rate_hz: float) -> tuple[int, int]:
    """Output frames lost on the way (gaps in ``seq``) and deadlines the service missed (its
    frames' ``t`` stepping by more than one period beyond the lost frames)."""
    if not seq.size:
        return 0, 0
    lost = np.clip(np.diff(seq) - 1, 0, None)
    steps = np.rint(np.diff(t) * rate_hz).astype(np.int64)
    return int(lost.sum()), int(np.clip(steps - 1 - lost, 0, None).sum())


def command_figures(u: np.ndarray, parts: list[slice], rate_hz: float,
                    a_max: float) -> dict[str, float]:
    """At-limit share and :func:`command_quality_over` of the stretches ``parts`` of ``u``
    (nothing is bridged)."""
    at = n_acc = 0
    for part in parts:
        if u[part].size >= 3:
            at_limit = at_acc_limit(u[part], rate_hz, a_max)
            at += int(np.count_nonzero(at_limit))
            n_acc += at_limit.size
    q = command_quality_over(u, parts, rate_hz, HF_ABOVE_HZ)
    return {"at_limit": at / n_acc if n_acc else math.nan, **q.as_dict()}


def resampled_delay(t_ref: np.ndarray, ref: np.ndarray, t_out: np.ndarray, out: np.ndarray,
                    velocity: bool = False) -> float:
    """Delay of ``out`` behind ``ref`` on a common 1 ms grid over their overlap (as the demo),
    or of their velocities (first differences on that grid) with ``velocity``."""
    if t_ref.size < 10 or t_out.size < 100 or np.ptp(ref) == 0:
        return math.nan
    grid = np.arange(max(t_ref[0], t_out[0]), min(t_ref[-1], t_out[-1]), 1e-3)
    r, y = np.interp(grid, t_ref, ref), np.interp(grid, t_out, out)
    if velocity:
        r, y = np.diff(r), np.diff(y)
    try:
        return estimate_delay(r, y, 1000.0, max_lag_s=1.0)
    except ValueError:
        return math.nan


def percentiles_ms(x: np.ndarray) -> dict[str, float]:
    if x.size == 0:
        return {"p50": math.nan, "p99": math.nan, "max": math.nan}
    return {"p50": float(np.percentile(x, 50)) * 1e3, "p99": float(np.percentile(x, 99)) * 1e3,
            "max": float(x.max()) * 1e3}


def analyse(rec: Recording, signal_name: str, sender: Sender, axis: str, a_max: float,
            loop_hz: float, ideal_u: np.ndarray) -> dict[str, Any]:
    """The figures of one live run (module docstring); ``ideal_u``: the ideal run's command of
    the same sender rate and mode, from the motion's start, on the loop's grid."""
    traj = builtin(signal_name, sender.rate_hz)
    src = rec.source
    t0 = float(src["t0_s"])
    duration = traj.duration_s
    t_nom = t0 + np.arange(traj.samples) / sender.rate_hz
    ref = traj.pos[axis]
    # the sender's frames as received: lateness behind their nominal instants
    late = []
    for arrival, payload in rec.inputs:
        f = msgpack.unpackb(payload)
        if "t" in f:
            late.append(arrival - f["t"])
        elif src["skipped"] == 0:  # (seq -> sample index holds only if nothing was dropped)
            late.append(arrival - (t0 + (f["seq"] - src["seq_start"]) / sender.rate_hz))
    # the command, on the output seq grid, over the motion
    frames = [msgpack.unpackb(p) for p in rec.outputs]
    frames = [f for f in frames if t0 - 0.5 / loop_hz <= f["t"] < t0 + duration]
    frames.sort(key=lambda f: f["seq"])
    seq = np.array([f["seq"] for f in frames], dtype=np.int64)
    t = np.array([f["t"] for f in frames])
    u = np.array([f["pos"][axis] for f in frames])
    sat = np.array([f"sat:{axis}" in f["flags"] for f in frames])
    # (stale at the motion's start is the pause before it, not an episode begun during it)
    stale = np.array([True] + ["stale" in f["flags"] for f in frames])
    expected = round(duration * loop_hz)
    lost, missed = frame_gaps(seq, t, loop_hz)
    parts = segments(seq, t, loop_hz) if seq.size else []
    fig = (command_figures(u, parts, loop_hz, a_max) if seq.size else
           dict.fromkeys(("at_limit", "hf_acc_rms", "jerk_rms", "acc_peak"), math.nan))
    # the ideal command over the same stretches of the motion: what the stretches' edges alone
    # do to the figures (a spectrum over a short stretch leaks the motion's own acceleration)
    k = np.rint((t - t0) * loop_hz).astype(np.int64) if seq.size else np.zeros(0, np.int64)
    same = [slice(int(np.clip(k[p.start], 0, ideal_u.size)),
                  int(np.clip(k[p.stop - 1] + 1, 0, ideal_u.size))) for p in parts]
    floor = command_figures(ideal_u, same, loop_hz, a_max) if same else {}
    fb = [msgpack.unpackb(p) for p in rec.feedback]
    t_fb = np.array([f["t"] for f in fb])
    y_fb = np.array([f["pos"][axis] for f in fb])
    sel = (t_fb >= t0) & (t_fb <= t0 + duration)
    before, after = rec.status_before, rec.status_after
    fr0, fr1 = before.get("frames", {}), after.get("frames", {})
    return {
        "delay_ms": resampled_delay(t_nom, ref, t_fb[sel], y_fb[sel],
                                    signal_name in DELAY_ON_VELOCITY) * 1e3,
        "sat": float(sat.mean()) if sat.size else math.nan,
        **fig,
        "hf_floor_same": floor.get("hf_acc_rms", math.nan),
        "hf_ratio": fig["hf_acc_rms"] / floor["hf_acc_rms"] if floor else math.nan,
        "frames": {"expected": expected, "recorded": int(seq.size), "lost": lost,
                   "missed_deadlines": missed},
        "input": {"sent": src["sent"], "skipped": src["skipped"], "stalls": src["stalls"],
                  "held": src["held"], "seed": src["seed"],
                  "received_here": len(rec.inputs),
                  "lateness_ms": percentiles_ms(np.array(late))},
        "service": {
            "accepted": fr1.get("accepted", 0) - fr0.get("accepted", 0),
            "rejected": fr1.get("rejected", 0) - fr0.get("rejected", 0),
            "stale_episodes": int(np.count_nonzero(stale[1:] & ~stale[:-1])),
        },
        "steal_pct": rec.steal,
        "load": rec.load,
    }


def ideal_figures(cfg: ServiceConfig, signal_name: str, rate_hz: float, mode: str,
                  a_max: float, truth: Any) -> tuple[dict[str, Any], np.ndarray]:
    """The figures of the ideal offline run (delay through the hil's true model), and its
    command on the loop's grid."""
    traj = builtin(signal_name, rate_hz)
    (axis, ref), = traj.pos.items()
    run = ideal_run(cfg, traj.pos, rate_hz, bypass=mode == "bypass")
    u = run.u[axis]
    y = simulate_axis(truth, u, run.rate_hz)
    t_src = np.arange(traj.samples) / rate_hz
    fig = command_figures(u, [slice(0, u.size)], run.rate_hz, a_max)
    return {"delay_ms": resampled_delay(t_src, ref, run.t, y,
                                        signal_name in DELAY_ON_VELOCITY) * 1e3,
            "sat": math.nan, **fig,
            "acted": float(np.mean(run.acted[axis]))}, u


# --- report -----------------------------------------------------------------------------------
def median(rows: list[dict[str, Any]], key: str) -> float:
    vals = [r[key] for r in rows if key in r and r[key] is not None and math.isfinite(r[key])]
    return float(np.median(vals)) if vals else math.nan


def fmt(x: float, spec: str = ".2f") -> str:
    return "-" if not math.isfinite(x) else format(x, spec)


def pct(x: float) -> str:
    return "-" if not math.isfinite(x) else f"{100 * x:.2f}"


def pair(on: float, off: float, f: Callable[[float], str]) -> str:
    return f"{f(on)} / {f(off)}"


def report(args: argparse.Namespace, runs: list[dict[str, Any]], ideal: list[dict[str, Any]],
           elapsed_s: float, machine_line: str, load_end: tuple[float, float, float],
           steal: float, cfg: ServiceConfig) -> str:
    axes = resolve_axes(cfg)
    limits = ", ".join(f"{a} {axes.limits.a_max[AXIS_INDEX[a]]:g} m/s^2" for a in
                       dict.fromkeys(r["axis"] for r in runs))
    opts = " ".join(
        ([f"--config {args.config}"] if args.config != default_config() else [])
        + (["--quick"] if args.quick else [])
        + ([f"--signals {' '.join(args.signals)}"] if args.signals != list(SIGNALS) else [])
        + ([f"--senders {' '.join(args.senders)}"] if args.senders != list(SENDERS) else [])
        + ([f"--modes {' '.join(args.modes)}"] if args.modes != list(MODES) else [])
        + ([f"--repeats {args.repeats}"] if args.repeats != 1 else []))
    lines = [
        f"Machine: {machine_line}; 1-minute load average at the runs' ends "
        f"{min((r['load'] for r in runs), default=math.nan):.1f}-"
        f"{max((r['load'] for r in runs), default=math.nan):.1f} (median "
        f"{median(runs, 'load'):.1f}; this benchmark alone keeps four processes busy on the "
        f"machine), at the end {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f}; the host's "
        f"steal {steal:.1f} % of the CPU time during the runs.",
        "",
        f"`python tools/bench_motion.py{' ' + opts if opts else ''}` ({elapsed_s / 60:.1f} min, "
        f"config `{display_path(args.config)}` as it was at the start, hash "
        f"{config_hash(cfg)}; code {runs[0].get('code', '?') if runs else '?'}; loop "
        f"{cfg.loop.rate_hz:g} Hz, "
        f"{'sync to input' if cfg.loop.sync_to_input else 'own clock'}, input reconstruction "
        f"{cfg.input.reconstruction!r}): `motcomp hil`, `motcomp run` and `motcomp source` as "
        "processes on loopback; per signal, the axis it moves; each cell *on / bypass*"
        + (f", medians of {args.repeats} runs" if args.repeats > 1 else "") + ".  Ideal rows: "
        "the config's tick fed the same trajectory perfectly timed at the sender's rate, "
        "offline (`motcomp.sim.ideal.ideal_run`): the floor of each figure.",
        "",
    ]
    codes = list(dict.fromkeys(r.get("code") for r in [*ideal, *runs]))
    if len(codes) > 1:
        first = {c: next(i for i, r in enumerate(runs, 1) if r.get("code") == c)
                 for c in codes[1:] if any(r.get("code") == c for r in runs)}
        lines += ["**Warning**: motcomp's code in this tree changed during the benchmark (runs "
                  + ", ".join(f"{i}-" for i in first.values()) + " ran newer code): do not "
                  "compare their rows with the others.", ""]
    for sig in [s for s in SIGNALS if s in args.signals]:
        traj = builtin(sig)
        (axis, _), = traj.pos.items()
        lines += [f"**{sig}** ({traj.description}, {traj.duration_s:.1f} s; {axis}):", "",
                  "| sender | t | delay (ms) | sat flags (%) | at acc limit (%) | "
                  "HF acc RMS > 5 Hz (m/s^2) | HF acc / ideal's on the same stretches | "
                  "jerk RMS (m/s^3) | lost / missed frames, stale |",
                  "|---|---|---|---|---|---|---|---|---|"]
        rates = list(dict.fromkeys(SENDERS[s].rate_hz for s in args.senders))
        for rate in sorted(rates, reverse=True):
            rows = {m: [r for r in ideal if r["signal"] == sig and r["rate_hz"] == rate
                        and r["mode"] == m] for m in MODES}
            on, off = ({k: median(rows[m], k) for k in ("delay_ms", "at_limit", "hf_acc_rms",
                                                         "jerk_rms")} for m in MODES)
            lines.append(
                f"| ideal, {rate_name(rate)} | - | {pair(on['delay_ms'], off['delay_ms'], fmt)} "
                f"| - | {pair(on['at_limit'], off['at_limit'], pct)} | "
                f"{pair(on['hf_acc_rms'], off['hf_acc_rms'], lambda x: fmt(x, '.3g'))} | - | "
                f"{pair(on['jerk_rms'], off['jerk_rms'], lambda x: fmt(x, '.3g'))} | - |")
        for name in args.senders:
            s = SENDERS[name]
            rows = {m: [r for r in runs if r["signal"] == sig and r["sender"] == name
                        and r["mode"] == m] for m in MODES}
            if not any(rows.values()):
                continue
            on, off = ({k: median(rows[m], k) for k in ("delay_ms", "sat", "at_limit",
                                                         "hf_acc_rms", "jerk_rms", "hf_ratio")}
                       for m in MODES)
            lost = {m: sum(r["frames"]["lost"] for r in rows[m]) for m in MODES}
            missed = {m: sum(r["frames"]["missed_deadlines"] for r in rows[m]) for m in MODES}
            stale = {m: sum(r["service"]["stale_episodes"] for r in rows[m]) for m in MODES}
            lines.append(
                f"| {s.label()} | {'yes' if s.with_t else 'no'} | "
                f"{pair(on['delay_ms'], off['delay_ms'], fmt)} | "
                f"{pair(on['sat'], off['sat'], pct)} | "
                f"{pair(on['at_limit'], off['at_limit'], pct)} | "
                f"{pair(on['hf_acc_rms'], off['hf_acc_rms'], lambda x: fmt(x, '.3g'))} | "
                f"{pair(on['hf_ratio'], off['hf_ratio'], lambda x: fmt(x, '.2g'))} | "
                f"{pair(on['jerk_rms'], off['jerk_rms'], lambda x: fmt(x, '.3g'))} | "
                f"{lost['on']}/{missed['on']}/{stale['on']} / "
                f"{lost['bypass']}/{missed['bypass']}/{stale['bypass']} |")
        lines.append("")
    lines += [
        "The senders as received (all signals and modes; lateness = arrival here - nominal "
        "instant, medians of the runs' percentiles; without `t` and with samples dropped the "
        "nominal instant of a frame is unknown: -):",
        "",
        "| sender | t | runs | lateness p50 / p99 / max (ms) | stalls / frames held in "
        "bursts | samples dropped by the sender's own stalls | input frames rejected by the "
        "service | stale-input episodes during the motion |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in args.senders:
        rows = [r for r in runs if r["sender"] == name]
        if not rows:
            continue
        s = SENDERS[name]
        lat = {q: float(np.nanmedian([r["input"]["lateness_ms"][q] for r in rows]))
               if any(math.isfinite(r["input"]["lateness_ms"][q]) for r in rows) else math.nan
               for q in ("p50", "p99", "max")}
        lines.append(
            f"| {s.label()} | {'yes' if s.with_t else 'no'} | {len(rows)} | "
            f"{fmt(lat['p50'])} / {fmt(lat['p99'])} / {fmt(lat['max'])} | "
            f"{sum(r['input']['stalls'] for r in rows)} / {sum(r['input']['held'] for r in rows)}"
            f" | {sum(r['input']['skipped'] for r in rows)} | "
            f"{sum(r['service']['rejected'] for r in rows)} | "
            f"{sum(r['service']['stale_episodes'] for r in rows)} |")
    acted = [r for r in ideal if r["mode"] == "on"]
    lines += [
        "",
        "What the figures mean.  *delay*: the platform's feedback behind the trajectory the "
        "sender meant (its samples at their nominal instants), by cross-correlation "
        "(`motcomp.core.quality.estimate_delay`); ideal rows: the ideal command through the "
        "platform simulator's true model.  For the lane change, a step-like move, the delay is "
        "that of the velocities: on its positions the cross-correlation is nearly flat around "
        "its peak (a pure P1D lag of Td + Tp1 = 203 ms reads 13 ms there, 190 ms on the "
        "velocities).  *sat flags*: output frames flagged `sat:<axis>` "
        "(a position or velocity bound acted, or the command left its compensated target by "
        "more than `status.saturation_tolerance` on a 20 ms average; the ideal run does not "
        "report flags).  *at acc limit*: ticks whose command acceleration, the second "
        f"difference on the output `seq` grid, is within {100 * (1 - AT_LIMIT_FRACTION):g} % of "
        f"the axis' limit ({limits}): the limiter holding the command at its acceleration "
        "bound, the chatter the compensator's high-frequency gain provokes from irregular "
        "input.  *HF acc RMS*: RMS of the command's acceleration above "
        f"{HF_ABOVE_HZ:g} Hz, *jerk RMS* of its third difference "
        "(`motcomp.core.quality.command_quality`): what shakes the cabin and wears the "
        "actuators; a driver's motion lives below 2-3 Hz.  *lost / missed*: output frames lost "
        "on the way here (gaps in `seq`) / deadlines the service missed (its frames' `t` step "
        "by more than a period); the command figures skip the second differences across them, "
        "nothing is interpolated.  *stale*: stale-input episodes during the motion (no valid "
        f"input for `loop.stale_after_s` = {cfg.loop.stale_after_s * 1e3:g} ms: the service "
        "holds the reference, then blends back, which adds to the delay).  Runs: each "
        "(sender, signal, mode) once per repeat, the senders' seeds shared by the two modes and "
        "by the with- and without-`t` variants."
        + ("  The ideal runs' limiter acted (any bound, compensation on; most of all signals) "
           "on " + ", ".join(
               f"{fmt(100 * max(r['acted'] for r in acted if r['rate_hz'] == rate))} % "
               f"({rate_name(rate)})" for rate in dict.fromkeys(r["rate_hz"] for r in acted))
           + " of the ticks." if acted else ""),
    ]
    return "\n".join(lines)


def rate_name(rate: float) -> str:
    return "1 kHz" if rate == 1000 else f"{rate:g} Hz"


def default_config() -> str:
    return "config/motcomp.toml"


def display_path(path: str) -> str:
    p = Path(path).resolve()
    try:
        return str(p.relative_to(ROOT))
    except ValueError:
        return str(p)


def seed_of(sender: str, signal_name: str, repeat: int) -> int:
    """The same for both modes and for a sender with and without ``t``."""
    key = f"{sender.removesuffix('-no-t')}/{signal_name}/{repeat}"
    return zlib.crc32(key.encode()) & 0x7FFFFFFF


def rerender(path: Path, no_write: bool) -> None:
    """The report of a ``motion.json`` (its options, runs and machine), as the run wrote it."""
    result = unplain(json.loads(path.read_text()))
    args = argparse.Namespace(**result["args"])
    if "config_toml" in result:  # the config the runs used
        with tempfile.TemporaryDirectory() as tmp:
            frozen = Path(tmp) / "config.toml"
            frozen.write_text(result["config_toml"])
            cfg = load_config(frozen)
    else:
        cfg = load_config(result["config"])
    text = report(args, result["runs"], result["ideal"], result["elapsed_s"],
                  result["machine"], tuple(result["load_end"]), result["steal_pct"], cfg)
    print(text)
    if not no_write:
        write_section("motion", text)


def unplain(obj: Any) -> Any:
    """The inverse of :func:`plain` for the numbers: null -> NaN."""
    if isinstance(obj, dict):
        return {k: unplain(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [unplain(v) for v in obj]
    return math.nan if obj is None else obj


def words(text: str) -> list[str]:
    return [w for w in text.replace(",", " ").split() if w]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=default_config(),
                    help="the service's config (default config/motcomp.toml); bypass runs use "
                         "a copy with every driven axis bypassed")
    ap.add_argument("--quick", action="store_true",
                    help=f"a smoke run (< 2 min): senders {', '.join(QUICK['senders'])}, signal "
                         f"{', '.join(QUICK['signals'])}; does not write docs/BENCHMARKS.md")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench_motion",
                    help="directory for motion.json and motion.md (default out/bench_motion)")
    ap.add_argument("--signals", nargs="+", metavar="NAME",
                    help=f"signals to run (default: all of {', '.join(SIGNALS)})")
    ap.add_argument("--senders", nargs="+", metavar="NAME",
                    help=f"senders to run (default: all of {', '.join(SENDERS)})")
    ap.add_argument("--modes", nargs="+", metavar="MODE",
                    help="on (the config as is) and/or bypass (default: both)")
    ap.add_argument("--repeats", type=int, default=1,
                    help="runs of each case, interleaved; the tables show medians")
    ap.add_argument("--no-write", action="store_true",
                    help="do not write docs/BENCHMARKS.md (only --out and the terminal)")
    ap.add_argument("--from-json", type=Path, metavar="FILE",
                    help="measure nothing: report the runs of a motion.json written before "
                         "(and write the docs section unless --no-write)")
    args = ap.parse_args()
    if args.from_json is not None:
        rerender(args.from_json, args.no_write)
        return
    args.signals = (words(" ".join(args.signals)) if args.signals
                    else QUICK["signals"] if args.quick else list(SIGNALS))
    args.senders = (words(" ".join(args.senders)) if args.senders
                    else QUICK["senders"] if args.quick else list(SENDERS))
    args.modes = words(" ".join(args.modes)) if args.modes else list(MODES)
    for kind, got, known in (("signal", args.signals, SIGNALS), ("sender", args.senders, SENDERS),
                             ("mode", args.modes, MODES)):
        bad = [g for g in got if g not in known]
        if bad:
            ap.error(f"unknown {kind} {bad[0]!r}; {kind}s: {', '.join(known)}")
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {args.repeats}")
    cfg_path = Path(args.config)
    if not cfg_path.is_absolute() and not cfg_path.exists():
        cfg_path = ROOT / cfg_path
    with tempfile.TemporaryDirectory() as tmp:
        measure(args, ap, cfg_path, Path(tmp))


def measure(args: argparse.Namespace, ap: argparse.ArgumentParser, cfg_path: Path,
            tmp: Path) -> None:
    """The ideal runs, then the live runs; the report, the files, the docs section."""
    cfg_file = snapshot_config(cfg_path, tmp)
    cfg = load_config(cfg_file)
    if cfg.output.transport == "can":
        ap.error(f"{args.config}: output.transport is 'can': the benchmark reads the zenoh output")
    if (cfg.output.key, cfg.feedback.key) != ("platform/setpoint", "platform/feedback"):
        ap.error(f"{args.config}: motcomp hil uses platform/setpoint and platform/feedback, the "
                 f"config {cfg.output.key} and {cfg.feedback.key}")
    axes = resolve_axes(cfg)
    truth_models = default_truth()[0]
    loop_hz = cfg.loop.rate_hz
    machine_line = machine()
    code = snapshot_code(tmp)
    durations = {s: builtin(s).duration_s for s in args.signals}
    n_groups = args.repeats * len(args.senders) * len(args.modes)
    n_runs = n_groups * len(args.signals)
    estimate = n_groups * (GROUP_OVERHEAD_S + sum(durations.values())
                           + RUN_OVERHEAD_S * len(args.signals))
    print(f"motion-quality benchmark: {n_runs} runs ({len(args.senders)} senders x "
          f"{len(args.signals)} signals x {len(args.modes)} modes x {args.repeats}), about "
          f"{estimate / 60:.0f} min; config {display_path(str(cfg_path))} (hash "
          f"{config_hash(cfg)}, reconstruction {cfg.input.reconstruction!r}, frozen for the "
          f"runs), code {code}, frozen for the runs too", flush=True)
    print(f"machine: {machine_line}", flush=True)
    t_start = time.monotonic()
    ideal: list[dict[str, Any]] = []
    ideal_u: dict[tuple[str, float, str], np.ndarray] = {}
    rates = sorted({SENDERS[s].rate_hz for s in args.senders}, reverse=True)
    for sig in args.signals:
        (axis, _), = builtin(sig, 1000.0).pos.items()
        a_max = float(axes.limits.a_max[AXIS_INDEX[axis]])
        for rate in rates:
            for mode in args.modes:
                row, ideal_u[sig, rate, mode] = ideal_figures(
                    cfg, sig, rate, mode, a_max, truth_models[AXIS_INDEX[axis]])
                ideal.append({"signal": sig, "rate_hz": rate, "mode": mode, "axis": axis,
                              "code": code, **row})
                print(f"  ideal {sig:<10} {rate_name(rate):>6} {mode:<6} delay "
                      f"{fmt(row['delay_ms'], '.1f')} ms, at acc limit {pct(row['at_limit'])} "
                      f"%, HF acc {fmt(row['hf_acc_rms'], '.3g')}", flush=True)
    runs: list[dict[str, Any]] = []
    host0 = cpu_times()
    n = 0
    args.out.mkdir(parents=True, exist_ok=True)
    logs = args.out / "logs"
    logs.mkdir(exist_ok=True)
    for old in logs.glob("*.log"):  # (each process appends to its own)
        old.unlink()
    configs = {m: mode_config(cfg_file, m, tmp) for m in args.modes}
    for rep in range(args.repeats):
        for name in args.senders:
            sender = SENDERS[name]
            for mode in args.modes:
                label = f"{name}-{mode}-{rep + 1}"
                with Bench(cfg, configs[mode], logs, label).running() as bench:
                    for sig in args.signals:
                        n += 1
                        (axis, _), = builtin(sig, 1000.0).pos.items()
                        a_max = float(axes.limits.a_max[AXIS_INDEX[axis]])
                        print(f"[{n}/{n_runs}] {sig}, {sender.label()}, "
                              f"{'t' if sender.with_t else 'no t'}, {mode}: ", end="",
                              flush=True)
                        rec = bench.run(sig, sender, seed_of(name, sig, rep), durations[sig])
                        row = analyse(rec, sig, sender, axis, a_max, loop_hz,
                                      ideal_u[sig, sender.rate_hz, mode])
                        runs.append({"signal": sig, "sender": name, "mode": mode,
                                     "repeat": rep + 1, "axis": axis, "code": code, **row})
                        fr = row["frames"]
                        print(f"delay {fmt(row['delay_ms'], '.1f')} ms, sat "
                              f"{pct(row['sat'])} %, at acc limit {pct(row['at_limit'])} "
                              f"%, HF acc {fmt(row['hf_acc_rms'], '.3g')} (ideal on the "
                              f"same stretches {fmt(row['hf_floor_same'], '.3g')}), jerk "
                              f"{fmt(row['jerk_rms'], '.3g')}; frames lost {fr['lost']}, "
                              f"missed {fr['missed_deadlines']}; stalls "
                              f"{row['input']['stalls']}, dropped "
                              f"{row['input']['skipped']}; "
                              f"{(time.monotonic() - t_start) / 60:.1f} min", flush=True)
    host = [b - a for a, b in zip(host0, cpu_times(), strict=True)]
    steal = 100 * host[7] / max(sum(host), 1)
    elapsed = time.monotonic() - t_start
    load_end = os.getloadavg()
    text = report(args, runs, ideal, elapsed, machine_line, load_end, steal, cfg)
    result = {"machine": machine_line, "load_end": load_end, "steal_pct": steal,
              "elapsed_s": elapsed, "config": str(cfg_path), "config_hash": config_hash(cfg),
              "config_toml": cfg_file.read_text(), "loop_hz": loop_hz,
              "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
              "senders": {k: {"rate_hz": v.rate_hz, "jitter_us": v.jitter_us,
                              "stalls": v.stalls, "with_t": v.with_t, "label": v.label()}
                          for k, v in SENDERS.items() if k in args.senders},
              "ideal": ideal, "runs": runs}
    (args.out / "motion.json").write_text(json.dumps(finite(result), indent=1) + "\n")
    (args.out / "motion.md").write_text(text + "\n")
    print()
    print(text)
    print(f"\nwritten: {args.out / 'motion.json'}, {args.out / 'motion.md'}")
    if not (args.quick or args.no_write):
        write_section("motion", text)
        print("and the 'motion' section of docs/BENCHMARKS.md")

if __name__ == "__main__":
    main()
