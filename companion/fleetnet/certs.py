"""The fleet's TLS files: a fleet CA and one certificate per group companion (mutual TLS over Zenoh).

``python -m companion certs DIR --groups N --hosts H1 .. HN`` calls :func:`new_fleet_certs`, which
writes to ``DIR``::

    ca.pem              the fleet CA's certificate (public: every companion trusts it)
    ca.key              the CA's private key (mode 600; keep it off the companions, it signs new members)
    companion-g<G>.pem  group G's certificate, signed by the CA, for the host(s) of group G
    companion-g<G>.key  its private key (mode 600; only the Pi of group G needs it)

Every group certificate serves as server certificate (its listen endpoint) and as client
certificate (its connections to the other groups): extended key usage ``serverAuth`` and
``clientAuth``. Zenoh's TLS checks the name of the endpoint it connects to (``tls/10.0.0.12:7447``)
against the server's subjectAltName, so each group's certificate names its host: an IP address
(an IP SAN) or a DNS name, several separated by commas (``10.0.0.12,pi2.local``). Keys are ECDSA
P-256, PKCS#8 PEM. ``[zenoh.tls] certs_dir`` (:mod:`.config`) picks a group's files by the group.

:func:`check_group_certificate` is what a companion checks before its session opens: the
certificate is signed by the CA, valid now, and names the host of its listen endpoint, so a
mismatch is reported with the file and the fix instead of as silent TLS handshake failures.
The Raspberry Pis have no real-time clock: certificates start one day before they are made
(``BACKDATE``), and a Pi's clock must be set (NTP, GPS) before the companions connect.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import re
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from companion.keyfiles import write_private_text

from .config import CA_CERT, group_user

__all__ = ["BACKDATE", "CA_CERT", "CA_KEY", "group_cert_name", "group_key_name", "parse_hosts", "new_fleet_certs",
           "check_group_certificate"]

CA_KEY = "ca.key"
#: Certificates are valid from this long before they are made (Pis without a real-time clock).
BACKDATE = datetime.timedelta(days=1)
_DNS_RE = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")


def group_cert_name(group: int) -> str:
    """File name of 0-based ``group``'s certificate (named like its Zenoh user)."""
    return f"{group_user(group)}.pem"


def group_key_name(group: int) -> str:
    """File name of 0-based ``group``'s private key."""
    return f"{group_user(group)}.key"


def parse_hosts(text: str) -> list[x509.GeneralName]:
    """The subjectAltName entries of one group's ``HOST[,HOST...]`` (IP addresses or DNS names);
    ``ValueError`` naming a host that is neither."""
    names: list[x509.GeneralName] = []
    for host in text.split(","):
        host = host.strip().strip("[]")
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
            continue
        except ValueError:
            pass
        if not _DNS_RE.match(host):
            raise ValueError(f"host {host!r} is neither an IP address nor a DNS name")
        names.append(x509.DNSName(host.lower()))
    return names


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key) -> str:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption()).decode("ascii")


def _cert_pem(cert: x509.Certificate) -> str:
    return cert.public_bytes(serialization.Encoding.PEM).decode("ascii")


def _write_public_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    with os.fdopen(fd, "w", encoding="ascii") as fh:
        fh.write(text)
    os.chmod(tmp, 0o644)
    tmp.replace(path)


def new_fleet_certs(out_dir, n_groups: int, hosts: list[str] | None = None, days: int = 1095,
                    overwrite: bool = False, name: str = "aerial skeleton fleet") -> list[Path]:
    """Write a fleet CA and one certificate per group to ``out_dir`` (see the module docstring).

    ``hosts``: one ``HOST[,HOST...]`` per group (default ``127.0.0.1`` for every group). Refuses,
    before writing anything, when a file exists and ``overwrite`` is false. Returns the paths
    written. ``ValueError`` names the problem."""
    if n_groups < 1:
        raise ValueError(f"groups must be at least 1, got {n_groups}")
    if not 1 <= days <= 36500:
        raise ValueError(f"days must be in 1..36500, got {days}")
    hosts = list(hosts) if hosts else ["127.0.0.1"] * n_groups
    if len(hosts) != n_groups:
        raise ValueError(f"hosts lists {len(hosts)} hosts for {n_groups} groups (one per group, in group order)")
    sans = [parse_hosts(h) for h in hosts]
    out_dir = Path(out_dir)
    paths = [out_dir / CA_CERT, out_dir / CA_KEY]
    for g in range(n_groups):
        paths += [out_dir / group_cert_name(g), out_dir / group_key_name(g)]
    existing = [str(p) for p in paths if p.exists()]
    if existing and not overwrite:
        raise ValueError(f"{', '.join(existing)} exist{'s' if len(existing) == 1 else ''} "
                         "(refusing to overwrite; --overwrite replaces the CA and every certificate)")
    out_dir.mkdir(parents=True, exist_ok=True)

    now = datetime.datetime.now(datetime.timezone.utc)
    start, end = now - BACKDATE, now + datetime.timedelta(days=days)
    ca_key = _new_key()
    ca_name = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, name),
                         x509.NameAttribute(NameOID.COMMON_NAME, f"{name} CA")])
    ca_ski = x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key())
    ca_cert = (
        x509.CertificateBuilder()
        .subject_name(ca_name).issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start).not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                     content_commitment=False, key_encipherment=False, data_encipherment=False,
                                     key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(ca_ski, critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    written = []
    write_private_text(out_dir / CA_KEY, _key_pem(ca_key), overwrite=True)
    _write_public_text(out_dir / CA_CERT, _cert_pem(ca_cert))
    written += [out_dir / CA_CERT, out_dir / CA_KEY]
    for g, san in enumerate(sans):
        key = _new_key()
        subject = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, name),
                             x509.NameAttribute(NameOID.COMMON_NAME, group_user(g))])
        cert = (
            x509.CertificateBuilder()
            .subject_name(subject).issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(start).not_valid_after(end)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                                         content_commitment=False, key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(san), critical=False)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ca_ski), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        write_private_text(out_dir / group_key_name(g), _key_pem(key), overwrite=True)
        _write_public_text(out_dir / group_cert_name(g), _cert_pem(cert))
        written += [out_dir / group_cert_name(g), out_dir / group_key_name(g)]
    return written


def _load_cert(path: Path, what: str) -> x509.Certificate:
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None
    except ValueError:
        raise ValueError(f"{path}: not a PEM certificate ({what})") from None


def check_group_certificate(cert_path, ca_path, host: str | None, now: datetime.datetime | None = None) -> None:
    """``ValueError`` unless the certificate at ``cert_path`` is signed by the CA at ``ca_path``,
    valid at ``now`` (default: the clock) and names ``host`` (an IP address or DNS name; ``None``:
    any) in its subjectAltName."""
    cert_path, ca_path = Path(cert_path), Path(ca_path)
    cert = _load_cert(cert_path, "group certificate")
    ca = _load_cert(ca_path, "fleet CA certificate")
    try:
        cert.verify_directly_issued_by(ca)
    except (InvalidSignature, ValueError, TypeError) as exc:
        raise ValueError(f"{cert_path}: not signed by the fleet CA {ca_path} ({type(exc).__name__}); "
                         "copy the certificate and the CA from the same `python -m companion certs` run") from None
    now = now or datetime.datetime.now(datetime.timezone.utc)
    for c, p in ((cert, cert_path), (ca, ca_path)):
        if not c.not_valid_before_utc <= now <= c.not_valid_after_utc:
            raise ValueError(f"{p}: valid {c.not_valid_before_utc:%Y-%m-%d %H:%M} to {c.not_valid_after_utc:%Y-%m-%d %H:%M} "
                             f"UTC, not now ({now:%Y-%m-%d %H:%M} UTC; is this computer's clock set?)")
    if host is None:
        return
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        san = x509.SubjectAlternativeName([])
    wanted = parse_hosts(host)[0]
    names = [str(n.value) for n in san]
    if isinstance(wanted, x509.IPAddress):
        ok = wanted.value in san.get_values_for_type(x509.IPAddress)
    else:
        ok = wanted.value in [n.lower() for n in san.get_values_for_type(x509.DNSName)]
    if not ok:
        raise ValueError(f"{cert_path}: made for {', '.join(names) or 'no host'}, not {host} (this group's endpoint); "
                         "make the certificates with --hosts naming each group's endpoint host")
