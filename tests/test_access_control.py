"""Access control (config/zenoh-acl.json5): only the "cueing" peer's setpoints reach the loop,
only an "operator" may call the admin endpoints, unauthenticated peers are refused."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

import msgpack
import pytest

from motcomp.io.wire import decode_output, encode_input
from motcomp.io.zenoh_io import free_tcp_port, loopback
from motcomp.resources import config_file
from tests.conftest import motcomp_cmd, subprocess_env
from tests.test_service_process import process

pytestmark = pytest.mark.slow


def client(port: int, user: str | None) -> Any:
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("connect/endpoints", json.dumps([loopback(port)]))
    if user:
        c.insert_json5("transport/auth/usrpwd",
                       json.dumps({"user": user, "password": f"{user}-secret"}))
    return zenoh.open(c)


def status(session: Any) -> dict[str, Any]:
    for reply in session.get("motcomp/status", timeout=2.0):
        if reply.ok is not None:
            out: dict[str, Any] = msgpack.unpackb(reply.ok.payload.to_bytes())
            return out
    raise AssertionError("no status reply")


def test_only_authorised_peers_move_the_platform(tmp_path: Path) -> None:
    import zenoh

    creds = tmp_path / "credentials.txt"
    creds.write_text("".join(f"{u}:{u}-secret\n" for u in ("cueing", "operator", "platform")))
    acl = tmp_path / "zenoh-acl.json5"
    acl.write_text(config_file("zenoh-acl.json5").read_text().replace(
        "/etc/motcomp/zenoh-credentials.txt", str(creds)))
    port = free_tcp_port()
    cfg = tmp_path / "service.toml"
    cfg.write_text(f'include = ["{config_file("motcomp.toml")}"]\n[admin]\nenabled = true\n'
                   f'[zenoh]\nconfig_file = "zenoh-acl.json5"\nlisten = ["{loopback(port)}"]\n')
    with process(["run", "--config", str(cfg)], tmp_path / "svc.log"):
        platform = client(port, "platform")
        out_sub = platform.declare_subscriber("platform/setpoint", zenoh.handlers.RingChannel(1))
        t_end = time.monotonic() + 20
        while True:
            try:
                status(platform)
                break
            except AssertionError:
                assert time.monotonic() < t_end, "service not up"
                time.sleep(0.3)

        def push(session: Any, value: float, n: int = 1500) -> None:
            pub = session.declare_publisher("sim/motion/setpoint")
            seq = int(time.time() * 1000)
            for k in range(n):
                pub.put(encode_input(seq + k, time.time(), {"rails_x": value}))
                time.sleep(0.001)
            pub.undeclare()

        def rails_x() -> float:
            s = out_sub.try_recv()
            assert s is not None
            return float(decode_output(s.payload.to_bytes())["pos"]["rails_x"])

        # an authenticated peer in the wrong role: its setpoints are dropped before the service
        operator = client(port, "operator")
        push(operator, 0.4)
        st = status(platform)
        assert st["frames"]["received"] == 0 and abs(rails_x()) < 1e-9
        # a peer without credentials is refused at connection: nothing it sends arrives
        anon = client(port, None)
        push(anon, 0.4, 300)
        anon.close()
        assert status(platform)["frames"]["received"] == 0 and abs(rails_x()) < 1e-9
        # the motion-cueing peer moves the platform
        cueing = client(port, "cueing")
        push(cueing, 0.2)
        assert status(platform)["frames"]["accepted"] > 1000
        assert rails_x() == pytest.approx(0.2, abs=1e-3)
        # admin: the operator may reload, the cueing peer may not (its query is dropped: no
        # reply, exit 3)
        env = subprocess_env()
        for user, expect in (("operator", 0), ("cueing", 3)):
            zc = tmp_path / f"{user}.json5"
            zc.write_text(json.dumps({"transport": {"auth": {"usrpwd": {
                "user": user, "password": f"{user}-secret"}}}}))
            p = subprocess.run(motcomp_cmd("reload", "-c", str(zc), "-e", loopback(port),
                                           "--timeout", "2"),
                               capture_output=True, text=True, env=env, timeout=60)
            assert p.returncode == expect, (user, p.stdout, p.stderr)
            assert expect == 0 or "access-control rule" in p.stderr, p.stderr
        out_sub.undeclare()
        for s in (operator, cueing, platform):
            s.close()
