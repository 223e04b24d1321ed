"""Scenario profiles: named gain sets in the config, switched live and bumplessly (in process,
and against a running service); an unknown profile is refused and the running one stays."""

from __future__ import annotations

import math
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import msgpack
import pytest

from motcomp.config import parse_config, read_toml, resolve_axes
from motcomp.core.tuning import tune
from motcomp.errors import ConfigError
from motcomp.io.wire import decode_output, encode_input
from motcomp.io.zenoh_io import ZenohEndpoints, first_reply, free_tcp_port, loopback, open_session
from motcomp.resources import config_file
from motcomp.runtime.service import Service
from tests._frames import assert_frames_within_limits
from tests.conftest import RAILS, motcomp_cmd, subprocess_env
from tests.test_reload import Y, assert_within_limits, running
from tests.test_service_process import process, wait_status

PROFILES = """
[profiles.normal]
description = "normal driving: the paper's tuning"
rule = "zn"

[profiles.fast]
description = "fast manoeuvres: less over-amplification"
rule = "amigo"

[profiles.fast.axes.rails_y]
gains = { kp = 3.0, ki_per_s = 40.0 }
"""


def config(extra: str = "") -> dict[str, Any]:
    """The example config with the profiles; ``extra`` top-level keys go first, tables after."""
    import tomllib

    top = "".join(ln + "\n" for ln in extra.splitlines() if not ln.startswith("[")
                  and "=" in ln and not extra.lstrip().startswith("["))
    tables = extra if extra.lstrip().startswith("[") else ""
    data = read_toml(config_file("motcomp.toml"))
    data.update(tomllib.loads(top + PROFILES + tables))
    return data


def test_profile_precedence() -> None:
    cfg = parse_config(config())
    base = resolve_axes(cfg)  # no active profile: the axes' own (optimised) gains
    own = cfg.axes["rails_x"].gains
    assert own is not None and base.gains[0] == own.to_gains()
    assert base.gains[0].kp != tune("zn", RAILS).gains.kp
    fast = resolve_axes(cfg, "fast")
    assert fast.gains[0] == tune("amigo", RAILS).gains  # the profile's rule for every axis
    assert (fast.gains[1].kp, fast.gains[1].ki) == (3.0, 40.0)  # its axis entry wins
    assert fast.bypass == base.bypass  # bypass comes from the axes unless the profile sets it
    active = parse_config(config('profile = "fast"\n'))
    assert resolve_axes(active).gains == fast.gains


@pytest.mark.parametrize(("extra", "msg"), [
    ('profile = "sport"\n', "profile 'sport' is not defined"),
    ("[profiles.x]\nrule = \"zn\"\ngains = { kp = 1.0 }\n", "either rule or gains"),
    ("[profiles.x.axes.rails_q]\nrule = \"zn\"\n", "not a configured axis"),
    ("[profiles.x]\nrule = \"pid\"\n", "unknown rule 'pid'"),
])
def test_bad_profiles_rejected(extra: str, msg: str) -> None:
    with pytest.raises(ConfigError, match=msg):
        parse_config(config(extra))


def test_profile_switch_in_process() -> None:
    """Switched between two ticks of the running loop, each profile's gains take over; an
    unknown profile changes nothing; the command stays within the limits throughout."""
    svc = Service(parse_config(config()), ZenohEndpoints())
    with running(svc) as run:
        for name, gains in (("fast", (3.0, 40.0)), ("normal", tune("zn", RAILS).gains),
                            (None, resolve_axes(parse_config(config())).gains[Y])):
            r = svc.admin("profile", msgpack.packb({"name": name}))
            assert r["ok"] and svc.cfg.profile == name and svc.status()["profile"] == name, r
            got = svc.axes.gains[Y]
            if isinstance(gains, tuple):  # the profile's own rails_y gains
                assert (got.kp, got.ki) == gains
            else:
                assert got == gains
            run.wait(200)
        kept = (svc.cfg, svc.axes, svc.params, svc.config_id, svc.config_version)
        r = svc.switch_profile("sport")
        assert not r["ok"] and "profile 'sport' is not defined" in r["error"]
        assert (svc.cfg, svc.axes, svc.params, svc.config_id, svc.config_version) == kept
    assert len(run.swaps()) == 3
    assert_within_limits(run, svc)


@pytest.mark.slow
def test_live_profile_switch_is_bumpless(tmp_path: Path) -> None:
    import zenoh

    cfg = tmp_path / "motcomp.toml"
    cfg.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[admin]\nenabled = true\n'
                   + PROFILES)
    port = free_tcp_port()
    stop = threading.Event()
    with process(["run", "--config", str(cfg), "-l", loopback(port)], tmp_path / "svc.log") \
            as svc, open_session(ZenohEndpoints(connect=(loopback(port),))) as session:
        out = session.declare_subscriber("platform/setpoint", zenoh.handlers.FifoChannel(100_000))
        wait_status(session)
        pub = session.declare_publisher("sim/motion/setpoint")

        def feed() -> None:
            k, t0 = 0, time.time()
            while not stop.is_set():
                pub.put(encode_input(k, t0 + k / 1000, {
                    "rails_y": 0.3 * math.sin(2 * math.pi * 0.3 * k / 1000)}))
                k += 1
                time.sleep(max(0.0, t0 + k / 1000 - time.time()))

        th = threading.Thread(target=feed, daemon=True)
        th.start()
        try:
            time.sleep(2.0)
            for name in ("fast", "normal", "none"):
                p = subprocess.run(motcomp_cmd("profile", name, "-e", loopback(port)),
                                   capture_output=True, text=True, env=subprocess_env(),
                                   timeout=60)
                assert p.returncode == 0, p.stderr
                assert p.stdout.startswith("no profile active (the config's base tuning)"
                                           if name == "none" else f"profile {name} active")
                st = msgpack.unpackb(first_reply(session, "motcomp/status", None, 2.0))
                assert st["profile"] == (None if name == "none" else name)
                assert st["profiles"] == ["fast", "normal", "paper"]
                time.sleep(1.0)
            p = subprocess.run(motcomp_cmd("profile", "sport", "-e", loopback(port)),
                               capture_output=True, text=True, env=subprocess_env(), timeout=60)
            assert p.returncode == 2 and "rejected: profile 'sport' is not defined" in p.stderr
            p = subprocess.run(motcomp_cmd("bypass", "on", "--axes", "rails_q", "-e",
                                           loopback(port)),
                               capture_output=True, text=True, env=subprocess_env(), timeout=60)
            assert p.returncode == 2 and "rejected:" in p.stderr and "rails_q" in p.stderr
        finally:
            stop.set()
            th.join()
        frames = []
        while (s := out.try_recv()) is not None:
            frames.append(decode_output(s.payload.to_bytes()))
        assert_frames_within_limits(frames, "rails_y", 2.0, 6.0)
        out.undeclare()
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=20) == 0
    log = (tmp_path / "svc.log").read_text()
    assert "switch to profile fast ok" in log and "switch to profile sport rejected" in log


def test_a_reload_keeps_the_profile_chosen_live(tmp_path: Path) -> None:
    """``motcomp profile fast`` then a reload (SIGHUP) of a file that sets no profile: fast
    stays active; a file that sets one wins; a file that no longer defines it: none."""
    path = tmp_path / "motcomp.toml"
    head = f'include = ["{config_file("motcomp.toml")}"]\n'
    path.write_text(head + PROFILES)
    svc = Service(parse_config(read_toml(path), str(path)), ZenohEndpoints(), config_path=path)
    svc.preparer.start(wait=True)
    with running(svc):
        assert svc.switch_profile("fast")["ok"]
        r = svc.reload()
        assert r["ok"] and svc.cfg.profile == "fast" and r["profile"] == "fast", r
        assert (svc.axes.gains[Y].kp, svc.axes.gains[Y].ki) == (3.0, 40.0)
        path.write_text(head + 'profile = "normal"\n' + PROFILES)  # the file's own: it wins
        assert svc.reload()["ok"] and svc.cfg.profile == "normal"
        path.write_text(head + PROFILES)  # none in the file, none chosen live since
        assert svc.reload()["ok"] and svc.cfg.profile is None
        assert svc.switch_profile("normal")["ok"]
        path.write_text(head + PROFILES[PROFILES.index("[profiles.fast]"):])  # normal gone
        r = svc.reload()
        assert r["ok"] and svc.cfg.profile is None, r


def test_a_profile_chosen_live_that_no_longer_fits_is_dropped_not_the_reload(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The profile chosen live cannot be applied over the reloaded file: the file applies, the
    profile is dropped and the log says why (the reload was refused for it, unsaid)."""
    path = tmp_path / "motcomp.toml"
    path.write_text(f'include = ["{config_file("motcomp.toml")}"]\n' + PROFILES)
    svc = Service(parse_config(read_toml(path), str(path)), ZenohEndpoints(), config_path=path)
    svc.preparer.start(wait=True)
    with running(svc):
        assert svc.switch_profile("fast")["ok"]

        def refuse(*_: object) -> None:
            raise ConfigError("rails_y: gains unstable with the new model")

        svc.preparer.prepare_profile = refuse  # type: ignore[method-assign,assignment]
        r = svc.reload()
        assert r["ok"] and svc.cfg.profile is None and svc.live_profile is None, r
    assert "profile fast (chosen live) does not fit the reloaded config (rails_y: gains " \
           "unstable with the new model): dropped" in caplog.text
