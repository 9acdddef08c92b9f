"""Bus security: TLS / mutual TLS links and zenoh access control per node role, from the site TOML.

Site TOML (all optional; without ``[bus.tls]`` the bus is plain TCP, the default on loopback)::

    [bus.tls]
    ca = "certs/ca.pem"         # root CA (PEM) that signed every node's certificate
    certs = "certs"             # folder with <role>.pem / <role>.key (``constructaide certs`` makes them)
    mtls = true                 # every link presents a certificate (default true); needed by [bus.acl]

    [bus.acl]
    enabled = true              # zenoh access control: each role publishes only its own topics
    cameras = ["cam-a"]         # optional: camera roles ``camera-<id>`` (a camera publishes only photo/<id>)

A role is the common name of a session's certificate: a node's name (``register``, ``render``, ...), ``router``
and ``admin`` (tools such as ``replay``: publish anything), or ``camera-<id>``. Relative paths are relative to the
TOML file. Every session gets the same access-control config; zenoh checks each incoming put against the rules of
the sender's common name (ingress), so a peer link is checked too, not only the router.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import logging
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from constructaide.errors import UserError
from schemas import keys

log = logging.getLogger("constructaide.bus")
CAMERA_PREFIX = "camera-"
TRUSTED_ROLES = ("router", "admin")  # may publish anything: a router forwards, replay re-publishes

# What each node role may publish (the outputs of its NodeSpec, checked by tests/test_bus_security.py), plus errors.
ROLE_PUBLISHES: dict[str, tuple[str, ...]] = {
    "ingest": (keys.BIM_MODEL, keys.BIM_UPDATE, keys.PHOTO),
    "register": (keys.REGISTRATION, keys.VIEWPOINTS, keys.SPARSE, keys.NEEDS_ANCHOR),
    "occlude": (keys.OCCLUSION,),
    "render": (keys.OVERLAY,),
    "progress": (keys.PHOTO_EVIDENCE, keys.PROGRESS),
    "workbench": (keys.ANCHORS, keys.ANNOTATION),
    "recorder": (),
    "dashboard": (),
}
CAMERA_PUBLISHES = (keys.PHOTO, keys.UPLOAD)  # with camera = the camera's own id
NODE_ROLES = tuple(ROLE_PUBLISHES)

# Everything but publications: subscribing, liveliness, latched queries and their replies.
_NON_PUT = [
    "declare_subscriber",
    "declare_queryable",
    "query",
    "reply",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
]


class TlsConfig(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    ca: str
    certs: str = "certs"
    cert: str = ""  # explicit <cert>/<key> instead of certs/<role>.pem
    key: str = ""
    mtls: bool = True


class AclConfig(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    enabled: bool = True
    cameras: list[str] = msgspec.field(default_factory=list)


class SecurityDoc(msgspec.Struct, forbid_unknown_fields=False, kw_only=True):
    tls: TlsConfig | None = None
    acl: AclConfig | None = None


@dataclass(frozen=True)
class BusSecurity:
    """Resolved security of one session: CA, this role's certificate and key (absolute paths), mTLS, ACL."""

    role: str
    ca: Path
    cert: Path
    key: Path
    mtls: bool = True
    acl: bool = False
    cameras: tuple[str, ...] = ()

    def check_publish(self, key: str) -> None:
        """Raise PermissionError when the ACL would drop a put on ``key`` by this role (zenoh drops it silently)."""
        if self.acl and not may_publish(self.role, key, self.cameras):
            raise PermissionError(f"bus ACL: role {self.role!r} may not publish on {key} (zenoh drops it)")

    def json5(self) -> dict[str, Any]:
        """zenoh config entries (path -> value) for :meth:`zenoh.Config.insert_json5`."""
        tls = {
            "root_ca_certificate": str(self.ca),
            "listen_certificate": str(self.cert),
            "listen_private_key": str(self.key),
            "enable_mtls": self.mtls,
            "verify_name_on_connect": True,
        }
        if self.mtls:
            tls |= {"connect_certificate": str(self.cert), "connect_private_key": str(self.key)}
        out: dict[str, Any] = {"transport/link/tls": tls}
        if self.acl:
            out["access_control"] = acl_config(self.cameras)
        return out


def acl_config(cameras: tuple[str, ...] | list[str] = ()) -> dict[str, Any]:
    """The zenoh ``access_control`` table: deny by default; every role may subscribe, query, reply and hold
    liveliness tokens; incoming puts only on the role's own topics (see :data:`ROLE_PUBLISHES`)."""
    live = keys.LIVELINESS.split("{node}")[0].replace("{site}", "*") + "**"  # constructaide/*/@live/**
    rules: list[dict[str, Any]] = [
        {"id": "all-but-put", "messages": _NON_PUT, "flows": ["ingress", "egress"], "permission": "allow",
         "key_exprs": ["**", "@/**", live]},
        {"id": "put-out", "messages": ["put", "delete"], "flows": ["egress"], "permission": "allow",
         "key_exprs": ["**", live]},
        {"id": "live", "messages": ["put", "delete"], "flows": ["ingress"], "permission": "allow",
         "key_exprs": [live]},  # a liveliness token travels as put/delete on its key
        {"id": "put-any", "messages": ["put", "delete"], "flows": ["ingress"], "permission": "allow",
         "key_exprs": ["**"]},
    ]  # fmt: skip
    subjects: list[dict[str, Any]] = [{"id": r, "cert_common_names": [r]} for r in (*TRUSTED_ROLES, *NODE_ROLES)]
    policies: list[dict[str, Any]] = [
        {"id": f"p-{r}", "subjects": [r], "rules": ["all-but-put", "put-out", "live", "put-any"]} for r in TRUSTED_ROLES
    ]
    errors = keys.pattern(keys.ERRORS)
    for role, templates in ROLE_PUBLISHES.items():
        rules.append(
            {"id": f"put-{role}", "messages": ["put", "delete"], "flows": ["ingress"], "permission": "allow",
             "key_exprs": [keys.pattern(t) for t in templates] + [errors]}
        )  # fmt: skip
        policies.append(
            {"id": f"p-{role}", "subjects": [role], "rules": ["all-but-put", "put-out", "live", f"put-{role}"]}
        )
    for cam in cameras:
        role = camera_role(cam)
        rules.append(
            {"id": f"put-{role}", "messages": ["put"], "flows": ["ingress"], "permission": "allow",
             "key_exprs": [keys.pattern(t, camera=cam) for t in CAMERA_PUBLISHES]}
        )  # fmt: skip
        subjects.append({"id": role, "cert_common_names": [role]})
        policies.append(
            {"id": f"p-{role}", "subjects": [role], "rules": ["all-but-put", "put-out", "live", f"put-{role}"]}
        )
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def check_endpoints(endpoints: list[str], security: BusSecurity | None) -> None:
    """Refuse endpoints that do not fit the security: ``tls/`` without certificates, plain ``tcp/`` while TLS is on
    (it would bypass the ACL); warn about plain TCP beyond loopback."""
    for e in endpoints:
        proto = e.split("/", 1)[0]
        if proto == "tls" and security is None:
            raise UserError(f"endpoint {e} is TLS but no [bus.tls] is configured (pass the site TOML: --bus-security)")
        if security is not None and proto != "tls":
            raise UserError(
                f"[bus.tls] is on but endpoint {e} is {proto}/: use tls/ (a plain link bypasses TLS and ACL)"
            )
        host = e.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]")
        if security is None and host not in ("127.0.0.1", "localhost", "::1"):
            log.warning("bus endpoint %s is plain TCP beyond loopback: anyone reaching it can read and publish "
                        "(set [bus.tls] and [bus.acl] in the site TOML)", e)  # fmt: skip


def camera_role(camera: str) -> str:
    return CAMERA_PREFIX + keys.check_chunk(camera, "camera")


def may_publish(role: str, key: str, cameras: tuple[str, ...] | list[str] = ()) -> bool:
    """Whether ``role`` may publish on the concrete ``key`` under :func:`acl_config` (the same table)."""
    from constructaide.runtime.bus import ke_match

    if role in TRUSTED_ROLES:
        return True
    if role.startswith(CAMERA_PREFIX):
        cam = role[len(CAMERA_PREFIX) :]
        return cam in cameras and any(ke_match(keys.pattern(t, camera=cam), key) for t in CAMERA_PUBLISHES)
    templates = (*ROLE_PUBLISHES.get(role, ()), keys.ERRORS) if role in ROLE_PUBLISHES else ()
    return any(ke_match(keys.pattern(t), key) for t in templates)


def load_security(site_toml: str | Path, role: str) -> BusSecurity | None:
    """The security of ``role``'s session from a site TOML's ``[bus.tls]`` / ``[bus.acl]`` (None when there is no
    ``[bus.tls]``). Raises :class:`UserError` for a configuration that cannot work (missing files, a certificate
    not signed by the CA, expired, not for this role, ACL without mutual TLS, an unknown role)."""
    path = Path(site_toml)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"bus security: config file not found: {path}") from None
    except tomllib.TOMLDecodeError as e:
        raise UserError(f"bus security: {path} is not valid TOML: {e}") from None
    try:
        sec = msgspec.convert(doc.get("bus", {}), SecurityDoc)
    except msgspec.ValidationError as e:
        raise UserError(f"{path}: bad [bus.tls]/[bus.acl]: {e}") from None
    if sec.tls is None:
        if sec.acl is not None and sec.acl.enabled:
            raise UserError(f"{path}: [bus.acl] needs [bus.tls] with mtls = true (roles are certificate names)")
        return None
    acl = sec.acl is not None and sec.acl.enabled
    if acl and not sec.tls.mtls:
        raise UserError(f"{path}: [bus.acl] needs mtls = true in [bus.tls] (roles are certificate common names)")
    cameras = tuple(keys.check_chunk(c, "camera") for c in (sec.acl.cameras if sec.acl else []))
    check_role(role, cameras)
    base = path.resolve().parent

    def resolve(p: str) -> Path:
        q = Path(p).expanduser()
        return q if q.is_absolute() else base / q

    certs = resolve(sec.tls.certs)
    cert = resolve(sec.tls.cert) if sec.tls.cert else certs / f"{role}.pem"
    key = resolve(sec.tls.key) if sec.tls.key else certs / f"{role}.key"
    out = BusSecurity(role, resolve(sec.tls.ca), cert, key, sec.tls.mtls, acl, cameras)
    check_files(out)
    return out


def check_role(role: str, cameras: tuple[str, ...] = ()) -> None:
    if role in TRUSTED_ROLES or role in NODE_ROLES:
        return
    if role.startswith(CAMERA_PREFIX) and role[len(CAMERA_PREFIX) :] in cameras:
        return
    known = [*TRUSTED_ROLES, *NODE_ROLES, *(camera_role(c) for c in cameras)]
    raise UserError(f"bus security: unknown role {role!r}; roles: {', '.join(known)}")


def check_files(sec: BusSecurity) -> None:
    """Refuse a CA / certificate / key that zenoh would only reject later with a vague TLS error."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec, padding, rsa

    for what, p in (("CA certificate", sec.ca), ("certificate", sec.cert), ("private key", sec.key)):
        if not p.is_file():
            raise UserError(f"bus security: {what} not found: {p} (make test ones with `constructaide certs`)")
    try:
        ca = x509.load_pem_x509_certificate(sec.ca.read_bytes())
        cert = x509.load_pem_x509_certificate(sec.cert.read_bytes())
    except ValueError as e:
        raise UserError(f"bus security: not a PEM certificate ({sec.ca} / {sec.cert}): {e}") from None
    try:
        key = serialization.load_pem_private_key(sec.key.read_bytes(), password=None)
    except (ValueError, TypeError) as e:
        raise UserError(f"bus security: cannot read the private key {sec.key}: {e}") from None
    pub = cert.public_key()
    if pub.public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    ) != key.public_key().public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo):  # type: ignore[union-attr]
        raise UserError(f"bus security: {sec.key} is not the key of {sec.cert}")
    try:
        ca_pub = ca.public_key()
        sig_hash = cert.signature_hash_algorithm
        if isinstance(ca_pub, ec.EllipticCurvePublicKey) and sig_hash is not None:
            ca_pub.verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(sig_hash))
        elif isinstance(ca_pub, rsa.RSAPublicKey) and sig_hash is not None:
            ca_pub.verify(cert.signature, cert.tbs_certificate_bytes, padding.PKCS1v15(), sig_hash)
    except Exception:
        raise UserError(f"bus security: {sec.cert} is not signed by the CA {sec.ca}") from None
    now = dt.datetime.now(dt.UTC)
    for c, p in ((ca, sec.ca), (cert, sec.cert)):
        if not (c.not_valid_before_utc <= now <= c.not_valid_after_utc):
            raise UserError(f"bus security: {p} is not valid now (valid {c.not_valid_before_utc:%Y-%m-%d} to "
                            f"{c.not_valid_after_utc:%Y-%m-%d})")  # fmt: skip
    cns = [a.value for a in cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)]
    if sec.acl and sec.role not in cns:
        raise UserError(f"bus security: {sec.cert} is for {cns}, not role {sec.role!r} (ACL roles are common names)")


def make_certs(out: Path, roles: list[str], hosts: list[str] | None = None, days: int = 365) -> list[Path]:
    """A test CA (``ca.pem``/``ca.key``) and one certificate per role (``<role>.pem``/``<role>.key``, common name =
    role, for server and client use, names ``hosts`` (default localhost, 127.0.0.1)). Returns the files written."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    out.mkdir(parents=True, exist_ok=True)
    now = dt.datetime.now(dt.UTC) - dt.timedelta(minutes=5)
    hosts = hosts or ["localhost", "127.0.0.1"]

    def write_key(k: ec.EllipticCurvePrivateKey, p: Path) -> None:
        p.write_bytes(
            k.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
        )
        p.chmod(0o600)

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "constructaide test CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now)
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True
        )  # key_cert_sign, crl_sign
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    written = [out / "ca.pem", out / "ca.key"]
    written[0].write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    write_key(ca_key, written[1])
    sans: list[x509.GeneralName] = []
    for h in hosts:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            sans.append(x509.DNSName(h))
    for role in roles:
        keys.check_chunk(role, "role")
        k = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, role)]))
            .issuer_name(ca_name)
            .public_key(k.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now)
            .not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(
                x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                critical=False,
            )
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        (out / f"{role}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        write_key(k, out / f"{role}.key")
        written += [out / f"{role}.pem", out / f"{role}.key"]
    return written
