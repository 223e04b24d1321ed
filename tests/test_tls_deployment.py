"""The mutual-TLS deployment (config/zenoh-tls.json5, certificates made by
tools/make_test_certs.py), the service as a subprocess on loopback: a client with the cueing
certificate drives it; a client without a certificate, or with one from another CA, cannot
connect; the operator's certificate reloads but moves nothing, and no role's certificate gets a
forged ``platform/setpoint`` to the platform bridge."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from motcomp.io.zenoh_io import free_tcp_port
from motcomp.resources import config_file
from tests.conftest import ROOT, motcomp_cmd, subprocess_env
from tests.test_access_control import (
    ROLES,
    assert_no_forged_setpoints,
    newest_rails_x,
    push_setpoints,
    service,
    status,
    wait_status,
    zenoh_session,
)

pytestmark = pytest.mark.slow


def make_certs(out: Path) -> Path:
    subprocess.run([sys.executable, str(ROOT / "tools" / "make_test_certs.py"), str(out)],
                   check=True, capture_output=True, timeout=60)
    return out


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_certs(tmp_path_factory.mktemp("tls"))


def tls_settings(certs: Path, role: str | None) -> dict[str, Any]:
    """A client's ``transport/link/tls`` with ``role``'s certificate (None: the CA only)."""
    tls: dict[str, Any] = {"root_ca_certificate": str(certs / "ca.pem")}
    if role:
        tls |= {"enable_mtls": True, "connect_certificate": str(certs / f"{role}.pem"),
                "connect_private_key": str(certs / f"{role}-key.pem")}
    return tls


def tls_client(endpoint: str, certs: Path, role: str | None, mode: str = "client",
               ca: Path | None = None) -> Any:
    settings = tls_settings(certs, role)
    if ca is not None:
        settings["root_ca_certificate"] = str(ca / "ca.pem")
    return zenoh_session(endpoint, mode, transport__link__tls=settings)


def when_up(open_session: Callable[[], Any], timeout_s: float = 20.0) -> Any:
    """``open_session()`` once the service accepts it (a client fails while it starts)."""
    t_end = time.monotonic() + timeout_s
    while True:
        try:
            return open_session()
        except Exception:
            assert time.monotonic() < t_end, "service not up"
            time.sleep(0.3)


def test_tls_deployment(tmp_path: Path, certs: Path) -> None:
    import zenoh

    zfile = tmp_path / "zenoh-tls.json5"
    zfile.write_text(config_file("zenoh-tls.json5").read_text().replace(
        "/etc/motcomp/tls", str(certs)))
    endpoint = f"tls/127.0.0.1:{free_tcp_port()}"
    with service(tmp_path, zfile, endpoint):
        operator = when_up(lambda: tls_client(endpoint, certs, "operator"))
        wait_status(operator)
        bridge = tls_client(endpoint, certs, "platform")
        out_sub = bridge.declare_subscriber("platform/setpoint", zenoh.handlers.RingChannel(1))
        sessions = [operator, bridge]
        try:
            # no client certificate, or one signed by another CA (common name "cueing"): the
            # TLS handshake fails, no session
            rogue = make_certs(tmp_path / "rogue")
            for refused in (lambda: tls_client(endpoint, certs, None),
                            lambda: tls_client(endpoint, rogue, "cueing", ca=certs)):
                with pytest.raises(zenoh.ZError, match="Unable to connect"):
                    refused().close()
            # the operator's certificate: setpoints dropped, reload allowed
            push_setpoints(operator, 0.4)
            assert status(operator)["frames"]["received"] == 0
            assert abs(newest_rails_x(out_sub)) < 1e-9
            env = subprocess_env()
            # the operator's waits as long as a reload may take to prepare, the refused one 2 s
            for role, expect, wait in (("operator", 0, "15"), ("cueing", 3, "2")):
                zc = tmp_path / f"{role}.json5"
                zc.write_text(json.dumps({"listen": {"endpoints": []}, "transport": {"link": {
                    "tls": tls_settings(certs, role)}}}))
                p = subprocess.run(motcomp_cmd("reload", "-c", str(zc), "-e", endpoint,
                                               "--timeout", wait),
                                   capture_output=True, text=True, env=env, timeout=60)
                assert p.returncode == expect, (role, p.stdout, p.stderr)
            # the cueing computer's certificate moves the platform
            cueing = tls_client(endpoint, certs, "cueing")
            sessions.append(cueing)
            push_setpoints(cueing, 0.2)
            assert status(cueing)["frames"]["accepted"] > 1000
            assert newest_rails_x(out_sub) == pytest.approx(0.2, abs=1e-3)
            out_sub.undeclare()
            # no role's certificate gets a platform/setpoint to the bridge, as client or peer
            forgers = {f"{role} ({mode})": tls_client(endpoint, certs, role, mode)
                       for mode in ("client", "peer") for role in ROLES}
            sessions += forgers.values()
            assert_no_forged_setpoints(bridge, forgers)
        finally:
            for s in sessions:
                s.close()


def test_tls_and_password_deployments_share_their_rules() -> None:
    """The two shipped configs differ in their subjects' key only (one set of rules)."""
    import zenoh

    acl = [json.loads(zenoh.Config.from_file(str(config_file(name))).get_json("access_control"))
           for name in ("zenoh-acl.json5", "zenoh-tls.json5")]
    assert acl[0]["enabled"] and acl[0]["default_permission"] == "deny"
    for key in ("enabled", "default_permission", "rules", "policies"):
        assert acl[0][key] == acl[1][key], key
    by_name = [{s["id"]: s.get(k) for s in a["subjects"]}
               for a, k in zip(acl, ("usernames", "cert_common_names"), strict=True)]
    assert by_name[0] == by_name[1]
    assert all(set(names) <= set(ROLES) for names in by_name[0].values())


def test_a_tcp_endpoint_under_the_tls_config_is_named_before_zenoh_refuses_it(
        tmp_path: Path, certs: Path) -> None:
    """The shipped TLS config allows the tls protocol only: a service config that listens on
    tcp/ (or a -l/-e that says so) is bad input, exit 2 naming the endpoint and the rule, from
    ``motcomp run`` and ``motcomp config check`` alike (zenoh's own refusal exited 1)."""
    zfile = tmp_path / "zenoh-tls.json5"
    zfile.write_text(config_file("zenoh-tls.json5").read_text().replace(
        "/etc/motcomp/tls", str(certs)))
    tcp = f"tcp/127.0.0.1:{free_tcp_port()}"
    cfg = tmp_path / "service.toml"
    cfg.write_text(f'include = ["{config_file("motcomp.toml")}"]\n'
                   f'[zenoh]\nconfig_file = "{zfile.name}"\nlisten = ["{tcp}"]\n')
    env = subprocess_env()
    rule = (f"listen endpoint '{tcp}': protocol 'tcp' is not allowed by {zfile} "
            "(transport/link/protocols = ['tls']): use tls/ endpoints")
    for args in (["run", "--config", str(cfg)], ["config", "check", str(cfg)]):
        p = subprocess.run(motcomp_cmd(*args), capture_output=True, text=True, env=env,
                           timeout=60)
        assert p.returncode == 2, (args, p.stdout, p.stderr)
        assert rule in p.stderr and "Traceback" not in p.stderr, p.stderr
    tls = f"tls/127.0.0.1:{free_tcp_port()}"  # a tls/ listener: accepted
    cfg.write_text(cfg.read_text().replace(tcp, tls))
    p = subprocess.run(motcomp_cmd("config", "check", str(cfg)), capture_output=True, text=True,
                       env=env, timeout=60)
    assert p.returncode == 0, p.stderr
