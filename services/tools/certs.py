"""``nwr certs``: the lab's certificate authority and one certificate per service.

The Zenoh router of the LAN deployment accepts only TLS links whose client
presents a certificate signed by the lab CA (mutual TLS), and its access
control decides what each connection may put by the certificate's common
name. This module makes those certificates:

- ``nwr certs init DIR`` creates the CA (``ca.crt``, ``ca.key``) on the lab's
  admin machine. ``ca.key`` never leaves it.
- ``nwr certs issue NAME --role ROLE`` writes ``NAME.crt`` and ``NAME.key``,
  signed by the CA, with the common name ``ROLE:NAME`` (e.g.
  ``planner:cartesian``, ``bridge:bridge``). The access-control rules
  (``deploy/acl.json5``) list exactly these common names.
- ``nwr certs list`` prints every certificate of the directory: name, role,
  common name, expiry.

Keys are ECDSA P-256 (what rustls, Zenoh's TLS, supports everywhere), written
with owner-only permissions (0600). Only the router's certificate may act as
a TLS server (extended key usage ``serverAuth``): a stolen service key cannot
impersonate the router. All the cryptography is the ``cryptography``
package's; nothing here is hand-rolled.
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from nwr.common.errors import ConfigError

log = logging.getLogger(__name__)

ROLES = ("router", "gateway", "gain", "planner", "bridge", "recorder", "view", "operator")
# A name is a file name and part of the common name, and for a planner also
# its key (reflex/<name>/...): the same alphabet as planner and robot names.
NAME = re.compile(r"^[a-z][a-z0-9_-]{0,31}$")
CA_CERT = "ca.crt"
CA_KEY = "ca.key"
# Long enough that a lab does not re-issue its CA every term; short enough
# that a forgotten service certificate does not work forever.
CA_DAYS = 3650
DEFAULT_DAYS = 365
# The router's certificate is checked against the host name clients dial
# (verify_name_on_connect): these cover the compose service name and loopback.
ROUTER_DEFAULT_SANS = ("router", "localhost", "127.0.0.1")
EXPIRY_WARNING_DAYS = 30


def default_dir() -> Path:
    """``$NWR_CERTS`` or ``./certs``: read at call time, never at import."""
    return Path(os.environ.get("NWR_CERTS") or "certs")


# A robot's own certificates (one router for several arms, `nwr router --robots`): ROLE:NAME@ROBOT.
ROBOT_SEP = "@"


def common_name(role: str, name: str, robot: str | None = None) -> str:
    """The certificate's common name, which the router's access control matches: ``ROLE:NAME``, or
    ``ROLE:NAME@ROBOT`` for a certificate of one robot's pipeline (its rules hold on that robot's keys only)."""
    return f"{role}:{name}" if robot is None else f"{role}:{name}{ROBOT_SEP}{robot}"


def parse_common_name(cn: str) -> tuple[str, str]:
    """(role, name) of a ``ROLE:NAME`` or ``ROLE:NAME@ROBOT`` common name; ConfigError if it is not one."""
    role, sep, name = cn.partition(":")
    name, at, robot = name.partition(ROBOT_SEP)
    if not sep or role not in ROLES or not NAME.match(name) or (at and not NAME.match(robot)):
        raise ConfigError(f"common name {cn!r} is not ROLE:NAME (or ROLE:NAME@ROBOT) with a role of {list(ROLES)}: "
                          "issue the certificate with `nwr certs issue NAME --role ROLE [--robot ROBOT]`")
    return role, name


def _write_private(path: Path, data: bytes) -> None:
    """Write a key readable by its owner only, from the first byte (no window at 0644)."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, 0o600)  # the umask may not lower it, but an existing tmp file keeps its mode
        os.write(fd, data)
    finally:
        os.close(fd)
    os.replace(tmp, path)


def _write_public(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def init_ca(directory: Path, *, days: int = CA_DAYS, lab: str = "nwr lab", force: bool = False) -> Path:
    """Create ``ca.crt`` and ``ca.key`` in ``directory``; returns the certificate's path."""
    directory.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = directory / CA_CERT, directory / CA_KEY
    if key_path.exists() and not force:
        raise ConfigError(f"{key_path} exists: a new CA invalidates every certificate it signed. "
                          "Use --force to replace it on purpose (then re-issue every certificate)")
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"{lab} CA"),
                      x509.NameAttribute(NameOID.ORGANIZATION_NAME, lab)])
    now = _now()
    cert = (
        x509.CertificateBuilder()
        .subject_name(name).issuer_name(name).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))  # tolerate small clock skew between hosts
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                     crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write_private(key_path, _key_pem(key))
    _write_public(cert_path, cert.public_bytes(serialization.Encoding.PEM))
    log.info("created the lab CA %s (valid until %s); keep %s on this machine only", cert_path,
             cert.not_valid_after_utc.date(), key_path)
    return cert_path


def _load_ca(directory: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert_path, key_path = directory / CA_CERT, directory / CA_KEY
    if not key_path.exists():
        raise ConfigError(f"no CA key {key_path}: create the lab CA first with `nwr certs init {directory}` "
                          "(on the admin machine, where ca.key stays)")
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ConfigError(f"{key_path} is not an EC key made by `nwr certs init`")
    return cert, key


def _san(entry: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(entry))
    except ValueError:
        return x509.DNSName(entry)


def issue(directory: Path, name: str, role: str, *, days: int = DEFAULT_DAYS, sans: list[str] | None = None,
          force: bool = False, out: Path | None = None, robot: str | None = None) -> Path:
    """Write ``NAME.crt`` and ``NAME.key`` signed by the CA in ``directory``; returns the certificate's path.

    They go to ``out`` if given (a service's own directory), else next to the
    CA (``ROBOT/`` beside it for a robot's certificate). The router's certificate also carries subject
    alternative names (the host names and addresses clients dial), since clients verify them. ``robot``: a
    certificate of that robot's pipeline, common name ``ROLE:NAME@ROBOT`` (``nwr router --robots``).
    """
    if role not in ROLES:
        raise ConfigError(f"role {role!r} is not one of {list(ROLES)}")
    if robot is not None and (role == "router" or not NAME.match(robot)):
        raise ConfigError(f"--robot {robot!r}: a robot name (lower-case letters, digits, '_' and '-'), for a "
                          "service's certificate (the router serves every robot)")
    if not NAME.match(name):
        raise ConfigError(f"certificate name {name!r}: lower-case letters, digits, '_' and '-', starting with a "
                          "letter, at most 32 characters (a planner's name is its planner name, e.g. cartesian)")
    if name == "ca":
        raise ConfigError("certificate name 'ca' is the CA's own: choose another name")
    if not 1 <= days <= CA_DAYS:
        raise ConfigError(f"--days {days}: give 1 to {CA_DAYS} days")
    out = (directory if robot is None else directory / robot) if out is None else out
    cert_path, key_path = out / f"{name}.crt", out / f"{name}.key"
    if cert_path.exists() and not force:
        raise ConfigError(f"{cert_path} exists: use --force to re-issue it (rotation), then copy it to its host")
    ca_cert, ca_key = _load_ca(directory)
    out.mkdir(parents=True, exist_ok=True)
    now = _now()
    not_after = min(now + dt.timedelta(days=days), ca_cert.not_valid_after_utc)
    key = ec.generate_private_key(ec.SECP256R1())
    alt_names = list(sans or [])
    if role == "router":
        alt_names += [s for s in ROUTER_DEFAULT_SANS if s not in alt_names]
    if name not in alt_names:
        alt_names.append(name)
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
    if role == "router":
        usages.insert(0, ExtendedKeyUsageOID.SERVER_AUTH)  # only the router may serve TLS
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name(role, name, robot))]))
        .issuer_name(ca_cert.subject).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False, key_cert_sign=False,
                                     crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        .add_extension(x509.SubjectAlternativeName([_san(s) for s in alt_names]), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    _write_private(key_path, _key_pem(key))
    _write_public(cert_path, cert.public_bytes(serialization.Encoding.PEM))
    log.info("issued %s for %s (valid until %s)", cert_path, common_name(role, name, robot), not_after.date())
    return cert_path


@dataclass(frozen=True)
class Grant:
    """One service's certificate in a deployment: its own directory, role and name."""

    directory: str  # the subdirectory its container mounts as /certs
    role: str
    name: str

    @property
    def common_name(self) -> str:
        return common_name(self.role, self.name)


def parse_grant(text: str) -> Grant:
    """``DIR=ROLE:NAME`` (e.g. ``planner=planner:cartesian``); ConfigError saying what a grant looks like."""
    directory, sep, cn = text.partition("=")
    if not sep or not NAME.match(directory) or directory == "ca":
        raise ConfigError(f"grant {text!r}: write DIR=ROLE:NAME, e.g. bridge=bridge:bridge or "
                          "planner=planner:cartesian (DIR a plain directory name other than 'ca')")
    role, name = parse_common_name(cn)
    return Grant(directory, role, name)


def provision(root: Path, grants: list[Grant], *, sans: list[str] | None = None,
              owner: tuple[int, int] | None = None, days: int = DEFAULT_DAYS) -> list[str]:
    """Give every service its own directory ``root/DIR`` with ``ca.crt``, ``NAME.crt`` and ``NAME.key``.

    What a single-host deployment runs before its services (the compose
    ``certs`` service): on an empty ``root`` it creates the lab CA in
    ``root/ca`` (which no service mounts) and issues every certificate; later
    runs issue only what is missing and never replace a certificate (rotation
    is ``nwr certs issue --force`` on purpose). A host that received its
    services' directories from the admin machine has no CA key: nothing is
    created there, and a missing certificate is reported (its service then
    refuses to start, naming the file). Returns one line per action.
    """
    ca_dir = root / "ca"
    lines: list[str] = []

    def has(g: Grant) -> bool:
        d = root / g.directory
        return (d / f"{g.name}.crt").exists() and (d / f"{g.name}.key").exists()

    present = [g for g in grants if has(g)]
    anything_here = bool(present) or any((root / g.directory / CA_CERT).exists() for g in grants)
    if not (ca_dir / CA_KEY).exists() and not anything_here:
        init_ca(ca_dir, days=CA_DAYS)
        lines.append(f"created the lab CA {ca_dir / CA_CERT}; its key stays in {ca_dir}, which no service mounts")
    have_ca = (ca_dir / CA_KEY).exists()
    for g in grants:
        d = root / g.directory
        if has(g):
            cert = read_certificate(d / f"{g.name}.crt")
            cn = certificate_common_name(cert)
            left = (cert.not_valid_after_utc - _now()).total_seconds() / 86400
            note = "" if cn == g.common_name else f"; WRONG common name {cn!r}, expected {g.common_name!r}"
            if left <= 0:
                note += "; EXPIRED: re-issue it with --force"
            elif left <= EXPIRY_WARNING_DAYS:
                note += f"; expires in {left:.0f} days: re-issue it with --force"
            lines.append(f"kept {d / g.name}.crt ({cn}){note}")
        elif have_ca:
            d.mkdir(parents=True, exist_ok=True)
            issue(ca_dir, g.name, g.role, days=days, sans=sans if g.role == "router" else None, out=d)
            lines.append(f"issued {d / g.name}.crt ({g.common_name})")
        else:
            lines.append(f"MISSING {d / g.name}.crt: this host has no CA key ({ca_dir / CA_KEY}); issue it on the "
                         f"admin machine (nwr certs issue {g.name} --role {g.role}) and copy NAME.crt, NAME.key "
                         f"and ca.crt into {d}")
        if have_ca and d.is_dir():
            ca_pem = (ca_dir / CA_CERT).read_bytes()
            if not (d / CA_CERT).exists() or (d / CA_CERT).read_bytes() != ca_pem:
                _write_public(d / CA_CERT, ca_pem)
    if owner is not None:
        # The services' user must own what it reads (keys are 0600); the CA stays root-only.
        for g in grants:
            d = root / g.directory
            if not d.is_dir():
                continue
            os.chown(d, *owner)
            os.chmod(d, 0o700)
            for f in d.iterdir():
                if f.is_file():
                    os.chown(f, *owner)
        if ca_dir.is_dir():
            os.chmod(ca_dir, 0o700)
    return lines


@dataclass(frozen=True)
class CertInfo:
    name: str
    common_name: str
    role: str
    not_after: dt.datetime
    signed_by_ca: bool
    key_mode: int | None  # permission bits of NAME.key, None if it is not here (copied elsewhere)

    def days_left(self, now: dt.datetime) -> float:
        return (self.not_after - now).total_seconds() / 86400


def read_certificate(path: Path) -> x509.Certificate:
    """A PEM certificate; ConfigError naming the file and what to do."""
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except FileNotFoundError:
        raise ConfigError(f"certificate {path} does not exist: issue it on the admin machine with "
                          "`nwr certs issue NAME --role ROLE` and copy NAME.crt, NAME.key and ca.crt here") from None
    except ValueError as exc:
        raise ConfigError(f"{path} is not a PEM certificate: {exc}") from exc


def certificate_common_name(cert: x509.Certificate) -> str:
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    value = names[0].value if names else ""
    return value if isinstance(value, str) else value.decode()


def list_certificates(directory: Path) -> list[CertInfo]:
    """Every ``*.crt`` of ``directory`` but the CA's, by name."""
    ca_path = directory / CA_CERT
    ca = read_certificate(ca_path) if ca_path.exists() else None
    found = []
    for path in sorted(directory.glob("*.crt")):
        if path.name == CA_CERT:
            continue
        cert = read_certificate(path)
        cn = certificate_common_name(cert)
        role = cn.partition(":")[0] if cn.partition(":")[0] in ROLES else "?"
        signed = False
        if ca is not None:
            try:
                cert.verify_directly_issued_by(ca)
                signed = True
            except (InvalidSignature, ValueError, TypeError):  # another CA's, or another key type
                signed = False
        key = path.with_suffix(".key")
        found.append(CertInfo(path.stem, cn, role, cert.not_valid_after_utc, signed,
                              key.stat().st_mode & 0o777 if key.exists() else None))
    return found


def format_listing(certs: list[CertInfo], now: dt.datetime) -> str:
    rows = [("name", "role", "common name", "expires (UTC)", "days", "notes")]
    for c in certs:
        notes = []
        days = c.days_left(now)
        if days <= 0:
            notes.append("EXPIRED: re-issue with --force")
        elif days <= EXPIRY_WARNING_DAYS:
            notes.append("expires soon: re-issue with --force")
        if not c.signed_by_ca:
            notes.append("NOT signed by this directory's ca.crt")
        if c.key_mode is not None and c.key_mode & 0o077:
            notes.append(f"key mode {c.key_mode:o}: chmod 600")
        rows.append((c.name, c.role, c.common_name, c.not_after.strftime("%Y-%m-%d %H:%M"), f"{days:.0f}",
                     "; ".join(notes)))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip() for r in rows)


# -- command line ---------------------------------------------------------
def _handler(args: argparse.Namespace) -> int:
    directory = Path(args.dir) if args.dir else default_dir()
    if args.certs_command == "init":
        path = init_ca(directory, days=args.days, lab=args.lab, force=args.force)
        print(f"CA certificate {path}; its key {directory / CA_KEY} (0600) must stay on this machine")
        return 0
    if args.certs_command == "issue":
        path = issue(directory, args.name, args.role, days=args.days, sans=args.san, force=args.force,
                     robot=args.robot)
        print(f"{path} and {path.with_suffix('.key')} (0600), common name "
              f"{common_name(args.role, args.name, args.robot)}: "
              f"copy them and {directory / CA_CERT} to the service's host")
        return 0
    if args.certs_command == "provision":
        owner = None
        if args.owner:
            try:
                uid, gid = (int(x) for x in args.owner.split(":"))
            except ValueError:
                raise ConfigError(f"--owner {args.owner!r}: write UID:GID, e.g. 10001:10001") from None
            owner = (uid, gid)
        grants = [parse_grant(g) for g in args.grants]
        if len({(g.directory, g.name) for g in grants}) != len(grants):
            raise ConfigError(f"the same certificate is granted twice: {args.grants}")
        # "--san a,b" as well as "--san a --san b": compose passes one variable.
        sans = [h.strip() for entry in args.san or [] for h in entry.split(",") if h.strip()]
        lines = provision(Path(args.root), grants, sans=sans, owner=owner, days=args.days)
        print("\n".join(lines))
        return 0
    if not directory.is_dir():
        raise ConfigError(f"no certificate directory {directory}: give --dir, set NWR_CERTS, or create it with "
                          "`nwr certs init DIR`")
    print(format_listing(list_certificates(directory), _now()))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("certs", help="the lab CA and per-service TLS certificates for the secure LAN deployment",
                       description="Create the lab certificate authority, issue a certificate per service "
                                   "(common name ROLE:NAME, matched by the router's access control) and list them.")
    certs_sub = p.add_subparsers(dest="certs_command", required=True, metavar="ACTION")
    init = certs_sub.add_parser("init", help="create the lab CA (ca.crt, ca.key) in DIR")
    init.add_argument("dir", metavar="DIR", help="directory of the CA and the certificates")
    init.add_argument("--days", type=int, default=CA_DAYS, help=f"validity in days (default {CA_DAYS})")
    init.add_argument("--lab", default="nwr lab", help="the lab's name, in the CA's subject")
    init.add_argument("--force", action="store_true",
                      help="replace an existing CA (every certificate must be re-issued)")
    issue_p = certs_sub.add_parser("issue", help="a key and certificate for one service, signed by the CA")
    issue_p.add_argument("name", metavar="NAME",
                         help="certificate name: the file names and the common name ROLE:NAME (a planner: its name)")
    issue_p.add_argument("--role", required=True, choices=ROLES, help="what the service may do (deploy/acl.json5)")
    issue_p.add_argument("--san", action="append", metavar="HOST",
                         help="a host name or address clients dial (router certificates; repeatable; "
                              f"{', '.join(ROUTER_DEFAULT_SANS)} are always included)")
    issue_p.add_argument("--robot", metavar="ROBOT",
                         help="a certificate of this robot's pipeline only: common name ROLE:NAME@ROBOT, files in "
                              "DIR/ROBOT/; a router started with --robots lets it put on that robot's keys only")
    issue_p.add_argument("--days", type=int, default=DEFAULT_DAYS, help=f"validity in days (default {DEFAULT_DAYS})")
    issue_p.add_argument("--force", action="store_true", help="replace an existing certificate (rotation)")
    prov = certs_sub.add_parser(
        "provision", help="a deployment's certificates, one directory per service (the compose 'certs' step)",
        description="Give every service its own directory ROOT/DIR with ca.crt, NAME.crt and NAME.key. On an "
                    "empty ROOT it creates the lab CA in ROOT/ca (mounted by no service) and issues everything; "
                    "later runs issue only what is missing and never replace a certificate. Without the CA key "
                    "(a host that received copied directories) it creates nothing and reports what is missing.")
    prov.add_argument("root", metavar="ROOT", help="the deployment's certificate root (compose: $NWR_CERTS)")
    prov.add_argument("grants", metavar="DIR=ROLE:NAME", nargs="+",
                      help="a service's directory and certificate, e.g. bridge=bridge:bridge, "
                           "planner=planner:cartesian")
    prov.add_argument("--san", action="append", metavar="HOST",
                      help="host names or addresses clients dial the router by (repeatable or comma-separated)")
    prov.add_argument("--owner", metavar="UID:GID",
                      help="give the service directories to this user (the services' user; keys stay 0600)")
    prov.add_argument("--days", type=int, default=DEFAULT_DAYS, help=f"validity in days (default {DEFAULT_DAYS})")
    listing = certs_sub.add_parser("list", help="every certificate in the directory: name, role, expiry")
    for q in (issue_p, listing):
        q.add_argument("--dir", help="certificate directory (default: $NWR_CERTS or ./certs)")
    p.set_defaults(handler=_handler, dir=None)
