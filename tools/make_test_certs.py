"""Make a test certificate authority and one certificate per motcomp role, for the mutual-TLS
deployment (config/zenoh-tls.json5, docs/DEPLOYMENT.md section 6).

    pip install cryptography
    python tools/make_test_certs.py /etc/motcomp/tls --host motion-pc --ip 192.0.2.10

writes into DIR: ``ca.pem`` (the CA's certificate; its key ``ca-key.pem`` too, to sign more
later) and, for each role, ``ROLE.pem`` and ``ROLE-key.pem``, whose certificate's common name
is the role: ``motcomp`` (the service), ``cueing``, ``operator``, ``platform`` -- the names the
access-control rules of config/zenoh-tls.json5 match.  The service's certificate also names
the hosts the clients connect to (``--host``, ``--ip``; localhost and 127.0.0.1 always), which
they verify.  Private keys are written with mode 600, nothing is overwritten.  For a test bench
or a lab: a site with its own CA signs the same names with it instead.
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import os
from collections.abc import Sequence
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

ROLES = ("motcomp", "cueing", "operator", "platform")
"""Common names: the service first, then the client roles."""


def _write(path: Path, data: bytes, mode: int) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def make_certs(out: Path, roles: Sequence[str] = ROLES, hosts: Sequence[str] = (),
               ips: Sequence[str] = (), days: int = 365) -> list[Path]:
    """Write the CA and one key and certificate per role into ``out`` (created); the paths
    written.  Raises FileExistsError rather than overwrite a file."""
    out.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.UTC)
    valid = (now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=days))
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "motcomp test CA")])
    ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name)
          .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
          .not_valid_before(valid[0]).not_valid_after(valid[1])
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False,
                                       False), critical=True)
          .sign(ca_key, hashes.SHA256()))
    written = [out / "ca.pem", out / "ca-key.pem"]
    _write(written[0], ca.public_bytes(serialization.Encoding.PEM), 0o644)
    _write(written[1], _key_pem(ca_key), 0o600)
    names: list[x509.GeneralName] = [x509.DNSName(h) for h in ("localhost", *hosts)]
    names += [x509.IPAddress(ipaddress.ip_address(a)) for a in ("127.0.0.1", *ips)]
    for i, role in enumerate(roles):
        key = ec.generate_private_key(ec.SECP256R1())
        builder = (x509.CertificateBuilder()
                   .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, role)]))
                   .issuer_name(ca_name).public_key(key.public_key())
                   .serial_number(x509.random_serial_number())
                   .not_valid_before(valid[0]).not_valid_after(valid[1])
                   .add_extension(x509.BasicConstraints(ca=False, path_length=None),
                                  critical=True)
                   .add_extension(x509.ExtendedKeyUsage(
                       [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                       critical=False))
        # the service is the server the clients verify; every role also authenticates as a
        # client (mutual TLS), whose certificate must name some host too
        builder = builder.add_extension(x509.SubjectAlternativeName(
            names if i == 0 else [x509.DNSName(role)]), critical=False)
        cert = builder.sign(ca_key, hashes.SHA256())
        pem, key_path = out / f"{role}.pem", out / f"{role}-key.pem"
        _write(pem, cert.public_bytes(serialization.Encoding.PEM), 0o644)
        _write(key_path, _key_pem(key), 0o600)
        written += [pem, key_path]
    return written


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="directory to write into (created)")
    ap.add_argument("--host", action="append", default=[], metavar="NAME",
                    help="a DNS name of the service's host (repeatable)")
    ap.add_argument("--ip", action="append", default=[], metavar="ADDRESS",
                    help="an IP address of the service's host (repeatable)")
    ap.add_argument("--days", type=int, default=365, help="validity (default 365)")
    args = ap.parse_args()
    for path in make_certs(args.out, hosts=args.host, ips=args.ip, days=args.days):
        print(path)


if __name__ == "__main__":
    main()
