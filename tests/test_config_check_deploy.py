"""``motcomp config check`` checks the zenoh deployment's files as the start-up does (one
implementation, motcomp/io/zenoh_deploy.py): the zenoh config and every file it names exist,
parse and are readable, secrets (credentials, private keys) are mode 600, nothing is writable by
group or others; each problem names the file, the key and the rule, and both refuse (exit 2)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from motcomp.cli import main
from motcomp.resources import config_file
from tests.conftest import ROOT, motcomp_cmd, subprocess_env

CREDS_KEY = "transport/auth/usrpwd/dictionary_file"


def service_toml(tmp_path: Path, zenoh_file: str) -> Path:
    cfg = tmp_path / "motcomp.toml"
    cfg.write_text(f'include = ["{config_file("motcomp.toml")}"]\n'
                   f'[zenoh]\nconfig_file = "{zenoh_file}"\n')
    return cfg


def acl_deployment(tmp_path: Path, creds_mode: int | None = 0o600) -> Path:
    """The shipped ACL config beside a service config; its credentials file made with
    ``creds_mode`` (None: not made, as DEPLOYMENT.md once forgot to)."""
    creds = tmp_path / "zenoh-credentials.txt"
    if creds_mode is not None:
        creds.write_text("cueing:cueing-secret\n")
        creds.chmod(creds_mode)
    (tmp_path / "zenoh-acl.json5").write_text(config_file("zenoh-acl.json5").read_text()
                                              .replace("/etc/motcomp/zenoh-credentials.txt",
                                                       str(creds)))
    return service_toml(tmp_path, "zenoh-acl.json5")


def check(cfg: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(["config", "check", str(cfg)])
    out = capsys.readouterr()
    return code, out.out, out.err


def start(cfg: Path) -> subprocess.CompletedProcess[str]:
    """``motcomp run`` of ``cfg``, expected to refuse before it opens zenoh."""
    return subprocess.run(motcomp_cmd("run", "--config", str(cfg)), capture_output=True,
                          text=True, env=subprocess_env(), timeout=60)


def test_missing_credentials_refused_by_check_and_start_up_alike(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = acl_deployment(tmp_path, creds_mode=None)
    code, out, err = check(cfg, capsys)
    problem = f"{tmp_path / 'zenoh-credentials.txt'} ({CREDS_KEY}): does not exist"
    assert code == 2 and problem in err and "OK" not in out
    run = start(cfg)
    assert run.returncode == 2 and problem in run.stderr, run.stderr


@pytest.mark.parametrize("mode", [0o640, 0o604, 0o660])
def test_credentials_readable_by_others_refused(tmp_path: Path, mode: int,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    cfg = acl_deployment(tmp_path, creds_mode=mode)
    code, _, err = check(cfg, capsys)
    assert code == 2
    assert f"({CREDS_KEY}): mode {mode:04o} gives group/others access to a secret" in err
    run = start(cfg)
    assert run.returncode == 2 and f"mode {mode:04o}" in run.stderr, run.stderr


def test_the_documented_deployment_passes(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = check(acl_deployment(tmp_path), capsys)
    assert code == 0, err
    assert f"zenoh: a session opens with {tmp_path / 'zenoh-acl.json5'} (listening on" in out


def test_zenoh_config_itself(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = service_toml(tmp_path, "zenoh.json5")
    zfile = tmp_path / "zenoh.json5"
    code, _, err = check(cfg, capsys)
    assert code == 2 and f"{zfile} ([zenoh] config_file): does not exist" in err
    zfile.write_text("{ mode: 'peer', access_control: { enabled: tru } }")
    code, _, err = check(cfg, capsys)
    assert code == 2 and f"{zfile} ([zenoh] config_file): does not parse" in err
    # a group-writable ACL lets others rewrite the rules
    zfile.write_text("{ mode: 'peer' }")
    zfile.chmod(0o664)
    code, _, err = check(cfg, capsys)
    assert code == 2 and "mode 0664 lets group/others write it" in err
    # a password held inline makes the config a secret
    zfile.write_text('{ transport: { auth: { usrpwd: { user: "motcomp", password: "pw" } } } }')
    zfile.chmod(0o644)
    code, _, err = check(cfg, capsys)
    assert code == 2 and "(it holds transport/auth/usrpwd/password)" in err
    zfile.chmod(0o600)
    assert check(cfg, capsys)[0] == 0


def test_rules_zenoh_refuses_are_reported(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """What zenoh itself reads at start-up (the ACL's references) is read by the check."""
    cfg = acl_deployment(tmp_path)
    zfile = tmp_path / "zenoh-acl.json5"
    zfile.write_text(zfile.read_text().replace('subjects: ["platform"] }',
                                               'subjects: ["platforms"] }'))
    code, _, err = check(cfg, capsys)
    assert code == 2 and "zenoh refuses the deployment" in err
    assert "Subject 'platforms'" in err


def test_tls_material(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    certs = tmp_path / "tls"
    subprocess.run([sys.executable, str(ROOT / "tools" / "make_test_certs.py"), str(certs)],
                   check=True, capture_output=True, timeout=60)
    (tmp_path / "zenoh-tls.json5").write_text(
        config_file("zenoh-tls.json5").read_text().replace("/etc/motcomp/tls", str(certs)))
    cfg = service_toml(tmp_path, "zenoh-tls.json5")
    with cfg.open("a") as fh:
        fh.write('listen = ["tls/127.0.0.1:7447"]\n')
    code, out, err = check(cfg, capsys)
    assert code == 0, err
    assert "listening on tls" in out
    # every file named, each problem on its own line with its key
    (certs / "motcomp-key.pem").chmod(0o644)
    (certs / "ca.pem").rename(certs / "ca-old.pem")
    (certs / "motcomp.pem").chmod(0o666)
    code, _, err = check(cfg, capsys)
    assert code == 2 and "3 problems" in err
    assert (f"{certs / 'motcomp-key.pem'} (transport/link/tls/listen_private_key): mode 0644 "
            "gives group/others access to a secret") in err
    assert f"{certs / 'ca.pem'} (transport/link/tls/root_ca_certificate): does not exist" in err
    assert (f"{certs / 'motcomp.pem'} (transport/link/tls/listen_certificate): mode 0666 "
            "lets group/others write it") in err
    run = start(cfg)
    assert run.returncode == 2 and "3 problems" in run.stderr, run.stderr
    # files in order but a key that is no key: zenoh's own reading refuses it
    (certs / "motcomp-key.pem").chmod(0o600)
    (certs / "ca-old.pem").rename(certs / "ca.pem")
    (certs / "motcomp.pem").chmod(0o644)
    (certs / "motcomp-key.pem").write_text("not a key\n")
    code, _, err = check(cfg, capsys)
    assert code == 2 and "zenoh refuses the deployment" in err and "listening on tls" in err
