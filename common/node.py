"""The thin Zenoh adapter every service shares.

- :func:`zenoh_config` builds the session configuration: multicast scouting is
  always off and every endpoint is explicit. The embedded default is a mesh
  of peers on loopback: each core service listens on ``base_port + slot`` and
  every process connects to all those ports (gossip over the links tells
  late-comers about each other). With ``router`` set, processes are clients
  of that router and listen nowhere.
- :class:`Node` owns one session: publishers declared once with the QoS of
  the key registry, subscribers that decode strictly and count and report
  bad samples instead of crashing, a liveliness token, the service's
  ``diag/<service>`` channel, and one stop event that SIGINT and SIGTERM set.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import zenoh

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.clock import Clock, MonotonicClock
from nwr.common.config import ZenohSection
from nwr.common.door import Door
from nwr.common.errors import ConfigError, DecodeError
from nwr.common.journal import JOURNAL_PERIOD_S, Batcher, Recording, service_config

log = logging.getLogger(__name__)

# Listening slots of the embedded mesh: service -> offset from base_port.
SLOTS = {"gateway": 0, "gain": 1, "planner": 2, "bridge": 3, "recorder": 4}


LOG_FORMAT = "%(asctime)s {service:>8s} %(levelname)-7s %(name)s: %(message)s"


def setup_logging(level: str = "INFO", service: str = "nwr") -> None:
    """Configure logging once per process."""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format=LOG_FORMAT.format(service=service),
        datefmt="%H:%M:%S",
    )


def relabel_logging(service: str) -> None:
    """Label this process's log lines with ``service`` (a planner's name is known once its profile is)."""
    for handler in logging.getLogger().handlers:
        handler.setFormatter(logging.Formatter(LOG_FORMAT.format(service=service), datefmt="%H:%M:%S"))


# A pipeline's instance: the launcher (nwr up, demo, replay, study, bench) sets it for every process it starts,
# so that a service it restarts finds its own pipeline's tokens, not another's.
INSTANCE_ENV = "NWR_INSTANCE"
# Why this process is a restart, set by the launcher that restarted it (nwr up, demo): the service says so on its
# diag/<service> (``restarted``), once something listens there or after RESTARTED_WAIT_S.
RESTART_ENV = "NWR_RESTART"
RESTARTED_WAIT_S = 2.0
# A message of another pipeline instance is reported at most this often per service, s (each one is counted).
FOREIGN_DIAG_EVERY_S = 10.0
# How long a starting service asks who else drives its robot, s (the answers come as soon as the peers reply).
OWNER_QUERY_S = 1.0


def pipeline_instance() -> str:
    """This process's pipeline instance (``NWR_INSTANCE``), or keys.NO_INSTANCE for a process started alone."""
    return keys.key_chunk(os.environ.get(INSTANCE_ENV, ""))


# Which pipeline a message comes from travels beside it, as the Zenoh attachment of every put (the instance's
# UTF-8 bytes), not in it: a message's bytes, what recordings keep and what nwr verify and lockstep compare, are
# the same in every pipeline, and a recording made before instances travelled still verifies and replays.
# Producers a process started alone may legitimately stand for beside a launched pipeline: the operator's tools,
# a live replay, a planner added with `nwr run planner`. Any other key's messages must come from this pipeline.
_ALONE_MAY_PUT = frozenset({"operator", "replay", "status", "planner", keys.ANY_SERVICE})


def sender_instance(attachment: Any) -> str:
    """The pipeline instance a sample's attachment names (keys.NO_INSTANCE for none, or one that is no instance)."""
    if attachment is None:
        return keys.NO_INSTANCE
    try:
        raw = attachment.to_bytes() if hasattr(attachment, "to_bytes") else bytes(attachment)
        text = raw.decode()
    except (UnicodeDecodeError, TypeError, ValueError):
        return keys.NO_INSTANCE
    return text if text and keys.key_chunk(text) == text else keys.NO_INSTANCE


def from_this_pipeline(mine: str, theirs: str, relative: str) -> bool:
    """Whether a message on ``relative`` from pipeline ``theirs`` may feed a process of pipeline ``mine``.

    A process started alone (``mine`` is keys.NO_INSTANCE) takes every message: its owner token kept it from
    starting beside another pipeline's. A launched one takes its own pipeline's, and a process started alone's
    only on the keys such a process may put on (the operator's, a replay's, a planner's, diagnostics): a
    message of another pipeline instance never feeds it, whatever the key.
    """
    if mine == keys.NO_INSTANCE or theirs == mine:
        return True
    if theirs != keys.NO_INSTANCE:
        return False
    try:
        producers = keys.topic_for(relative).producers
    except DecodeError:
        return False
    return not _ALONE_MAY_PUT.isdisjoint(producers)


def endpoints(cfg: ZenohSection) -> list[str]:
    return [f"tcp/{cfg.host}:{cfg.base_port + slot}" for slot in SLOTS.values()]


def qos(topic: keys.Topic) -> dict[str, Any]:
    """A registry key's QoS as Zenoh's publisher options (priority, express, congestion control)."""
    return {"priority": getattr(zenoh.Priority, topic.priority), "express": topic.express,
            "congestion_control": zenoh.CongestionControl.DROP if topic.drop else zenoh.CongestionControl.BLOCK}


def zenoh_config(cfg: ZenohSection, listen_slot: str | None = None) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    if cfg.secure:
        return _secure_client_config(conf, cfg)
    if cfg.router:
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps(cfg.router))
        return conf
    conf.insert_json5("mode", json.dumps(cfg.mode))
    listen: list[str] = []
    if listen_slot is not None and listen_slot in SLOTS:
        listen.append(f"tcp/{cfg.host}:{cfg.base_port + SLOTS[listen_slot]}")
    else:
        # Not a core service: listen on a free loopback port so that peers
        # learning about this one through gossip can reach it.
        listen.append(f"tcp/{cfg.host}:0")
    mine = set(listen)
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps([e for e in endpoints(cfg) if e not in mine]))
    return conf


# A certificate this close to its end is reported at every start, so that
# it is re-issued before the router starts refusing the service.
TLS_EXPIRY_WARNING_DAYS = 30


def tls_endpoints(endpoints: list[str], what: str) -> list[str]:
    """``endpoints`` with ``tcp/`` dialled as ``tls/`` (same host and port); ConfigError for other protocols.

    Secure mode upgrades rather than rejects ``tcp/``, so that NWR_ROUTER
    stays the same whether NWR_INSECURE=1 is set or not.
    """
    out = []
    for e in endpoints:
        proto, _, rest = e.partition("/")
        if proto not in ("tcp", "tls"):
            raise ConfigError(f"{what}: {e!r} in secure mode: only tls/HOST:PORT (or tcp/, dialled as tls/) "
                              "carries mutual TLS; set NWR_INSECURE=1 to use other protocols without it")
        out.append(f"tls/{rest}")
    return out


def check_tls_files(cfg: ZenohSection, *, role: str | None = None) -> str:
    """The certificate's common name, after checking every TLS file is there and usable.

    ConfigError naming the file and what to do: a service in secure mode must
    refuse to start rather than retry a router that will never let it in.
    ``role``: the role the certificate's common name must carry (``router``).
    """
    from cryptography import x509  # secure mode only: the embedded default never loads it
    from cryptography.x509.oid import NameOID

    fix = ("issue one on the admin machine with `nwr certs issue NAME --role ROLE`, copy NAME.crt, NAME.key and "
           "ca.crt to this host and name them in [zenoh] ca_certificate / certificate / private_key (or "
           "NWR_TLS_CA, NWR_TLS_CERT, NWR_TLS_KEY); NWR_INSECURE=1 runs without TLS, on a trusted network only")
    for field in ("ca_certificate", "certificate", "private_key"):
        value = getattr(cfg, field)
        if not value:
            raise ConfigError(f"secure mode but [zenoh] {field} is empty: this service has no certificate; {fix}")
        path = Path(value)
        if not path.is_file():
            raise ConfigError(f"secure mode: [zenoh] {field} {value!r} does not exist; {fix}")
        try:
            path.read_bytes()
        except OSError as exc:
            raise ConfigError(f"secure mode: cannot read [zenoh] {field} {value!r} ({exc}); the service's user must "
                              "own it (chown) or be able to read it") from exc
    key_mode = Path(cfg.private_key).stat().st_mode & 0o777
    if key_mode & 0o077:
        log.warning("private key %s has mode %o: anyone on this host who can read it can act as this service; "
                    "chmod 600 it", cfg.private_key, key_mode)
    try:
        cert = x509.load_pem_x509_certificate(Path(cfg.certificate).read_bytes())
    except ValueError as exc:
        raise ConfigError(f"secure mode: [zenoh] certificate {cfg.certificate!r} is not a PEM certificate "
                          f"({exc}); {fix}") from exc
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    cn = str(names[0].value) if names else ""
    now = datetime.now(UTC)
    left_days = (cert.not_valid_after_utc - now).total_seconds() / 86400
    if left_days <= 0:
        raise ConfigError(f"secure mode: certificate {cfg.certificate} ({cn}) expired on "
                          f"{cert.not_valid_after_utc:%Y-%m-%d}: re-issue it with `nwr certs issue NAME --role ROLE "
                          "--force` and copy it here")
    if left_days <= TLS_EXPIRY_WARNING_DAYS:
        log.warning("certificate %s (%s) expires in %.0f days (%s): re-issue it with --force", cfg.certificate, cn,
                    left_days, f"{cert.not_valid_after_utc:%Y-%m-%d}")
    if role is not None and not cn.startswith(f"{role}:"):
        raise ConfigError(f"secure mode: certificate {cfg.certificate} has the common name {cn!r}, not {role}:NAME; "
                          f"issue one with `nwr certs issue NAME --role {role}`")
    return cn


def tls_config(conf: zenoh.Config, cfg: ZenohSection, *, listen: bool) -> None:
    """Mutual TLS with the lab CA, over TLS links only."""
    conf.insert_json5("transport/link/protocols", '["tls"]')
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(cfg.ca_certificate))
    conf.insert_json5("transport/link/tls/enable_mtls", "true")
    # The router's certificate must name the host it is dialled by.
    conf.insert_json5("transport/link/tls/verify_name_on_connect", "true")
    # A link whose peer's certificate expires is closed, not trusted until it drops.
    conf.insert_json5("transport/link/tls/close_link_on_expiration", "true")
    conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(cfg.certificate))
    conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(cfg.private_key))
    if listen:
        conf.insert_json5("transport/link/tls/listen_certificate", json.dumps(cfg.certificate))
        conf.insert_json5("transport/link/tls/listen_private_key", json.dumps(cfg.private_key))


def _secure_client_config(conf: zenoh.Config, cfg: ZenohSection) -> zenoh.Config:
    if not cfg.router:
        raise ConfigError("secure mode ([zenoh] secure = true) needs a router, which enforces the access control: "
                          "set [zenoh] router or NWR_ROUTER=tls/HOST:7447 (start one with `nwr router`), or "
                          "NWR_INSECURE=1 for the embedded mesh without TLS")
    cn = check_tls_files(cfg)
    routers = tls_endpoints(cfg.router, "[zenoh] router")
    log.info("secure mode: mutual TLS to %s as %s", ", ".join(routers), cn)
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps(routers))
    tls_config(conf, cfg, listen=False)
    return conf


class RepeatedLog:
    """A diagnostic's warnings and errors in the log: the first of a code at once, its repeats within
    ``window_ns`` counted into the next line of that code (or one line at :meth:`flush`): a repeated fault
    prints a line a minute with its count, never one per event. The diag key still carries every report."""

    def __init__(self, window_ns: int = 60_000_000_000) -> None:
        self.window_ns = window_ns
        self._codes: dict[str, tuple[int, int, str, str]] = {}  # code -> (logged at ns, not logged, level, message)

    def log(self, level: str, code: str, message: str, count: int, now_ns: int) -> None:
        logged, unlogged, _, _ = self._codes.get(code, (0, 0, level, message))
        if logged and now_ns - logged < self.window_ns:
            self._codes[code] = (logged, unlogged + count, level, message)
            return
        self._codes[code] = (now_ns, 0, level, message)
        repeats = unlogged + count - 1
        self._emit(level, code, message, repeats, now_ns - logged if logged else 0)

    def flush(self, now_ns: int) -> None:
        """A line for each code with repeats not yet logged (at the end of the run)."""
        for code, (logged, unlogged, level, message) in list(self._codes.items()):
            if unlogged:
                self._codes[code] = (now_ns, 0, level, message)
                log.log(logging.ERROR if level == "error" else logging.WARNING,
                        "[%s] %d more like it in the last %.0f s, the last: %s", code, unlogged,
                        (now_ns - logged) / 1e9, message)

    @staticmethod
    def _emit(level: str, code: str, message: str, repeats: int, since_ns: int) -> None:
        tail = f" ({repeats} more like it in the last {since_ns / 1e9:.0f} s)" if repeats else ""
        log.log(logging.ERROR if level == "error" else logging.WARNING, "[%s] %s%s", code, message, tail)


class Node:
    """One service's Zenoh session and its plumbing."""

    def __init__(
        self,
        service: str,
        robot: str,
        zcfg: ZenohSection,
        *,
        clock: Clock | None = None,
        listen_slot: str | None = None,
        token: bool = True,
        door: Door | None = None,
        exclusive: bool = False,
    ) -> None:
        """``exclusive``: this process is one of the pipeline's services on ``robot``; it refuses to start (a
        ConfigError naming the other) while a process of another pipeline instance is that robot's ``service``
        (:meth:`claim`)."""
        self.service = service
        self.instance = pipeline_instance()
        self._attachment = self.instance.encode()
        self.foreign = 0  # messages of another pipeline instance dropped (foreign_instance on diag/<service>)
        self.door = door  # the semantic checks of every message subscribed to (None: decoding only)
        self.refused = 0
        self.handler_errors = 0
        self._failed_before: set[tuple[str, str]] = set()  # (key, exception type) already logged with a traceback
        self.robot = robot
        self.clock = clock or MonotonicClock()
        self.stop = threading.Event()
        try:
            self.session = zenoh.open(zenoh_config(zcfg, listen_slot))
        except zenoh.ZError:
            if listen_slot is None or zcfg.router:
                raise
            # Another process holds this slot's port (a second planner, say):
            # listen on a free port instead; gossip tells the others about it.
            log.info("%s: port %d of the %s slot is taken: listening on a free port", service,
                     zcfg.base_port + SLOTS[listen_slot], listen_slot)
            self.session = zenoh.open(zenoh_config(zcfg, None))
        self._owner_token: Any = None
        if exclusive:
            try:
                self.claim()
            except ConfigError:
                self.session.close()
                raise
        self._publishers: list[Any] = []
        self._subscribers: list[Any] = []
        self._diag_seq = 0
        self._diag_lock = threading.Lock()
        self._diag_last: dict[str, tuple[int, int]] = {}  # code -> (last sent ns, suppressed)
        self._diag_log = RepeatedLog()
        self.decode_errors = 0
        self._diag_pub = self.session.declare_publisher(
            keys.key(robot, keys.diag(service)),
            priority=zenoh.Priority.DATA_LOW,
            congestion_control=zenoh.CongestionControl.DROP,
        )
        self._diag_codec = keys.codec(keys.diag(service))
        self._token: Any = None
        if token:
            self.declare_token()
        self._journal: tuple[Recording, threading.Lock, Batcher, Callable[[Any], None]] | None = None
        self._journal_thread: threading.Thread | None = None
        self._journal_stop = threading.Event()
        self._ros2: Any = None
        restart = os.environ.pop(RESTART_ENV, None)  # the process's first Node says it
        if restart:
            threading.Thread(target=self._say_restarted, args=(restart,), name="restarted", daemon=True).start()

    def owners(self, service: str = "*", timeout_s: float = OWNER_QUERY_S) -> list[keys.Owner]:
        """The live services of every pipeline on this robot (``service``: one name, or ``*`` for all)."""
        found = []
        for reply in self.session.liveliness().get(keys.key(self.robot, f"owner/{service}/**"), timeout=timeout_s):
            if reply.ok is not None:
                owner = keys.parse_owner(keys.relative_key(self.robot, str(reply.ok.key_expr)))
                if owner is not None:
                    found.append(owner)
        return sorted(found, key=lambda o: (o.service, o.since_s))

    def claim(self) -> None:
        """Drive this robot's ``service`` for this pipeline instance (its owner token), or refuse: a ConfigError
        naming the live one of another pipeline (a process started alone refuses beside any)."""
        instance = pipeline_instance()
        others = [o for o in self.owners(self.service) if instance == keys.NO_INSTANCE or o.instance != instance]
        if others:
            raise ConfigError(
                f"robot {self.robot!r} is already driven: its {others[0].describe()} is alive on "
                f"{keys.prefix(self.robot)}/. Two pipelines on one robot's keys would mix their commands: stop "
                "that pipeline, or run this one under another robot name (NWR_ROBOT=NAME or [robot] name; on one "
                "machine, another [zenoh] base_port too)")
        self._owner_token = self.session.liveliness().declare_token(keys.key(
            self.robot, keys.owner(self.service, instance, socket.gethostname(), os.getpid(), int(time.time()))))

    def declare_token(self) -> None:
        """Announce this service (``alive/<service>``); a Node declares it at once unless ``token=False``."""
        if self._token is None:
            self._token = self.session.liveliness().declare_token(keys.key(self.robot, keys.alive(self.service)))

    def withdraw_token(self) -> None:
        """No longer announce this service: to the others it is gone (a planner that keeps failing)."""
        if self._token is not None:
            self._token.undeclare()
            self._token = None

    # -- the service's wiring and its journal -------------------------------
    def wire(self, factory: Callable[..., Any], profile: Any, lock: threading.Lock, **kwargs: Any) -> Any:
        """The service's wiring, built on this node: its outputs published here, its journal on ``journal/<service>``.

        ``factory(profile, journal=, out=, diag=, **kwargs)`` builds it; every
        call into it must hold ``lock``, which the journal's batches are taken
        under too (every :data:`JOURNAL_PERIOD_S`, and a final one at close).
        """
        journal = Recording(self.clock)
        publishers: dict[str, Callable[[Any], None]] = {}

        def out(key: str, message: Any) -> None:
            publishers[key](message)

        with lock:
            run_ns = self.clock.now_ns()
            wiring = factory(profile, journal=journal, out=out, diag=self.diag, **kwargs)
        mirror = self._ros2_mirror(profile, wiring.outputs)
        for key in wiring.outputs:
            publish = self.publisher(key)
            publishers[key] = mirror.tee(key, publish) if mirror is not None else publish
        batcher = Batcher(self.service, run_ns, service_config(profile, **wiring.params()))
        self._journal = (journal, lock, batcher, self.publisher(keys.journal(self.service)))
        self._journal_thread = threading.Thread(target=self._publish_journal, name="journal", daemon=True)
        self._journal_thread.start()
        return wiring

    # -- the ROS 2 side ----------------------------------------------------------
    def ros2(self, cfg: Any) -> Any:
        """This process's ROS 2 node (:class:`nwr.common.ros2.Ros2Link`, ``cfg``: ``[ros2]``), made once."""
        if self._ros2 is None:
            from nwr.common.ros2 import Ros2Link  # rosbags' type store loads only where ROS 2 is used

            self._ros2 = Ros2Link(cfg, self.service, self.diag)
        return self._ros2

    def _ros2_mirror(self, profile: Any, outputs: tuple[str, ...]) -> Any:
        """With ``[ros2] enabled``, what publishes this service's outputs as ROS 2 topics too (nwr.common.ros2)."""
        cfg = getattr(profile, "ros2", None)
        if cfg is None or not cfg.enabled:
            return None
        from nwr.common import ros2

        if not any(ros2.mirrored(key) for key in outputs):
            return None
        return ros2.mirror(self.ros2(cfg), profile)

    def _flush_journal(self, final: bool = False) -> None:
        assert self._journal is not None
        journal, lock, batcher, publish = self._journal
        with lock:
            entries = journal.take()
        message = batcher.batch(entries, self.clock.now_ns(), final=final)
        if message is not None:
            publish(message)

    def _publish_journal(self) -> None:
        while not self._journal_stop.wait(JOURNAL_PERIOD_S):
            try:
                self._flush_journal()
            except zenoh.ZError:  # the session is closing
                return

    # -- publishing -------------------------------------------------------
    def publisher(self, relative: str) -> Callable[[Any], None]:
        """A ``publish(message)`` function for a registry key, declared once."""
        codec = keys.codec(relative)
        topic = codec.topic
        pub = self.session.declare_publisher(keys.key(self.robot, relative), **qos(topic))
        self._publishers.append(pub)
        encode = codec.encode

        attachment = self._attachment

        def publish(message: Any) -> None:
            pub.put(encode(message), attachment=attachment)

        return publish

    # -- subscribing ------------------------------------------------------
    def subscribe(self, relative: str, handler: Callable[..., None], *, keyed: bool = False,
                  direct: bool = False) -> None:
        """Call ``handler(message)`` for every valid message on a registry key (a pattern, too).

        With ``keyed``, ``handler(relative_key, message)``: which key of a
        pattern the message came on. Runs in Zenoh's callback thread. A sample that does not decode is
        counted, reported on ``diag/<service>`` and dropped; an exception in
        the handler is logged and reported, and the subscription goes on.

        With ``direct``, the handler runs on Zenoh's network thread itself
        instead of being handed to a Python thread (zenoh-python's default):
        one thread wake-up less per sample, for the reflex path. Only for a
        handler that returns quickly and whose puts (and those of any thread
        holding a lock it takes) never reach a subscription of this same
        process: Zenoh delivers those in the putting thread.
        """
        codec = keys.codec(relative)
        full = keys.key(self.robot, relative)
        door = self.door
        mine = self.instance

        def on_sample(sample: zenoh.Sample) -> None:
            if mine != keys.NO_INSTANCE and not self.accepts(sample):
                return
            try:
                message = codec.decode(sample.payload.to_bytes())
            except DecodeError as exc:
                self.decode_errors += 1
                self.diag("warning", "decode_error", f"dropped a malformed sample on {sample.key_expr}: {exc}")
                return
            if door is not None:
                refusal = door.refuse(message)
                if refusal is not None:
                    self.refused += 1
                    self.diag("warning", "refused_" + refusal.cause.replace(" ", "_"),
                              f"refused a {type(message).__name__} on {sample.key_expr}: {refusal}")
                    return
            try:
                if keyed:
                    handler(keys.relative_key(self.robot, str(sample.key_expr)), message)
                else:
                    handler(message)
            except Exception as exc:  # a bad message must never kill the subscription
                self.handler_errors += 1
                first = (full, type(exc).__name__)
                if first not in self._failed_before:  # one traceback per kind of failure, then counts
                    self._failed_before.add(first)
                    log.exception("handler for %s failed (later failures like it: diag/%s only)", full, self.service)
                self.diag("error", "handler_error", f"handling a message on {full} failed: {exc!r}")

        callback = zenoh.handlers.Callback(on_sample, indirect=False) if direct else on_sample
        self._subscribers.append(self.session.declare_subscriber(full, callback))

    def accepts(self, sample: zenoh.Sample) -> bool:
        """Whether ``sample`` comes from this pipeline (:func:`from_this_pipeline`); one that does not is
        counted (:attr:`foreign`) and reported on ``diag/<service>`` as ``foreign_instance``, every 10 s at most."""
        theirs = sender_instance(sample.attachment)
        if theirs == self.instance:  # the reflex path's case: nothing more to look at
            return True
        key = str(sample.key_expr)
        try:
            relative = keys.relative_key(self.robot, key)
        except DecodeError:
            relative = key
        if from_this_pipeline(self.instance, theirs, relative):
            return True
        self.foreign += 1
        who = "a process started alone" if theirs == keys.NO_INSTANCE else f"pipeline {theirs}"
        self.diag("warning", "foreign_instance",
                  f"dropped a message on {key} from {who}: this {self.service} is of pipeline {self.instance} "
                  f"({self.foreign} dropped so far). Another pipeline publishes on robot {self.robot!r}'s keys (a "
                  "stale process of an earlier run, or a second pipeline under the same robot name): stop it, or "
                  "run it under another robot name", every_s=FOREIGN_DIAG_EVERY_S)
        return False

    # -- diagnostics ------------------------------------------------------
    def diag(self, level: str, code: str, message: str, *, every_s: float = 1.0) -> None:
        """Log and publish a diagnostic; repeats of a code are rate limited."""
        with self._diag_lock:  # the services' threads and Zenoh's call it
            now = self.clock.now_ns()
            last, suppressed = self._diag_last.get(code, (0, 0))
            if last and now - last < every_s * 1e9:
                self._diag_last[code] = (last, suppressed + 1)
                return
            self._diag_last[code] = (now, 0)
            text = message if not suppressed else f"{message} ({suppressed} more like it suppressed)"
            if level in ("warning", "error"):
                self._diag_log.log(level, code, message, suppressed + 1, now)
            else:
                log.info("[%s] %s", code, text)
            msg = m.Diagnostic(
                seq=self._diag_seq, stamp_ns=now, service=self.service, level=level,  # type: ignore[arg-type]
                code=code, message=text, count=suppressed + 1,
            )
            self._diag_seq += 1
            try:
                self._diag_pub.put(self._diag_codec.encode(msg), attachment=self._attachment)
            except zenoh.ZError:  # the session is closing
                pass

    def _say_restarted(self, why: str) -> None:
        """A restarted service says so where a person and the session's recording see it: on its diag channel,
        once a subscriber matches it (the recorder, the view) or after :data:`RESTARTED_WAIT_S`."""
        deadline = time.monotonic() + RESTARTED_WAIT_S
        try:
            # (zenoh's stub says bool; it is a MatchingStatus)
            while not self._diag_pub.matching_status.matching and time.monotonic() < deadline:  # type: ignore[attr-defined]
                if self.stop.wait(0.02):
                    return
        except zenoh.ZError:
            return  # the session is closing
        self.diag("warning", "restarted", f"{self.service} was restarted by its launcher: {why}")

    # -- lifecycle --------------------------------------------------------
    def install_signal_handlers(self) -> None:
        """SIGINT and SIGTERM set the stop event (main thread only)."""

        def on_signal(signum: int, _frame: object) -> None:
            log.info("received %s, stopping", signal.Signals(signum).name)
            self.stop.set()

        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)

    def alive_services(self, timeout_s: float = 1.0) -> list[str]:
        """Services whose liveliness token is visible from here."""
        found = []
        for reply in self.session.liveliness().get(keys.key(self.robot, "alive/*"), timeout=timeout_s):
            if reply.ok is not None:
                found.append(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        return sorted(found)

    def wait_for(self, services: list[str], timeout_s: float) -> list[str]:
        """Wait until every named service is alive; returns those still missing."""
        deadline = time.monotonic() + timeout_s
        missing = list(services)
        while time.monotonic() < deadline and not self.stop.is_set():
            alive = set(self.alive_services(0.5))
            missing = [s for s in services if s not in alive]
            if not missing:
                break
            time.sleep(0.1)
        return missing

    def close(self) -> None:
        self._diag_log.flush(self.clock.now_ns())
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers.clear()
        if self._journal_thread is not None:
            self._journal_stop.set()
            self._journal_thread.join()
            self._journal_thread = None
            try:
                self._flush_journal(final=True)  # after the last handler: the run ends here
            except zenoh.ZError:
                log.warning("%s: the journal's last batch could not be published", self.service)
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        if self._ros2 is not None:
            self._ros2.close()
        self.session.close()

    def __enter__(self) -> Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
