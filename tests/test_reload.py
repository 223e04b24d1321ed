"""Live reload: in process (the service's tick driven by a thread standing in for its loop,
in-memory ports) and against a running service (subprocess): ``motcomp reload`` and SIGHUP.

Either way: a valid config is swapped in bumplessly (no step in the raw PID output, the command
within the limits), an invalid one is refused with its reason and the running config stays,
untouched."""

from __future__ import annotations

import contextlib
import math
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from motcomp.cli.admin import CHANGE_TIMEOUT_S
from motcomp.config import load_config
from motcomp.core.axes import AXES
from motcomp.core.saturation import AxisLimits
from motcomp.core.tuning import tune
from motcomp.io.memory import MemorySink, MemorySource
from motcomp.io.wire import decode_output, encode_input
from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, free_tcp_port, loopback, open_session
from motcomp.resources import config_file
from motcomp.runtime.service import Service
from tests._frames import assert_frames_within_limits
from tests._notify import NotifyListener
from tests.conftest import RAILS, motcomp_cmd, subprocess_env
from tests.test_saturation import check_sequence
from tests.test_service_process import process, wait_status

MS = 1_000_000  # ns
Y = AXES.index("rails_y")

BASE = f'include = ["{config_file("motcomp.toml")}"]\n[admin]\nenabled = true\n'


def reload_cmd(port: int, path: Path | None = None) -> subprocess.CompletedProcess[str]:
    args = ["reload", "-e", loopback(port)] + (["--config", str(path)] if path else [])
    return subprocess.run(motcomp_cmd(*args), capture_output=True, text=True,
                          env=subprocess_env(), timeout=60)


def status(session: Any) -> dict[str, Any]:
    out: dict[str, Any] = msgpack.unpackb(first_reply(session, "motcomp/status", None, 3.0))
    return out


INVALID = {
    "not TOML": ("[loop\nrate_hz = 1000\n", "not valid TOML"),
    "unknown key": (BASE + "[loop]\nratehz = 1000\n", "loop.ratehz"),
    "inverted limits": (BASE + "[axes.rails_y]\npos_min_m = 1.0\npos_max_m = -1.0\n",
                        "pos_min_m=1.0 must be < pos_max_m=-1.0"),
    "non-finite": (BASE + "[axes.rails_x]\nvel_max_m_s = nan\n", "finite"),
    "unstable gains": (BASE + "[axes.rails_y]\ngains = { kp = 500.0, ki_per_s = 10.0 }\n",
                       "bad-unstable_gains.toml: gains of rails_y", "unstable"),
    "restart key": (BASE + "[loop]\nrate_hz = 500\n", "loop.rate_hz cannot change live"),
    # a restart key changed and a limit beyond the hardware envelope: both said, the envelope
    # (which no restart cures) first
    "restart key and envelope": (
        BASE + "[status]\nperiod_s = 2.0\n[axes.rails_y]\nvel_max_m_s = 3.0\n",
        "2 problems: (1) ", "axes.rails_y.vel_max_m_s = 3.0 lies outside envelope.rails_y",
        "(2) ", "status.period_s cannot change live"),
    "axes set": (BASE.replace("enabled = true", "enabled = true") + "", None),
}


# --- in process ------------------------------------------------------------------------------
@dataclass
class Run:
    """Per tick of :func:`running`: the rails_y command and raw PID output, and the tick
    parameters it ran with."""

    u: list[float] = field(default_factory=list)
    raw: list[float] = field(default_factory=list)
    params: list[object] = field(default_factory=list)

    def swaps(self) -> list[int]:
        """The first tick of each new config."""
        return [k for k in range(1, len(self.params)) if self.params[k] is not self.params[k - 1]]

    def wait(self, ticks: int) -> None:
        """Let the loop run ``ticks`` more ticks."""
        end = len(self.u) + ticks
        while len(self.u) < end:
            time.sleep(1e-3)


@contextlib.contextmanager
def running(svc: Service) -> Iterator[Run]:
    """Tick ``svc`` from a thread standing in for its loop (1 ms of tick time per tick, a
    feasible motion on rails_y that starts at rest; 1.5 s of it before the block, 0.3 s after),
    while the block calls the service from this thread, as its main thread would."""
    src, sink = MemorySource(burst=True), MemorySink(keep=1)
    svc.attach(src, [sink])
    stop = threading.Event()
    errors: list[BaseException] = []
    run = Run()

    def tick(k: int) -> None:
        t = k / 1000
        src.push(encode_input(k, t, {"rails_y": 0.25 * math.sin(0.6 * math.pi * t) ** 3}))
        svc.tick(k * MS)
        run.u.append(decode_output(sink.payloads[-1])["pos"]["rails_y"])
        run.raw.append(float(svc.state.comp.raw_output[Y]))
        run.params.append(svc.params)  # swapped in by the tick's commands, before its step

    def loop(k: int) -> None:
        try:
            while not stop.is_set():
                tick(k)
                k += 1
                time.sleep(50e-6)  # let the main thread run
            for j in range(k, k + 300):
                tick(j)
        except BaseException as exc:  # reported below
            errors.append(exc)

    for k in range(1500):  # start-up, in this thread
        tick(k)
    thread = threading.Thread(target=loop, args=(1500,), daemon=True)
    thread.start()
    try:
        yield run
    finally:
        stop.set()
        thread.join(timeout=30)
    assert not errors and not thread.is_alive()


def ticked(svc: Service, ticks: int = 3) -> None:
    """Wait until the loop of :func:`running` ticked ``ticks`` more times."""
    end, until = svc.state.ticks + ticks, time.monotonic() + 30.0
    while svc.state.ticks < end:
        assert time.monotonic() < until, "the loop stopped ticking"
        time.sleep(0.001)


def assert_within_limits(run: Run, svc: Service) -> None:
    lim = svc.axes.limits
    check_sequence(np.array(run.u), 0.0, AxisLimits(lim.p_min[Y:Y + 1], lim.p_max[Y:Y + 1],
                                                     lim.v_max[Y:Y + 1], lim.a_max[Y:Y + 1]),
                   1e-3)


def assert_command_smooth(run: Run) -> None:
    """No kick in the command at a swap: over the 0.6 s from each swap on, its acceleration
    changes by less than 0.1 m/s^2 a tick (the tick's own period: the loop of :func:`running`
    never skips one).  The new gains' path, which the command blends onto, may lie a few
    millimetres from the old one's: the raw PID output moves to it at once (re-seeding the
    integrator alone, the command rode the acceleration limit after a switch to ZN gains)."""
    u = np.array(run.u)
    for k in run.swaps():
        acc = np.diff(u[k - 3:k + 600], 2) * 1e6
        assert np.abs(np.diff(acc)).max() < 0.1, (k, np.abs(np.diff(acc)).max())


def test_reload_in_process_keeps_the_old_config_on_failure(tmp_path: Path) -> None:
    path = tmp_path / "motcomp.toml"
    path.write_text(BASE)
    svc = Service(load_config(path), ZenohEndpoints(), config_path=path)
    svc.preparer.start(wait=True)  # the reloads' reader process: started as the service does
    with running(svc) as run:
        path.write_text('profile = "fast"\n' + BASE)  # optimised -> AMIGO gains on the rails
        r = svc.reload()
        assert r["ok"] and r["version"] == 2 and svc.config_version == 2, r
        assert r["unchanged"] is False  # another config
        ticked(svc)
        # the status' delay is measured afresh on every axis after a change of config
        marked = list(svc.monitor._changed_ns)
        assert all(m is not None for m in marked), marked
        again = svc.reload()  # the same file again: said (an operator meant another file?)
        assert again["ok"] and again["unchanged"] is True and svc.config_version == 3, again
        ticked(svc)  # ...but not after the same config again (the rails, whose gains the
        # profile changed, may still blend onto their new path)
        rails = {AXES.index("rails_x"), Y}
        assert [m for i, m in enumerate(svc.monitor._changed_ns) if i not in rails] == [
            m for i, m in enumerate(marked) if i not in rails]
        assert svc.axes.gains[Y] == tune("amigo", RAILS).gains
        kept = (svc.cfg, svc.axes, svc.params, svc.config_id)
        for name, (text, *reasons) in INVALID.items():
            if reasons[0] is None:
                continue
            bad = tmp_path / f"bad-{name.replace(' ', '_')}.toml"
            bad.write_text(text)
            r = svc.admin("reload", msgpack.packb({"path": str(bad)}))
            at = [r["error"].find(reason) for reason in reasons]
            assert r["ok"] is False and min(at) >= 0 and at == sorted(at), (name, r)
            assert (svc.cfg, svc.axes, svc.params, svc.config_id) == kept, name
            assert svc.config_version == 3 and svc.reloads[-1]["ok"] is False
        path.write_text('profile = "paper"\n' + BASE)  # -> Ziegler-Nichols
        assert svc.reload()["ok"] and svc.config_version == 4
        assert svc.axes.gains[Y] == tune("zn", RAILS).gains
    assert len(run.swaps()) == 3
    assert_within_limits(run, svc)
    assert svc.state.rejected == 0 and svc.state.ticks == len(run.u)


def test_reload_in_process_is_bumpless(tmp_path: Path) -> None:
    path = tmp_path / "motcomp.toml"
    path.write_text(BASE)
    svc = Service(load_config(path), ZenohEndpoints(), config_path=path)
    # prepared first (in the reader process, while the loop runs on: its phase at the swap
    # would depend on the machine), swapped in at the same instants of the motion every run
    prepared = []
    for profile in ("fast", "paper"):
        path.write_text(f'profile = "{profile}"\n' + BASE)
        prepared.append(svc.preparer.prepare_config(svc.cfg, svc.axes, path, svc.confinement))
    svc.preparer.close()
    with running(svc) as run:
        for new in prepared:
            svc.apply_config(new)
            run.wait(300)
    assert len(run.swaps()) == 2
    assert_within_limits(run, svc)
    assert_command_smooth(run)


# --- against the running service --------------------------------------------------------------
@pytest.mark.slow
def test_reload_valid_and_invalid_and_sighup(tmp_path: Path) -> None:
    import zenoh

    cfg = tmp_path / "motcomp.toml"
    cfg.write_text(BASE)
    p_svc = free_tcp_port()
    notify = tmp_path / "notify.sock"
    listener = NotifyListener(notify)
    env = subprocess_env()
    env["NOTIFY_SOCKET"] = str(notify)
    stop = threading.Event()
    with process(["run", "--config", str(cfg), "-l", loopback(p_svc)], tmp_path / "svc.log",
                 env) as svc, open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
        out_sub = session.declare_subscriber("platform/setpoint",
                                             zenoh.handlers.FifoChannel(200_000))
        st0 = wait_status(session)
        pub = session.declare_publisher("sim/motion/setpoint")

        def feed() -> None:  # a feasible slalom-like motion on rails_y, 1 kHz
            k = 0
            t0 = time.time()
            while not stop.is_set():
                t = k / 1000
                pub.put(encode_input(k, t0 + t,
                                     {"rails_y": 0.3 * math.sin(2 * math.pi * 0.3 * t)}))
                k += 1
                time.sleep(max(0.0, t0 + (k / 1000) - time.time()))

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            time.sleep(2.0)
            # 1. valid: ZN -> AMIGO on the rails, live
            cfg.write_text(BASE + "[defaults]\nrule = \"amigo\"\n")
            r = reload_cmd(p_svc)
            assert r.returncode == 0, r.stderr
            assert "reloaded" in r.stdout
            st1 = status(session)
            assert st1["config"]["version"] == 2
            assert st1["config"]["hash"] != st0["config"]["hash"]
            assert st1["reloads"][-1]["ok"] is True
            time.sleep(1.0)
            # 2. every kind of invalid config is refused; the running config stays
            for name, (text, *reasons) in INVALID.items():
                if reasons[0] is None:
                    continue
                bad = tmp_path / f"bad-{name.replace(' ', '_')}.toml"
                bad.write_text(text)
                r = reload_cmd(p_svc, bad)
                assert r.returncode == 2, (name, r.stdout, r.stderr)  # bad input
                at = [r.stderr.find(reason) for reason in reasons]
                assert min(at) >= 0 and at == sorted(at), (name, r.stderr)  # all, in order
                st = status(session)
                assert st["config"]["version"] == 2 and st["mode"] == "running", name
                assert st["reloads"][-1]["ok"] is False
            # 3. SIGHUP re-reads the file the service was started with
            cfg.write_text(BASE + "[defaults]\nrule = \"zn\"\nfilter_n = 8\n")
            svc.send_signal(signal.SIGHUP)
            t_end = time.monotonic() + 10
            while status(session)["config"]["version"] != 3 and time.monotonic() < t_end:
                time.sleep(0.1)
            assert status(session)["config"]["version"] == 3
            time.sleep(1.0)
        finally:
            stop.set()
            feeder.join()
        # the output never stepped beyond the limits through the reloads
        frames = []
        while (s := out_sub.try_recv()) is not None:
            frames.append(decode_output(s.payload.to_bytes()))
        assert_frames_within_limits(frames, "rails_y", 2.0, 6.0, min_checked=3000)
        out_sub.undeclare()
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=20) == 0
    text = listener.close()
    assert text.count("RELOADING=1") >= 2 + sum(1 for v in INVALID.values() if v[1])
    assert "MONOTONIC_USEC=" in text
    log = (tmp_path / "svc.log").read_text()
    assert "reload ok" in log and "reload rejected" in log
    assert log.count("hash") >= 2


@pytest.mark.slow
def test_admin_requests_refused_at_once_when_admin_is_off(tmp_path: Path) -> None:
    """Each admin command, and the live identification's bypass, told ``admin off`` at once;
    nothing changes."""
    cfg = tmp_path / "motcomp.toml"
    cfg.write_text(f'include = ["{config_file("motcomp.toml")}"]\n')
    p_svc = free_tcp_port()
    with process(["run", "--config", str(cfg), "-l", loopback(p_svc)], tmp_path / "svc.log"), \
            open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
        wait_status(session)
        t0 = time.monotonic()
        r = reload_cmd(p_svc)
        took = time.monotonic() - t0
        # answered at once, not the command's whole wait for a reply (12 s) as if unreachable
        assert r.returncode == 1, r.stderr
        assert "failed: admin off (the service's config has [admin] enabled = false" in r.stderr
        assert took < CHANGE_TIMEOUT_S, took
        ep = ["-e", loopback(p_svc)]
        for argv in (["bypass", "on", "--axes", "rails_y"], ["profile", "fast"],
                     ["identify", "--live", "--axis", "rails_y", str(tmp_path / "id.mcap"),
                      "--out", str(tmp_path / "ident"), "--no-figures", "--force"]):
            r = subprocess.run(motcomp_cmd(*argv, *ep), capture_output=True, text=True,
                               env=subprocess_env(), timeout=60)
            assert r.returncode == 1, (argv, r.stderr)
            assert "admin off (the service's config has [admin] enabled = false" in r.stderr, \
                (argv, r.stderr)
        st = status(session)
        assert st["bypass"] == [a for a in AXES if a.startswith("hex")] and st["reloads"] == []


def test_bypass_off_without_axes_keeps_the_config_bypass(tmp_path: Path) -> None:
    """``motcomp bypass off`` with no axes re-enables only the axes the running config
    compensates: the hexapod, whose PID the example config bypasses, keeps it bypassed and gets
    its prediction back; named, an axis whose PID the config bypasses gets its PID back only
    where it has no prediction (there, compensation is the prediction)."""
    path = tmp_path / "motcomp.toml"
    path.write_text(BASE)
    svc = Service(load_config(path), ZenohEndpoints(), config_path=path)
    hexapod = [a for a, b in zip(AXES, svc.axes.bypass, strict=True) if b]
    assert hexapod and "rails_y" not in hexapod
    with running(svc) as run:
        assert sorted(svc.request_bypass(True)) == sorted(
            a for a, d in zip(AXES, svc.axes.driven, strict=True) if d)
        assert sorted(svc.request_bypass(False)) == sorted(hexapod)
        assert all(st["state"] != "off" for st in svc.status()["prediction"].values())
        assert svc.request_bypass(True, ["hex_z"]) == hexapod
        assert svc.status()["prediction"]["hex_z"]["state"] == "off"
        assert svc.request_bypass(False, ["hex_z"]) == hexapod  # predicted: PID stays off
        assert svc.status()["prediction"]["hex_z"]["state"] != "off"
        # the reply says which of the PID-bypassed axes prediction compensates
        reply = svc.admin("bypass", msgpack.packb({"on": False, "axes": ["hex_z"]}))
        assert reply["bypass"] == hexapod and "hex_z" in reply["predicted"], reply
        run.wait(10)
    base = tmp_path / "base.toml"  # the hexapod without prediction: named, its PID comes on
    base.write_text("\n".join(line for line in config_file("motcomp.toml").read_text()
                              .splitlines() if not line.startswith("prediction = ")))
    plain = tmp_path / "plain.toml"
    plain.write_text(f'include = ["{base}"]\n[admin]\nenabled = true\n')
    svc = Service(load_config(plain), ZenohEndpoints(), config_path=plain)
    with running(svc) as run:
        assert svc.request_bypass(False, ["hex_z"]) == [a for a in hexapod if a != "hex_z"]
        run.wait(10)
    reply = svc.admin("bypass", msgpack.packb({"on": False, "axes": ["rails_q"]}))
    assert reply["ok"] is False and "rails_q" in reply["error"]
