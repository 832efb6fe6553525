"""Development credentials for a secure cluster: one CA, and per identity a certificate, a key and
a password (``forcegrasp certs DIR``).

Layout of DIR, one folder per identity so that a machine gets exactly the folder it needs::

    DIR/ca.pem, DIR/ca-key.pem        the CA (keep ca-key.pem on the machine that made it)
    DIR/<identity>/ca.pem             the CA certificate, to verify the other side
    DIR/<identity>/cert.pem, key.pem  the identity's certificate (CN = identity) and private key
    DIR/<identity>/user, password     its Zenoh user name and password
    DIR/learner/users.txt             every identity's user:password, the learner's dictionary

Identities: ``learner``, ``evaluator``, ``client`` (``forcegrasp best``, dashboards) and
``actor-0`` ... ``actor-<N-1>``; more actors later with ``--add actor-7`` (the CA is reused).
Each certificate names the hosts it may be reached at (``localhost``, ``learner``, 127.0.0.1 and
every ``--host``): the learner's is the one checked, since it is the only service that listens.
The learner's access control (`forcegrasp.security`) keys on the user names, so an identity's
folder is what lets a process act as that identity.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import re
import secrets
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

BASE_IDENTITIES = ("learner", "evaluator", "client")
DEFAULT_HOSTS = ("localhost", "learner", "127.0.0.1", "::1")
_IDENTITY = re.compile(r"^(learner|evaluator|client|actor-[A-Za-z0-9_.-]{1,48})$")


class CertsError(ValueError):
    """A bad identity, host or credentials folder."""


def check_identity(name: str) -> str:
    if not _IDENTITY.match(name):
        raise CertsError(f"identity {name!r}: expected learner, evaluator, client or actor-<id>")
    return name


def make_credentials(out: str | os.PathLike, actors: int = 2, hosts: tuple[str, ...] = (), add: tuple[str, ...] = (),
                     days: int = 365) -> list[str]:
    """Write (or extend) DIR; returns the identities written. An existing CA is reused, existing
    identities are left as they are (delete a folder to re-issue it)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = [check_identity(n) for n in (*BASE_IDENTITIES, *(f"actor-{i}" for i in range(actors)), *add)]
    all_hosts = tuple(dict.fromkeys((*DEFAULT_HOSTS, *hosts)))
    for h in all_hosts:
        if not h or len(h) > 253 or not re.match(r"^[A-Za-z0-9.:-]+$", h):
            raise CertsError(f"host {h!r} is not a host name or IP address")
    ca_key, ca_cert = _load_or_make_ca(out, days)
    written = []
    for name in names:
        folder = out / name
        if (folder / "cert.pem").is_file():
            continue
        folder.mkdir(exist_ok=True)
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _issue(ca_key, ca_cert, key, name, all_hosts, days)
        _write(folder / "key.pem", key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                     serialization.NoEncryption()), secret=True)
        _write(folder / "cert.pem", cert.public_bytes(serialization.Encoding.PEM))
        _write(folder / "ca.pem", ca_cert.public_bytes(serialization.Encoding.PEM))
        _write(folder / "user", (name + "\n").encode())
        _write(folder / "password", (secrets.token_urlsafe(24) + "\n").encode(), secret=True)
        written.append(name)
    users = [f"{p.name}:{(p / 'password').read_text().strip()}" for p in sorted(out.iterdir())
             if p.is_dir() and (p / "password").is_file()]
    _write(out / "learner" / "users.txt", ("\n".join(users) + "\n").encode(), secret=True)
    return written


def _load_or_make_ca(out: Path, days: int):
    key_path, cert_path = out / "ca-key.pem", out / "ca.pem"
    if key_path.is_file() and cert_path.is_file():
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        return key, x509.load_pem_x509_certificate(cert_path.read_bytes())
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "ForceGrasp development CA")])
    now = dt.datetime.now(dt.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    _write(key_path, key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()), secret=True)
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM))
    return key, cert


def _issue(ca_key, ca_cert, key, name: str, hosts: tuple[str, ...], days: int) -> x509.Certificate:
    alt = []
    for h in hosts:
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            alt.append(x509.DNSName(h))
    now = dt.datetime.now(dt.timezone.utc)
    return (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(alt), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))


def _write(path: Path, data: bytes, secret: bool = False) -> None:
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if secret else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, path)
