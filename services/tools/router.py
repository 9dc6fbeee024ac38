"""``nwr router``: the project's own Zenoh router, for labs without the official image.

A Zenoh session in router mode that listens on explicit endpoints, with
multicast scouting off (it does not cross Docker networks or routed LANs,
and an arm must not join a pipeline by accident). The services connect to it
by endpoint (``[zenoh] router = [...]`` or ``NWR_ROUTER``) as clients and
listen nowhere, so all traffic goes through it.

The default listen endpoint is loopback (``tcp/127.0.0.1:7447``): on a
host, opening the router to the LAN is a decision (``--listen
tcp/10.0.0.2:7447``, one of the host's addresses, or ``NWR_ROUTER_LISTEN``).
A wildcard address (``0.0.0.0``, ``[::]``) is every network the host is on,
and the router says so when it starts. The compose deployment passes
``tcp/0.0.0.0:7447`` inside the container's own network namespace, and
publishes the port on the host's loopback unless ``NWR_ROUTER_PUBLISH``
names another address (deploy/README.md).

The router declares the liveliness token ``nwr/<robot>/alive/router``, so
``nwr status`` lists it beside the services and ``nwr status --check
router`` is its health check.

In secure mode (``[zenoh] secure``, or ``NWR_TLS_*`` set, with the router's
own ``router:NAME`` certificate) it listens on TLS only (``tcp/`` endpoints
become ``tls/`` on the same port), requires a certificate from the lab CA of
every client (mutual TLS), and enforces the access control rules of
``--acl`` (``deploy/acl.json5``), which must deny by default. See
docs/security.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import signal
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import zenoh

from nwr.common import keys
from nwr.common.config import ZenohSection
from nwr.common.errors import ConfigError
from nwr.common.launch import parse_endpoints
from nwr.common.node import check_tls_files, tls_config, tls_endpoints
from nwr.services.profile import profile_for

log = logging.getLogger(__name__)

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
# Hosts of a listen endpoint that mean every address of the machine.
WILDCARD_HOSTS = frozenset({"0.0.0.0", "::"})
# The rules shipped with the deployment, for a router started from a checkout.
DEFAULT_ACL = "deploy/acl.json5"


def listen_choice(arg: str | None, environ: Mapping[str, str]) -> tuple[str, str]:
    """The listen endpoints (comma-separated) and where they came from: ``--listen``, the environment or the default."""
    if arg:
        return arg, "--listen"
    if environ.get("NWR_ROUTER_LISTEN"):
        return environ["NWR_ROUTER_LISTEN"], "NWR_ROUTER_LISTEN"
    return DEFAULT_LISTEN, "the default, loopback only"


def wildcard_endpoints(listen: list[str]) -> list[str]:
    """The endpoints of ``listen`` on every address of the machine (``tcp/0.0.0.0:7447``, ``tcp/[::]:7447``)."""
    wide = []
    for endpoint in listen:
        address = endpoint.split("/", 1)[-1].split("#", 1)[0].split("?", 1)[0]
        host = address.rsplit(":", 1)[0].strip("[]")
        if host in WILDCARD_HOSTS:
            wide.append(endpoint)
    return wide


def router_config(listen: list[str], connect: list[str], *, tls: ZenohSection | None = None,
                  acl: str | None = None) -> zenoh.Config:
    """The router's session configuration; with ``tls``, mutual TLS only and the access control ``acl`` (JSON5)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    if tls is not None:
        tls_config(conf, tls, listen=True)
        if acl is None:
            raise ConfigError("a secure router needs its access control rules: --acl deploy/acl.json5")
        conf.insert_json5("access_control", acl)
    return conf


# The rules are written for every robot (nwr/*/...); a router scopes them to its own.
ANY_ROBOT = "nwr/*/"


def per_robot(section: dict[str, Any], robots: list[str]) -> dict[str, Any]:
    """The rules of ``section`` once per robot: each robot's copy holds on ``nwr/<robot>/`` only and for that
    robot's certificates only (common names ``ROLE:NAME@ROBOT``, ``nwr certs issue --robot``). The rules that
    let everyone read, and the router's own certificate, stay as they are: reading is every certificate's."""
    shared = {"read-ingress", "read-egress", "router"}  # rule and subject ids kept once, for every robot
    rules = [r for r in section["rules"] if r["id"] in shared]
    subjects = [s for s in section["subjects"] if s["id"] in shared]
    policies = []
    for robot in robots:
        rules += [{**r, "id": f"{r['id']}@{robot}",
                   "key_exprs": [k.replace(ANY_ROBOT, f"nwr/{robot}/") for k in r["key_exprs"]]}
                  for r in section["rules"] if r["id"] not in shared]
        subjects += [{**s, "id": f"{s['id']}@{robot}", "cert_common_names": [f"{cn}@{robot}" for cn in
                                                                             s["cert_common_names"]]}
                     for s in section["subjects"] if s["id"] not in shared]
        policies += [{**p, "id": f"{p['id']}@{robot}",
                      "rules": [r if r in shared else f"{r}@{robot}" for r in p["rules"]],
                      "subjects": [s if s in shared else f"{s}@{robot}" for s in p["subjects"]]}
                     for p in section["policies"]]
    return {**section, "rules": rules, "subjects": subjects, "policies": policies}


def load_acl(path: Path, robot: str | None = None, robots: list[str] | None = None) -> str:
    """The access-control section in ``path`` (JSON5), checked to be on and to deny by default.

    With ``robot``, every ``nwr/*/`` key expression becomes ``nwr/<robot>/``:
    the router then allows nothing on another arm's keys, so a certificate
    issued for one arm's pipeline cannot command a second arm that shares
    the LAN (or, with ``--all-robots``, the same router). With ``robots``
    (one router for several arms), the rules once per robot, each for that
    robot's own certificates (:func:`per_robot`).
    """
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read the access control rules {path}: {exc}; the project ships "
                          "deploy/acl.json5") from exc
    for name in ([] if robot is None else [robot]) + (robots or []):
        if not re.fullmatch(r"[a-z][a-z0-9_-]{0,31}", name):
            raise ConfigError(f"robot name {name!r} cannot scope the access control rules")
    if robot is not None:
        text = text.replace(ANY_ROBOT, f"nwr/{robot}/")
    probe = zenoh.Config()
    try:
        probe.insert_json5("access_control", text)
    except (zenoh.ZError, ValueError) as exc:
        raise ConfigError(f"{path} is not a Zenoh access_control section: {exc}") from exc
    section = json.loads(probe.get_json("access_control"))
    # Deny by default is the point: a rules file that forgets it must not open the router.
    if section.get("enabled") is not True or section.get("default_permission") != "deny":
        raise ConfigError(f"{path}: access control must have enabled: true and default_permission: \"deny\" "
                          f"(got enabled={section.get('enabled')!r}, "
                          f"default_permission={section.get('default_permission')!r})")
    if robots:
        return json.dumps(per_robot(section, robots))
    return text


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--listen", metavar="ENDPOINTS",
        help=f"comma-separated endpoints to listen on (default: $NWR_ROUTER_LISTEN or {DEFAULT_LISTEN}, "
             "loopback; for a LAN, this host's address on it, e.g. tcp/10.0.0.2:7447; tcp/0.0.0.0:7447 is every "
             "network the host is on)",
    )
    parser.add_argument("--connect", metavar="ENDPOINTS", default="",
                        help="comma-separated endpoints of other routers to connect to (a router per site)")
    parser.add_argument("--acl", metavar="FILE",
                        help="secure mode: the access control rules, JSON5 (default: $NWR_ROUTER_ACL or "
                             f"{DEFAULT_ACL}, from the working directory)")
    scope = parser.add_mutually_exclusive_group()
    scope.add_argument("--robots", metavar="R1,R2,...",
                       help="secure mode, one router for several arms: the rules once per robot, each holding on "
                            "that robot's keys for that robot's certificates only (common names ROLE:NAME@ROBOT, "
                            "`nwr certs issue NAME --role ROLE --robot ROBOT`)")
    scope.add_argument("--all-robots", action="store_true",
                       help="secure mode: apply the rules to every robot's keys (nwr/*/) for the same certificates, "
                            "so that one arm's planner may command another (prefer --robots); by default they hold "
                            "for this router's robot only (NWR_ROBOT)")


def run(robot: str, args: argparse.Namespace, zcfg: ZenohSection | None = None) -> int:
    listen_arg, listen_source = listen_choice(args.listen, os.environ)
    listen = parse_endpoints(listen_arg, "--listen")
    if not listen:
        raise ConfigError("--listen names no endpoint: give at least one, e.g. tcp/10.0.0.2:7447")
    # Every interface is a choice the log states: on a host it is every
    # network the host is on; in a container, the host's port publishing
    # decides who reaches it.
    wide = wildcard_endpoints(listen)
    if wide:
        log.info("listening on every address of this host or container (%s, from %s): on a host, every network "
                 "it is on reaches the router; name one address (--listen tcp/10.0.0.2:7447) to serve one LAN",
                 ", ".join(wide), listen_source)
    connect = parse_endpoints(args.connect, "--connect")
    tls = zcfg if zcfg is not None and zcfg.secure else None
    acl = None
    if tls is not None:
        # Secure: TLS links only (tcp/ listens as tls/ on the same port), client
        # certificates required, and the access control decides every put.
        cn = check_tls_files(tls, role="router")
        listen = tls_endpoints(listen, "--listen")
        connect = tls_endpoints(connect, "--connect")
        acl_path = Path(getattr(args, "acl", None) or os.environ.get("NWR_ROUTER_ACL") or DEFAULT_ACL)
        robots = [r.strip() for r in (getattr(args, "robots", None) or "").split(",") if r.strip()]
        scope = None if getattr(args, "all_robots", False) or robots else robot
        acl = load_acl(acl_path, scope, robots)
        log.info("secure mode: mutual TLS only, as %s; access control from %s, deny by default, for %s", cn,
                 acl_path, f"nwr/{scope}/ only" if scope else
                 (f"each of {', '.join(robots)} by its own certificates (ROLE:NAME@ROBOT)" if robots
                  else "every robot (nwr/*/)"))
    else:
        log.warning("router without TLS or access control: anyone who reaches %s can publish on every key "
                    "(robot/command included); use secure mode on a lab LAN (docs/security.md)", ", ".join(listen))
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        log.info("received %s, stopping", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        session = zenoh.open(router_config(listen, connect, tls=tls, acl=acl))
    except zenoh.ZError as exc:
        raise ConfigError(f"cannot start the router on {listen}: {exc}; is the port taken (another router?) "
                          "or the address not one of this host's?") from exc
    with session:
        token = session.liveliness().declare_token(keys.key(robot, keys.alive("router")))
        log.info("Zenoh router %s listening on %s (%s)%s (multicast scouting off); token %s", session.zid(),
                 ", ".join(listen), listen_source, f", connected to {', '.join(connect)}" if connect else "",
                 keys.key(robot, keys.alive("router")))
        stop.wait()
        token.undeclare()
    return 0


def _handler(args: argparse.Namespace) -> int:

    profile = profile_for(args)
    return run(profile.robot.name, args, profile.zenoh)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "router", help="a Zenoh router for the LAN deployment (listens on loopback unless told otherwise)",
        description="Run a Zenoh session in router mode with multicast scouting off. Services reach it with "
                    "NWR_ROUTER=tcp/HOST:7447 (or [zenoh] router). It listens on loopback by default: use "
                    "--listen tcp/ADDRESS:7447 with this host's address on the LAN to serve it.",
    )
    add_arguments(p)
    p.set_defaults(handler=_handler)
