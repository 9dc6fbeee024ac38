"""``nwr certs``, the secure session configuration and the router's rules file: no network, no processes."""

from __future__ import annotations

import datetime as dt
import json
import os
import stat
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID

from nwr.common.config import ZenohSection, load_profile
from nwr.common.errors import ConfigError
from nwr.common.launch import apply_env_overrides, env_overrides
from nwr.common.node import check_tls_files, tls_endpoints, zenoh_config
from nwr.services.cli import main
from nwr.services.tools import certs
from nwr.services.tools.router import load_acl

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture()
def lab(tmp_path: Path) -> Path:
    directory = tmp_path / "lab"
    certs.init_ca(directory)
    return directory


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_init_writes_a_ca_with_an_owner_only_key(lab: Path) -> None:
    assert stat.S_IMODE((lab / "ca.key").stat().st_mode) == 0o600
    ca = _cert(lab / "ca.crt")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    with pytest.raises(ConfigError, match="--force"):
        certs.init_ca(lab)  # a second CA would silently invalidate every certificate


def test_a_robots_certificate_names_the_robot(lab: Path) -> None:
    path = certs.issue(lab, "cartesian", "planner", robot="arm-a")
    assert path == lab / "arm-a" / "cartesian.crt"
    assert certs.certificate_common_name(_cert(path)) == "planner:cartesian@arm-a"
    assert certs.parse_common_name("planner:cartesian@arm-a") == ("planner", "cartesian")
    with pytest.raises(ConfigError, match="ROLE:NAME@ROBOT"):
        certs.parse_common_name("planner:cartesian@Arm A")
    with pytest.raises(ConfigError, match="the router serves every robot"):
        certs.issue(lab, "router", "router", robot="arm-a")


def test_issue_puts_the_role_in_the_common_name(lab: Path) -> None:
    path = certs.issue(lab, "cartesian", "planner", days=30)
    assert stat.S_IMODE((lab / "cartesian.key").stat().st_mode) == 0o600
    cert = _cert(path)
    assert certs.certificate_common_name(cert) == "planner:cartesian"
    assert certs.parse_common_name("planner:cartesian") == ("planner", "cartesian")
    cert.verify_directly_issued_by(_cert(lab / "ca.crt"))
    usages = list(cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)
    assert usages == [ExtendedKeyUsageOID.CLIENT_AUTH]  # a service's key cannot pose as the router
    left = cert.not_valid_after_utc - dt.datetime.now(dt.UTC)
    assert dt.timedelta(days=29) < left <= dt.timedelta(days=30)
    with pytest.raises(ConfigError, match="--force"):
        certs.issue(lab, "cartesian", "planner")
    certs.issue(lab, "cartesian", "planner", force=True)  # rotation


def test_router_certificate_serves_and_names_its_hosts(lab: Path) -> None:
    cert = _cert(certs.issue(lab, "router", "router", sans=["10.0.0.2", "router.lab"]))
    usages = list(cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)
    assert ExtendedKeyUsageOID.SERVER_AUTH in usages
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert {"router", "localhost", "router.lab"} <= set(san.get_values_for_type(x509.DNSName))
    assert {str(a) for a in san.get_values_for_type(x509.IPAddress)} == {"10.0.0.2", "127.0.0.1"}


@pytest.mark.parametrize(("name", "role", "match"), [("Cartesian", "planner", "certificate name"),
                                                     ("x", "admin", "role"), ("ca", "view", "CA's own")])
def test_issue_rejects_bad_names_and_roles(lab: Path, name: str, role: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        certs.issue(lab, name, role)


def test_issue_needs_the_ca(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="nwr certs init"):
        certs.issue(tmp_path, "gain", "gain")


def test_list_shows_roles_expiry_and_foreign_certificates(lab: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    certs.issue(lab, "bridge", "bridge")
    certs.issue(lab, "gain", "gain", days=10)
    certs.init_ca(tmp_path / "other")
    certs.issue(tmp_path / "other", "spy", "recorder")
    (lab / "spy.crt").write_bytes((tmp_path / "other" / "spy.crt").read_bytes())
    listing = {c.name: c for c in certs.list_certificates(lab)}
    assert set(listing) == {"bridge", "gain", "spy"}
    assert listing["bridge"].role == "bridge" and listing["bridge"].signed_by_ca
    assert not listing["spy"].signed_by_ca
    text = certs.format_listing(list(listing.values()), dt.datetime.now(dt.UTC))
    assert "expires soon" in text and "NOT signed" in text
    assert main(["certs", "list", "--dir", str(lab)]) == 0
    assert "bridge:bridge" in capsys.readouterr().out


def test_cli_init_and_issue(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["certs", "init", str(tmp_path / "d")]) == 0
    assert main(["certs", "issue", "operator", "--role", "operator", "--dir", str(tmp_path / "d")]) == 0
    assert "operator:operator" in capsys.readouterr().out
    assert main(["certs", "issue", "x", "--role", "gain", "--dir", str(tmp_path / "none")]) == 2


# -- the session configuration ---------------------------------------------
def _secure(lab: Path, name: str = "gain", router: list[str] | None = None) -> ZenohSection:
    return ZenohSection(router=["tcp/127.0.0.1:7447"] if router is None else router, secure=True,
                        ca_certificate=str(lab / "ca.crt"), certificate=str(lab / f"{name}.crt"),
                        private_key=str(lab / f"{name}.key"))


def test_insecure_default_is_unchanged() -> None:
    conf = zenoh_config(ZenohSection(), "gain")
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7451"]
    assert "tcp/127.0.0.1:7450" in json.loads(conf.get_json("connect/endpoints"))
    assert json.loads(conf.get_json("transport/link/tls/root_ca_certificate")) is None


def test_secure_client_is_mutual_tls_to_the_router(lab: Path) -> None:
    certs.issue(lab, "gain", "gain")
    conf = zenoh_config(_secure(lab))
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tls/127.0.0.1:7447"]
    assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"]
    assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True
    assert json.loads(conf.get_json("transport/link/tls/connect_certificate")) == str(lab / "gain.crt")


def test_secure_mode_refuses_without_certificate_or_router(lab: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no certificate.*nwr certs issue"):
        zenoh_config(ZenohSection(router=["tcp/127.0.0.1:7447"], secure=True))
    with pytest.raises(ConfigError, match="does not exist"):
        zenoh_config(_secure(lab, "missing"))
    certs.issue(lab, "gain", "gain")
    with pytest.raises(ConfigError, match="needs a router"):
        zenoh_config(_secure(lab, router=[]))
    with pytest.raises(ConfigError, match="udp"):
        tls_endpoints(["udp/127.0.0.1:7447"], "NWR_ROUTER")
    with pytest.raises(ConfigError, match="router:NAME"):
        check_tls_files(_secure(lab), role="router")


def test_expired_certificate_refuses_to_start(lab: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    certs.issue(lab, "gain", "gain", days=1)
    real = certs._now
    monkeypatch.setattr(certs, "_now", lambda: real() - dt.timedelta(days=3))
    certs.issue(lab, "old", "gain", days=1)
    assert check_tls_files(_secure(lab)) == "gain:gain"
    with pytest.raises(ConfigError, match="expired"):
        check_tls_files(_secure(lab, "old"))


def test_environment_turns_secure_mode_on_and_off(lab: Path) -> None:
    env = {"NWR_ROUTER": "tcp/10.0.0.2:7447", "NWR_TLS_CA": "/c/ca.crt", "NWR_TLS_CERT": "/c/bridge.crt",
           "NWR_TLS_KEY": "/c/bridge.key"}
    profile = apply_env_overrides(load_profile(), env_overrides(env))
    assert profile.zenoh.secure and profile.zenoh.certificate == "/c/bridge.crt"
    profile = apply_env_overrides(load_profile(), env_overrides({**env, "NWR_INSECURE": "1"}))
    assert not profile.zenoh.secure
    with pytest.raises(ConfigError, match="NWR_INSECURE"):
        apply_env_overrides(load_profile(), env_overrides({"NWR_INSECURE": "maybe"}))


def test_shipped_rules_deny_by_default(tmp_path: Path) -> None:
    text = load_acl(ROOT / "deploy" / "acl.json5")
    assert "planner:cartesian" in text
    loose = tmp_path / "loose.json5"
    loose.write_text('{ enabled: true, default_permission: "allow", rules: [], subjects: [], policies: [] }')
    with pytest.raises(ConfigError, match="deny"):
        load_acl(loose)
    with pytest.raises(ConfigError, match="cannot read"):
        load_acl(tmp_path / "none.json5")


def test_rules_scoped_to_one_robot() -> None:
    scoped = load_acl(ROOT / "deploy" / "acl.json5", "ur10e")
    assert "nwr/*/" not in scoped and '"nwr/ur10e/robot/command/cartesian"' in scoped
    assert "nwr/*/robot/command/cartesian" in load_acl(ROOT / "deploy" / "acl.json5")
    with pytest.raises(ConfigError, match="robot name"):
        load_acl(ROOT / "deploy" / "acl.json5", "a/b")


GRANTS = ["router=router:router", "bridge=bridge:bridge", "planner=planner:cartesian",
          "planner-spare=planner:uniform"]


def test_provision_makes_a_ca_and_one_directory_per_service(tmp_path: Path) -> None:
    root = tmp_path / "certs"
    lines = certs.provision(root, [certs.parse_grant(g) for g in GRANTS], sans=["10.0.0.2"])
    assert lines[0].startswith("created the lab CA") and sum(x.startswith("issued") for x in lines) == 4
    ca = _cert(root / "ca" / "ca.crt")
    for directory, name, cn in (("router", "router", "router:router"), ("planner", "cartesian", "planner:cartesian"),
                                ("planner-spare", "uniform", "planner:uniform")):
        d = root / directory
        assert sorted(p.name for p in d.iterdir()) == sorted(["ca.crt", f"{name}.crt", f"{name}.key"])
        assert (d / "ca.crt").read_bytes() == (root / "ca" / "ca.crt").read_bytes()
        cert = _cert(d / f"{name}.crt")
        cert.verify_directly_issued_by(ca)
        assert certs.certificate_common_name(cert) == cn
        assert stat.S_IMODE((d / f"{name}.key").stat().st_mode) == 0o600
        assert check_tls_files(ZenohSection(router=["tls/router:7447"], secure=True, ca_certificate=str(d / "ca.crt"),
                                            certificate=str(d / f"{name}.crt"),
                                            private_key=str(d / f"{name}.key"))) == cn
    sans = _cert(root / "router" / "router.crt").extensions.get_extension_for_class(x509.SubjectAlternativeName)
    assert "10.0.0.2" in [str(ip) for ip in sans.value.get_values_for_type(x509.IPAddress)]
    assert not any(p.name == "ca.key" for p in root.rglob("*") if p.parent.name != "ca")


def test_provision_again_keeps_everything_and_adds_what_is_missing(tmp_path: Path) -> None:
    root = tmp_path / "certs"
    certs.provision(root, [certs.parse_grant(g) for g in GRANTS])
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    lines = certs.provision(root, [certs.parse_grant(g) for g in [*GRANTS, "planner=planner:location"]])
    assert sum(x.startswith("kept") for x in lines) == 4 and sum(x.startswith("issued") for x in lines) == 1
    assert all(p.read_bytes() == data for p, data in before.items())
    assert (root / "planner" / "location.crt").exists() and (root / "planner" / "cartesian.crt").exists()


def test_provision_without_the_ca_key_creates_nothing(tmp_path: Path) -> None:
    """A host that received its services' directories: no second CA, and what is missing is named."""
    admin = tmp_path / "admin"
    certs.provision(admin, [certs.parse_grant(g) for g in GRANTS])
    host = tmp_path / "robot-pc"
    host.mkdir()
    (host / "bridge").mkdir()
    for f in (admin / "bridge").iterdir():
        (host / "bridge" / f.name).write_bytes(f.read_bytes())
    lines = certs.provision(host, [certs.parse_grant(g) for g in GRANTS])
    assert not (host / "ca").exists()
    assert any(x.startswith("kept") and "bridge:bridge" in x for x in lines)
    missing = [x for x in lines if x.startswith("MISSING")]
    assert len(missing) == 3 and "nwr certs issue cartesian --role planner" in " ".join(missing)


def test_provision_hands_the_directories_to_the_services_user(tmp_path: Path) -> None:
    if os.geteuid() != 0:
        pytest.skip("chown needs root")
    root = tmp_path / "certs"
    certs.provision(root, [certs.parse_grant("bridge=bridge:bridge")], owner=(10001, 10001))
    d = root / "bridge"
    assert {(p.stat().st_uid, p.stat().st_gid) for p in [d, *d.iterdir()]} == {(10001, 10001)}
    assert stat.S_IMODE(d.stat().st_mode) == 0o700
    assert (root / "ca" / "ca.key").stat().st_uid == 0 and stat.S_IMODE((root / "ca").stat().st_mode) == 0o700


@pytest.mark.parametrize("grant", ["bridge", "bridge=bridge", "ca=bridge:bridge", "x=pilot:bridge",
                                   "x=bridge:Bad", "../x=bridge:bridge"])
def test_provision_rejects_bad_grants(grant: str) -> None:
    with pytest.raises(ConfigError):
        certs.parse_grant(grant)


def test_cli_provision(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["certs", "provision", str(tmp_path / "c"), "--san", "10.0.0.2,router-host", *GRANTS]) == 0
    out = capsys.readouterr().out
    assert "created the lab CA" in out and out.count("issued") == 4
    sans = _cert(tmp_path / "c" / "router" / "router.crt").extensions.get_extension_for_class(
        x509.SubjectAlternativeName).value
    assert "router-host" in sans.get_values_for_type(x509.DNSName)
    assert main(["certs", "provision", str(tmp_path / "c"), "bridge=bridge:bridge", "bridge=bridge:bridge"]) != 0
