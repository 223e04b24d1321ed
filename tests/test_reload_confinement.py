"""Reload confinement (docs/DEPLOYMENT.md, "Reload"; :mod:`motcomp.runtime.confine`): a reload
reads only regular, size-capped files under the service's config directory (and the files it
read at start-up); anything else is refused without being read, with one message whether the
file exists or not and nothing of its content.  An accepted ``reload --config FILE`` makes FILE
the config in force (status, SIGHUP, the recorder)."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from motcomp.config import config_hash, load_config
from motcomp.errors import ConfigError
from motcomp.io.zenoh_io import ZenohEndpoints, free_tcp_port, loopback, open_session
from motcomp.record.recorder import service_info
from motcomp.resources import config_file
from motcomp.runtime.confine import MAX_CONFIG_BYTES, Confinement
from tests.conftest import motcomp_cmd, subprocess_env
from tests.test_reload import BASE, reload_cmd, status
from tests.test_service_process import process, wait_status

SECRET = "TOPSECRET-rate"


def layout(tmp: Path) -> dict[str, Path]:
    """A config directory ``etc`` and, beside it, ``outside`` with a TOML file whose value a
    validation error would quote; in ``etc``: files that lead outside or are not plain."""
    etc, out = tmp / "etc", tmp / "outside"
    etc.mkdir()
    out.mkdir()
    secret = out / "secret.toml"
    secret.write_text(f'{BASE}[loop]\nrate_hz = "{SECRET}"\n')
    site = etc / "site.toml"
    site.write_text(BASE)
    (etc / "link.toml").symlink_to(secret)
    (etc / "include-out.toml").write_text('include = ["../outside/secret.toml"]\n')
    (etc / "big.toml").write_text(BASE + "# padding\n" * (MAX_CONFIG_BYTES // 10 + 1))
    os.mkfifo(etc / "fifo.toml")
    return {"site": site, "secret": secret, "etc": etc}


REFUSED = {  # name -> path relative to tmp (or absolute), what the refusal says
    "/dev/zero": ("/dev/zero", "refused"),
    "/etc/passwd": ("/etc/passwd", "refused"),
    "/proc/self/environ": ("/proc/self/environ", "refused"),
    "file outside": ("outside/secret.toml", "refused"),
    "missing outside": ("outside/missing.toml", "refused"),
    "dot-dot escape": ("etc/../outside/secret.toml", "refused"),
    "symlink escaping": ("etc/link.toml", "refused"),
    "include escaping": ("etc/include-out.toml", "include"),
    "oversize": ("etc/big.toml", "bytes"),
    "fifo": ("etc/fifo.toml", "not a regular file"),
}


def target(tmp: Path, rel: str) -> Path:
    return Path(rel) if rel.startswith("/") else tmp / rel


# --- the rule, in process ----------------------------------------------------------------------
def test_confinement_refuses_without_reading(tmp_path: Path) -> None:
    files = layout(tmp_path)
    c = Confinement(files["site"], [config_file("motcomp.toml")])
    assert c.root == files["etc"].resolve()
    assert c.check(files["site"]) == files["site"].resolve()  # includes the packaged base
    assert c.check("site.toml") == files["site"].resolve()  # relative: to the directory
    messages = {}
    for name, (rel, reason) in REFUSED.items():
        with pytest.raises(ConfigError) as err:
            c.check(target(tmp_path, rel))
        text = str(err.value)
        assert reason in text and SECRET not in text, (name, text)
        messages[name] = text
    # existing or missing, outside is outside: one message but for the path asked for
    assert (messages["file outside"].replace("secret", "X")
            == messages["missing outside"].replace("missing", "X"))
    assert "config directory" in messages["file outside"]
    assert "include" in messages["include escaping"]
    # an include inside the directory is fine, a file inside it that is missing says so
    (files["etc"] / "base.toml").write_text(BASE)
    (files["etc"] / "top.toml").write_text('include = ["base.toml"]\n')
    assert c.check(files["etc"] / "top.toml") == (files["etc"] / "top.toml").resolve()
    with pytest.raises(ConfigError, match="cannot read"):
        c.check(files["etc"] / "nothing.toml")
    # a missing include names the file including it, as `motcomp config check` does
    (files["etc"] / "typo.toml").write_text('include = ["base.toml", "desing.toml"]\n')
    with pytest.raises(ConfigError) as err:
        c.check(files["etc"] / "typo.toml")
    assert str(err.value) == (f"{(files['etc'] / 'desing.toml').resolve()}: cannot read: No such "
                              f"file or directory (included by "
                              f"{(files['etc'] / 'typo.toml').resolve()})")


def test_confinement_counts_files(tmp_path: Path) -> None:
    etc = tmp_path / "etc"
    etc.mkdir()
    for k in range(40):  # a chain of 40 includes
        (etc / f"f{k}.toml").write_text(f'include = ["f{k + 1}.toml"]\n' if k < 39 else "")
    with pytest.raises(ConfigError, match="more than 32 files"):
        Confinement(etc / "f0.toml").check(etc / "f0.toml")


# --- against the running service ---------------------------------------------------------------
@pytest.mark.slow
def test_reload_refuses_files_outside_and_keeps_running(tmp_path: Path) -> None:
    files = layout(tmp_path)
    p_svc = free_tcp_port()
    with process(["run", "--config", str(files["site"]), "-l", loopback(p_svc)],
                 tmp_path / "svc.log") as svc, \
            open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
        st0 = wait_status(session)
        for name, (rel, reason) in REFUSED.items():
            r = reload_cmd(p_svc, target(tmp_path, rel))  # a reply, or exit 3 after 5 s
            assert r.returncode == 2, (name, r.returncode, r.stderr)  # a refused request
            assert reason in r.stderr and SECRET not in r.stderr + r.stdout, (name, r.stderr)
            st = status(session)
            assert st["config"]["version"] == 1 and st["config"]["hash"] == st0["config"]["hash"]
            assert st["reloads"][-1]["ok"] is False and SECRET not in str(st["reloads"])
        st1 = status(session)
        assert st1["ticks"] > st0["ticks"] + 1000  # it kept ticking
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=30) == 0
    log = (tmp_path / "svc.log").read_text()
    assert SECRET not in log and log.count("reload rejected") == len(REFUSED)


@pytest.mark.slow
def test_reload_config_file_becomes_the_config_in_force(tmp_path: Path) -> None:
    files = layout(tmp_path)
    other = files["etc"] / "other.toml"
    other.write_text(BASE + '[defaults]\nrule = "amigo"\n')
    p_svc = free_tcp_port()

    def in_force(st: dict[str, Any], path: Path) -> None:
        assert st["config"]["path"] == str(path)
        assert st["config"]["hash"] == config_hash(load_config(path))
        info, attachment = service_info(st)  # what `motcomp record` attaches
        assert info["config_path"] == str(path) and attachment is not None

    with process(["run", "--config", str(files["site"]), "-l", loopback(p_svc)],
                 tmp_path / "svc.log") as svc, \
            open_session(ZenohEndpoints(connect=(loopback(p_svc),))) as session:
        in_force(wait_status(session), files["site"])
        r = reload_cmd(p_svc, other)
        assert r.returncode == 0, r.stderr
        st = status(session)
        assert st["config"]["version"] == 2
        in_force(st, other)
        # SIGHUP re-reads the config in force: other.toml, not the start-up file
        other.write_text(BASE + '[defaults]\nrule = "zn"\nfilter_n = 8\n')
        svc.send_signal(signal.SIGHUP)
        t_end = time.monotonic() + 20
        while status(session)["config"]["version"] != 3 and time.monotonic() < t_end:
            time.sleep(0.1)
        st = status(session)
        assert st["config"]["version"] == 3 and st["reloads"][-1]["path"] == str(other)
        in_force(st, other)
        # a refused reload --config leaves the config in force as it was
        assert reload_cmd(p_svc, files["secret"]).returncode == 2
        in_force(status(session), other)
        # a profile switch: the same file, its hash with the profile, still attached
        r = subprocess.run(motcomp_cmd("profile", "fast", "-e", loopback(p_svc)),
                           capture_output=True, text=True, env=subprocess_env(), timeout=60)
        assert r.returncode == 0, r.stderr
        st = status(session)
        assert st["profile"] == "fast" and st["config"]["path"] == str(other)
        assert service_info(st)[1] is not None
        svc.send_signal(signal.SIGTERM)
        assert svc.wait(timeout=30) == 0
    log = (tmp_path / "svc.log").read_text()
    assert f"config in force is now {other}" in log
