"""A clinic certificate authority and one TLS certificate per machine.

Links between machines (edge boxes and the analysis server) run Zenoh over TLS with mutual
authentication: every machine presents a certificate signed by the clinic CA and checks the
other side's certificate against that same CA. The certificate's common name is the machine
name (``edge-1``, ``server``), which the Zenoh access-control rules match
(``cert_common_names``), so a machine's rights follow from its certificate.

Keys are ECDSA P-256 in PKCS#8 PEM (what Zenoh's rustls accepts); private keys are written
with mode 0600. The CA private key stays with whoever runs ``gaitflow certs``; only
``ca.pem`` and the machine's own ``cert.pem``/``key.pem`` go to each machine.

Layout written by :func:`make_bundle`::

    OUT/ca.pem  OUT/ca-key.pem
    OUT/<machine>/cert.pem  OUT/<machine>/key.pem  OUT/<machine>/ca.pem
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from gaitflow.errors import ConfigError

_MACHINE = re.compile(r"^[a-z0-9][a-z0-9\-]{0,62}$")
# Names every certificate carries so that loopback tests and single-machine installs verify.
DEFAULT_SANS = ("localhost", "127.0.0.1")
DEFAULT_DAYS = 825


@dataclass(frozen=True)
class Issued:
    """Paths of one machine's TLS material."""

    machine: str
    cert: Path
    key: Path
    ca: Path


def check_machine(name: str) -> str:
    """A machine name is a DNS label: lowercase letters, digits and '-'."""
    if not isinstance(name, str) or not _MACHINE.match(name):
        raise ConfigError(f"machine name {name!r} must be a DNS label (lowercase a-z0-9-)")
    return name


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def _key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    data = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    # Create with 0600 from the start: no window in which the key is world-readable.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)


def _write_cert(path: Path, cert: x509.Certificate) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def make_ca(
    common_name: str = "gaitflow clinic CA", days: int = 3650
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A self-signed CA key and certificate (may sign end-entity certificates only)."""
    key = _key()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    now = _now()
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return key, cert


def _san(names: Iterable[str]) -> x509.SubjectAlternativeName:
    entries: list[x509.GeneralName] = []
    seen: set[str] = set()
    for n in names:
        if n in seen:
            continue
        seen.add(n)
        try:
            entries.append(x509.IPAddress(ipaddress.ip_address(n)))
        except ValueError:
            entries.append(x509.DNSName(n))
    return x509.SubjectAlternativeName(entries)


def issue(
    ca_key: ec.EllipticCurvePrivateKey,
    ca_cert: x509.Certificate,
    machine: str,
    sans: Sequence[str] = DEFAULT_SANS,
    days: int = DEFAULT_DAYS,
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A certificate for ``machine`` (CN = machine name) usable as TLS server and client.

    Both extended key usages are set because every machine both listens (router) or
    connects (edge client) and mutual TLS checks the client side too.
    """
    check_machine(machine)
    key = _key()
    now = _now()
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, machine)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_san((machine, *sans)), critical=False)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=True,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    return key, cert


def load_ca(out: Path) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate] | None:
    """The CA in ``out`` if there is one (so new machines join an existing clinic CA)."""
    ca_pem, ca_key_pem = out / "ca.pem", out / "ca-key.pem"
    if not (ca_pem.exists() and ca_key_pem.exists()):
        return None
    try:
        cert = x509.load_pem_x509_certificate(ca_pem.read_bytes())
        key = serialization.load_pem_private_key(ca_key_pem.read_bytes(), password=None)
    except ValueError as exc:
        raise ConfigError(f"{out}: cannot read the existing CA: {exc}") from exc
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ConfigError(f"{ca_key_pem}: CA key is not an EC key")
    return key, cert


def make_bundle(
    out: str | Path,
    machines: Sequence[str],
    sans: Sequence[str] = DEFAULT_SANS,
    days: int = DEFAULT_DAYS,
) -> dict[str, Issued]:
    """Write (or reuse) the clinic CA in ``out`` and a certificate per machine.

    Parameters
    ----------
    out : directory to write into (created).
    machines : machine names, e.g. ``("edge-1", "server")``; each is its cert's CN and a
        DNS SAN.
    sans : further subject alternative names on every certificate (IP addresses or DNS
        names), e.g. the network-namespace addresses used by tests.
    """
    if not machines:
        raise ConfigError("gaitflow certs: give at least one machine name")
    outp = Path(out)
    outp.mkdir(parents=True, exist_ok=True)
    existing = load_ca(outp)
    if existing is None:
        ca_key, ca_cert = make_ca()
        _write_key(outp / "ca-key.pem", ca_key)
        _write_cert(outp / "ca.pem", ca_cert)
    else:
        ca_key, ca_cert = existing
    issued: dict[str, Issued] = {}
    for m in machines:
        check_machine(m)
        key, cert = issue(ca_key, ca_cert, m, sans=sans, days=days)
        d = outp / m
        d.mkdir(parents=True, exist_ok=True)
        _write_key(d / "key.pem", key)
        _write_cert(d / "cert.pem", cert)
        _write_cert(d / "ca.pem", ca_cert)
        issued[m] = Issued(m, d / "cert.pem", d / "key.pem", d / "ca.pem")
    return issued


def tls_section(issued: Issued, mtls: bool = True) -> dict[str, object]:
    """Zenoh's ``transport/link/tls`` settings for a machine's own certificate."""
    return {
        "root_ca_certificate": str(issued.ca),
        "listen_private_key": str(issued.key),
        "listen_certificate": str(issued.cert),
        "connect_private_key": str(issued.key),
        "connect_certificate": str(issued.cert),
        "enable_mtls": bool(mtls),
    }
