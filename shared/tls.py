"""Certificates for the TLS links between routers, with mutual authentication (mTLS): a small
certificate authority made for one system, and one certificate per router that it signs.

A router links only with routers that present a certificate of the same authority, and its
access rules know a linked router by the common name of that certificate
(``shared.access.LINKED_ROUTER``). The authority's key signs the certificates of one call and
is never written; the routers' private keys are written readable by their owner only.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from shared.access import LINKED_ROUTER, write_private

CA_FILE = "ca.pem"
# Long enough for any run; the certificates of a forgotten run directory soon expire.
VALID_FOR = datetime.timedelta(days=30)
# The names a certificate is valid for: zenoh checks the host of a TLS endpoint against them.
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


@dataclass(frozen=True)
class RouterCertificate:
    """The files of one router: what it presents, its key, the authority it trusts, and its
    zenoh configuration with these (``jamnav router --zenoh-config``)."""

    certificate: Path
    private_key: Path
    authority: Path
    zenoh_config: Path

    def zenoh_settings(self) -> dict[str, Any]:
        """A router's TLS settings: it presents its certificate when it listens and when it
        connects, and demands one signed by ``authority`` from the other side. Absolute
        paths: a router started in another directory finds the files too."""
        certificate, key = str(self.certificate.resolve()), str(self.private_key.resolve())
        return {"transport": {"link": {"tls": {
            "root_ca_certificate": str(self.authority.resolve()),
            "enable_mtls": True,
            "listen_certificate": certificate, "listen_private_key": key,
            "connect_certificate": certificate, "connect_private_key": key,
        }}}}


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _alternative_names(names: tuple[str, ...]) -> x509.SubjectAlternativeName:
    entries: list[x509.GeneralName] = []
    for name in names:
        try:
            entries.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            entries.append(x509.DNSName(name))
    return x509.SubjectAlternativeName(entries)


def _sign(builder: x509.CertificateBuilder, key: ec.EllipticCurvePrivateKey) -> x509.Certificate:
    now = datetime.datetime.now(datetime.timezone.utc)
    # Valid from a minute ago: the clocks of two hosts never agree to the second.
    return builder.serial_number(x509.random_serial_number()).not_valid_before(
        now - datetime.timedelta(minutes=1)).not_valid_after(now + VALID_FOR).sign(
        key, hashes.SHA256())


def _pem(certificate: x509.Certificate) -> str:
    return certificate.public_bytes(serialization.Encoding.PEM).decode()


def _private_pem(key: ec.EllipticCurvePrivateKey) -> str:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption()).decode()


def make_router_certificates(directory: Path, router_ids: list[str],
                             names: tuple[str, ...] = LOOPBACK_NAMES
                             ) -> dict[str, RouterCertificate]:
    """A fresh authority in ``directory`` and a certificate for each router, valid for the
    host ``names``; router id -> its files."""
    authority_key = ec.generate_private_key(ec.SECP256R1())
    authority_name = _name("jamnav-link-ca")
    authority = _sign(
        x509.CertificateBuilder().subject_name(authority_name).issuer_name(authority_name)
        .public_key(authority_key.public_key())
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(
            digital_signature=False, content_commitment=False, key_encipherment=False,
            data_encipherment=False, key_agreement=False, key_cert_sign=True, crl_sign=True,
            encipher_only=False, decipher_only=False), critical=True),
        authority_key)
    directory.mkdir(parents=True, exist_ok=True)
    authority_path = directory / CA_FILE
    authority_path.write_text(_pem(authority), encoding="utf-8")
    made = {}
    for router_id in router_ids:
        key = ec.generate_private_key(ec.SECP256R1())
        certificate = _sign(
            x509.CertificateBuilder().subject_name(_name(LINKED_ROUTER))
            .issuer_name(authority_name).public_key(key.public_key())
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(_alternative_names(names), critical=False)
            .add_extension(x509.ExtendedKeyUsage([x509.ExtendedKeyUsageOID.SERVER_AUTH,
                                                  x509.ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False),
            authority_key)
        stem = directory / f"router-{router_id}"
        files = RouterCertificate(stem.with_suffix(".pem"), stem.with_suffix(".key"),
                                  authority_path, stem.with_suffix(".json5"))
        files.certificate.write_text(_pem(certificate), encoding="utf-8")
        write_private(files.private_key, _private_pem(key))
        files.zenoh_config.write_text(json.dumps(files.zenoh_settings(), indent=2) + "\n",
                                      encoding="utf-8")
        made[router_id] = files
    return made
