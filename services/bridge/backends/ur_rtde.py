"""The real UR (e-Series, or URSim) through ur_rtde.

- Position setpoints stream with ``servoJ`` (lookahead time and gain from the
  profile), velocity setpoints with ``speedJ``; a "hold" setpoint ends the
  stream with ``servoStop`` / ``speedStop`` once the bridge's own
  jerk-limited stop has brought the arm to rest.
- The control loop is paced by the controller's clock: ``initPeriod`` /
  ``waitPeriod`` at the profile's rate (500 Hz on e-Series).
- Faults are read every cycle from RTDEReceiveInterface and
  RTDEControlInterface: emergency stop, protective stop, the control script
  not running, a lost connection. The controller has stopped the arm by then;
  the bridge reports the fault in the robot state and sends nothing until it
  is cleared. Protective and emergency stops are cleared by a person at the
  pendant, never by the bridge; once they are, the bridge re-uploads its
  control script. A lost connection is retried with exponential backoff.
- ``disconnect()`` ends any stream, stops the control script and closes both
  interfaces: the robot is released at rest.
- The controller watches the bridge: ``setWatchdog(watchdog_hz)`` right after
  every (re)connection, ``kickWatchdog`` every cycle (and from a helper thread
  between ``connect()`` and the control loop's first cycle: opening the Zenoh
  session takes longer than the watchdog's period). A bridge that hangs or
  is starved of CPU for longer than ``1 / watchdog_hz`` has the controller
  stop its control script, and with it the arm, without the bridge's help.

- A call into ur_rtde that never returns is the one thing the loop cannot
  handle itself: ur_rtde waits up to 300 s for a command's acknowledgement
  (``setWatchdog``, ``servoStop``, ``stopScript``) from a controller whose
  connection dropped meanwhile, and its own reconnection thread may end the
  process. A guard thread exits the process (code ``EXIT_STALLED``) when the
  loop has made no progress for ``stall_exit_s`` (or a stop has been under
  way that long), so that the supervisor (``nwr up``, compose) starts a fresh
  bridge; the controller holds the arm meanwhile (no command arrives) or has
  stopped it (its watchdog).
- Never silent: every ur_rtde command first waits for the control script's
  readiness, and a stream's stop (``servoStop`` / ``speedStop``) for its
  acknowledgement, both read through the controller's data stream: a stream
  that freezes would hold any call. The setpoints, the stops and the watchdog's
  kicks are therefore sent from a thread of their own
  (:class:`~nwr.services.bridge.courier.Courier`): the loop posts them and goes
  on reading and publishing the state at its rate. While one is under way,
  nothing after it reaches the controller (a newer setpoint replaces one not
  yet sent; no kick: a command unanswered for ``1 / watchdog_hz`` has the
  controller's watchdog stop the script, and with it the arm).
  A reconnection runs in a thread of its own; the lost interfaces are
  disconnected there and kept, not destroyed, while the bridge runs (ur_rtde's
  destructor holds the GIL for about 0.5 s each, which stood the whole
  process still): at most :data:`KEPT_LOST` of them, released at shutdown.

``rtde_control`` / ``rtde_receive`` are imported only when this backend
connects, so the simulated bridge and the tests never need them: the tests
pass a ``factory`` returning test doubles of the two interfaces.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import socket
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, Any

import msgspec
import numpy as np

from nwr.common.config import BridgeSection, Profile
from nwr.common.errors import ConfigError, NwrError
from nwr.common.guards import Guard
from nwr.common.robot import RobotDescription
from nwr.common.section import Section
from nwr.services.bridge.backend import Backend, Observation
from nwr.services.bridge.backends import KIND
from nwr.services.bridge.core import Setpoint
from nwr.services.bridge.courier import Courier, Kind
from nwr.services.bridge.envelope import Envelope

if TYPE_CHECKING:
    from nwr.common.robot import RobotDescription

log = logging.getLogger(__name__)

NAME = "ur_rtde"
REAL_ARM = True


class Settings(Section):
    """The UR backend's settings: ``[bridge.ur_rtde]``."""

    # servoJ lookahead time, s (UR allows 0.03-0.2; longer is
    # smoother but lags more) and proportional gain (UR allows 100-2000).
    servo_lookahead_s: Annotated[float, msgspec.Meta(ge=0.03, le=0.2)] = 0.1
    servo_gain: Annotated[float, msgspec.Meta(ge=100, le=2000)] = 300.0
    # Reconnection backoff, doubling from min to max (min <= max), s.
    reconnect_min_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 0.5
    reconnect_max_s: Annotated[float, msgspec.Meta(gt=0, le=600)] = 8.0
    # The controller's watchdog on the bridge, Hz. The bridge
    # kicks it every cycle; if no kick arrives within 1/watchdog_hz (a hung or
    # starved bridge process), the controller stops the control script and
    # with it the arm. It cannot be switched off.
    watchdog_hz: Annotated[float, msgspec.Meta(ge=1, le=125)] = 10.0


# Safety-relevant beside a person ([safety] acknowledges a value past its default on this side).
GUARDS = {"watchdog_hz": Guard("below", "Hz")}


def check_settings(cfg: Settings, profile: Profile, desc: RobotDescription) -> None:
    if cfg.reconnect_min_s > cfg.reconnect_max_s:
        raise ConfigError(f"bridge.ur_rtde.reconnect_min_s = {cfg.reconnect_min_s} s is above "
                          f"bridge.ur_rtde.reconnect_max_s = {cfg.reconnect_max_s} s: the backoff doubles from min "
                          "to max")


def make(cfg: BridgeSection, env: Envelope, q0: np.ndarray, args: argparse.Namespace,
         desc: RobotDescription) -> Backend:
    """The UR at ``--robot-ip`` (its ``[bridge.ur_rtde]`` servo and reconnection settings); it starts where it
    is."""
    ur = KIND.settings(cfg, NAME, Settings)
    return URRtdeBackend(env, 1.0 / cfg.rate_hz, args.robot_ip, lookahead_s=ur.servo_lookahead_s,
                         gain=ur.servo_gain, reconnect_min_s=ur.reconnect_min_s,
                         reconnect_max_s=ur.reconnect_max_s, watchdog_hz=ur.watchdog_hz)

# Ports the two interfaces use on the controller (see docs/bridge.md).
RTDE_PORT = 30004  # RTDE: joint state out, registers in
SCRIPT_PORTS = (30001, 30002, 30003)  # primary / secondary / real-time: the control script is sent here

Factory = Callable[[str, float], tuple[Any, Any]]
# The loop stuck in one call into ur_rtde for this long has hung (see the module's docstring), s.
STALL_EXIT_S = 20.0
EXIT_STALLED = 75  # EX_TEMPFAIL: try again, i.e. start a fresh bridge
# At release, a reconnection attempt under way is waited for this long (what it connects is released too), s.
RECONNECT_JOIN_S = 10.0
# A command the controller answered later than this is reported, s.
SLOW_COMMAND_S = 0.1
# The loop kicks the controller's watchdog this many times per watchdog period (1 / watchdog_hz): 100 Hz at the
# default 10 Hz, at most once per control cycle.
KICKS_PER_PERIOD = 10
# Lost interfaces kept undestroyed while the bridge runs (each reconnection loses two; beyond this, the oldest are
# destroyed, a pause of about 0.5 s each: see the module's docstring).
KEPT_LOST = 16
# Before a reconnection, the controller's RTDE port must accept a connection within this long, s.
PROBE_TIMEOUT_S = 1.0
# ... and keep it open this long, s.
PROBE_OPEN_S = 0.25


class RobotConnectionError(NwrError):
    """The robot controller cannot be reached or refuses the control script."""


def rtde_factory(robot_ip: str, frequency_hz: float) -> tuple[Any, Any]:
    """The real ur_rtde interfaces (imported here, lazily)."""
    try:
        import rtde_control
        import rtde_receive
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise RobotConnectionError(
            f"the ur_rtde backend needs the ur-rtde package ({exc}): pip install ur-rtde"
        ) from exc
    # Receive first: it fails fast when the IP is wrong, before a script is uploaded.
    receive = rtde_receive.RTDEReceiveInterface(robot_ip, frequency_hz)
    try:
        control = rtde_control.RTDEControlInterface(robot_ip, frequency_hz)
    except BaseException:
        receive.disconnect()  # now, not whenever the failed attempt's traceback is collected
        raise
    return control, receive


def probe_rtde(robot_ip: str) -> None:
    """Raise OSError unless the controller's RTDE port accepts a connection and keeps it open (a server that
    closes it at once, as a controller that is starting or refusing, does not count)."""
    with socket.create_connection((robot_ip, RTDE_PORT), timeout=PROBE_TIMEOUT_S) as probe:
        probe.settimeout(PROBE_OPEN_S)
        try:
            if probe.recv(1) == b"":
                raise ConnectionRefusedError(f"{robot_ip}:{RTDE_PORT} closed the connection at once")
        except TimeoutError:
            pass  # open and silent, as an RTDE server is until asked


class RtdePacer:
    """Paces the bridge loop with the controller's ``initPeriod`` / ``waitPeriod``."""

    def __init__(self, backend: URRtdeBackend, rate_hz: float) -> None:
        self.backend = backend
        self.period_s = 1.0 / rate_hz
        self.ticks = 0
        self.starting = True  # the controller paces the loop: nothing here to warn about either way
        self._t: Any = None
        self._t_local = time.monotonic()

    def sleep(self, stop: threading.Event | None = None) -> bool:
        self.backend.take_over()  # the loop kicks the watchdog from now on
        self.backend.progress_at = time.monotonic()  # a cycle went through: nothing hung (the stall guard)
        control = self.backend.control
        # (initPeriod / waitPeriod read the local clock only; the kick goes through the courier, and reaches the
        # controller only once a command under way has been answered.)
        if control is not None and self.backend.connected:
            try:
                if self._t is not None:
                    control.waitPeriod(self._t)
                self._t = control.initPeriod()
                self.backend.kick()
            except RuntimeError:
                self._t = None
                self.backend.lost("waitPeriod failed")
        else:
            # Disconnected: keep the loop alive (the state reports the fault).
            self._t = None
            self._t_local += self.period_s
            delay = self._t_local - time.monotonic()
            if delay > 0:
                if stop is None:
                    time.sleep(delay)
                elif stop.wait(delay):
                    return False
            else:
                self._t_local = time.monotonic()
        self.ticks += 1
        return stop is None or not stop.is_set()

    def summary(self) -> str:
        return f"bridge: {self.ticks} cycles paced by the UR controller at {1 / self.period_s:.0f} Hz"


class URRtdeBackend(Backend):
    """A UR arm through ur_rtde's RTDEControlInterface and RTDEReceiveInterface."""

    name = "ur_rtde"

    def __init__(
        self,
        env: Envelope,
        dt: float,
        robot_ip: str,
        *,
        lookahead_s: float = 0.1,
        gain: float = 300.0,
        reconnect_min_s: float = 0.5,
        reconnect_max_s: float = 8.0,
        watchdog_hz: float = 10.0,
        factory: Factory = rtde_factory,
        clock: Callable[[], float] = time.monotonic,
        stall_exit_s: float | None = None,
        reconnect_in_thread: bool | None = None,
        commands_in_thread: bool | None = None,
    ) -> None:
        """``stall_exit_s``: the stall guard's limit (default :data:`STALL_EXIT_S` with the real ur_rtde;
        none with a test double's ``factory`` unless given); ``reconnect_in_thread``: reconnection attempts in a
        thread of their own, the control loop going on meanwhile (default: with the real ur_rtde only);
        ``commands_in_thread``: the setpoints, stops and kicks sent from a thread of their own, the loop never
        waiting on them (default: with the real ur_rtde only; a test double's answer at once)."""
        super().__init__(env, dt)
        if not robot_ip:
            raise RobotConnectionError("the ur_rtde backend needs the robot's IP address (--robot-ip)")
        self.robot_ip = robot_ip
        self.lookahead_s = lookahead_s
        self.gain = gain
        # servoJ's lag behind its target: a first-order lag whose time constant grows with the lookahead time and
        # shrinks with the gain (the controller emulator's model; 0.1 s at the defaults). The bridge's check of
        # the reported state allows bridge.following_lag_s per rad/s on top (docs/bridge.md).
        self.lag_s = min(0.2, lookahead_s) * 300.0 / max(gain, 100.0)
        self.reconnect_min_s = reconnect_min_s
        self.reconnect_max_s = reconnect_max_s
        self.watchdog_hz = watchdog_hz
        self.factory = factory
        self.clock = clock
        self.control: Any = None
        self.receive: Any = None
        self.connected = False
        self.streaming: str | None = None  # "servo" or "speed" while a stream runs on the controller
        self.backoff_s = reconnect_min_s
        self.next_attempt = 0.0
        self.reconnects = 0
        self.fault_reason = ""
        # Whether the running control script has the watchdog armed: after a
        # re-upload it is armed only once the script runs (setWatchdog fails before).
        self.watchdog_armed = False
        # Between connect() and the control loop's first cycle (the Zenoh
        # session, the wiring: easily longer than 1 / watchdog_hz) a thread
        # kicks the watchdog, under this lock; the pacer takes over.
        self._control_lock = threading.RLock()
        self._keepalive: threading.Thread | None = None
        self._keepalive_stop = threading.Event()
        # The stall guard: the loop's last sign of progress (monotonic s), watched from a thread.
        self.stall_exit_s = stall_exit_s if stall_exit_s is not None else (
            STALL_EXIT_S if factory is rtde_factory else 0.0)
        self.progress_at = time.monotonic()
        self.reconnect_in_thread = reconnect_in_thread if reconnect_in_thread is not None else \
            factory is rtde_factory
        self._connector: threading.Thread | None = None
        self.commands_in_thread = commands_in_thread if commands_in_thread is not None else \
            factory is rtde_factory
        # Its thread starts in connect(): it inherits the real-time scheduling the bridge sets up after making its
        # backend (under load, a thread of the normal scheduler beside a SCHED_FIFO loop missed most cycles).
        self.courier = Courier("rtde-commands", threaded=False)
        self.slow_commands = 0  # commands the controller answered later than SLOW_COMMAND_S
        self._kicked_at = -math.inf  # when the loop last posted a watchdog kick (monotonic s)
        self._lost_interfaces: list[Any] = []  # disconnected, kept undestroyed (KEPT_LOST)
        self._attempt_at = 0.0  # when the last reconnection attempt began (the clock's), s
        self._connected_pair: tuple[Any, Any] | None = None
        self._connect_error: BaseException | None = None
        self._guard: threading.Thread | None = None
        self._guard_stop = threading.Event()
        self.last_q = np.zeros(env.n)
        # The controller's own ramps: never steeper than the envelope's
        # slowest joint (the bridge's setpoints already are).
        self.acceleration = float(np.min(env.a_max))
        self.speed = float(np.min(env.v_max))

    # -- connection -------------------------------------------------------------------
    def connect(self) -> None:
        """Connect, or raise RobotConnectionError with what to check."""
        self._start_guard()
        if self.courier.closed or self.courier.threaded != self.commands_in_thread:
            self.courier = Courier("rtde-commands", threaded=self.commands_in_thread)
        try:
            self.control, self.receive = self.factory(self.robot_ip, 1.0 / self.dt)
            armed = self._arm_watchdog()
        except RobotConnectionError:
            raise
        except (RuntimeError, OSError) as exc:
            raise RobotConnectionError(
                f"cannot connect to the UR controller at {self.robot_ip} ({exc}): check the IP, that the robot "
                f"is powered on and in remote control mode, and that ports {RTDE_PORT} (RTDE) and "
                f"{', '.join(map(str, SCRIPT_PORTS))} are reachable (docs/bridge.md)"
            ) from exc
        if not armed:
            self.disconnect()
            raise RobotConnectionError(f"the UR controller at {self.robot_ip} refused the RTDE watchdog at "
                                       f"{self.watchdog_hz:g} Hz: the bridge does not run the arm without it")
        self.connected = True
        self.watchdog_armed = True
        self.streaming = None
        self.backoff_s = self.reconnect_min_s
        self.last_q = self._read_q()
        self.last_sent = self.last_q.copy()
        if self.factory is rtde_factory:  # test doubles (tests/test_rtde_backend.py) have no watchdog to feed
            self._start_keepalive()
        log.info("connected to the UR controller at %s (RTDE at %.0f Hz)", self.robot_ip, 1.0 / self.dt)

    def _start_guard(self) -> None:
        """Exit the process when the loop has made no progress for ``stall_exit_s`` (a hung ur_rtde call)."""
        if self.stall_exit_s <= 0.0 or self._guard is not None:
            return
        self.progress_at = time.monotonic()
        self._guard_stop.clear()

        def watch() -> None:
            while not self._guard_stop.wait(min(1.0, self.stall_exit_s / 4)):
                stalled = time.monotonic() - self.progress_at
                stalled = max(stalled, self.courier.busy_s())  # a command under way hangs as well as the loop could
                if stalled > self.stall_exit_s:
                    log.critical("a call into ur_rtde has not returned for %.0f s (the connection to %s dropped "
                                 "while it waited for the controller?): exiting so that a fresh bridge is started; "
                                 "the controller holds the arm or its watchdog has stopped it", stalled,
                                 self.robot_ip)
                    for handler in logging.getLogger().handlers:
                        handler.flush()
                    sys.stderr.flush()
                    os._exit(EXIT_STALLED)

        self._guard = threading.Thread(target=watch, name="rtde-stall-guard", daemon=True)
        self._guard.start()

    def _stop_guard(self) -> None:
        if self._guard is not None:
            self._guard_stop.set()
            self._guard.join()
            self._guard = None

    def _start_keepalive(self) -> None:
        """Kick the watchdog from a thread while no control loop does: from connect() to the loop's first cycle,
        and from the loop's end to disconnect() (both end with :meth:`take_over`)."""
        self._keepalive_stop.clear()
        period = min(0.25 / self.watchdog_hz, 0.02)

        def kick() -> None:
            while not self._keepalive_stop.wait(period):
                with self._control_lock:
                    try:
                        if self.control is not None:
                            self.control.kickWatchdog()
                            self.progress_at = time.monotonic()
                    except RuntimeError as exc:
                        log.warning("kicking the RTDE watchdog outside the control loop: %s", exc)
                        return

        self._keepalive = threading.Thread(target=kick, name="rtde-watchdog-keepalive", daemon=True)
        self._keepalive.start()

    def take_over(self) -> None:
        """The control loop runs, or the robot is released: stop the keepalive thread (the pacer kicks the
        watchdog)."""
        if self._keepalive is not None:
            self._keepalive_stop.set()
            self._keepalive.join()
            self._keepalive = None

    def _arm_watchdog(self) -> bool:
        """The controller's watchdog on this bridge, set whenever its control script (re)starts.

        It lives in the control script: every new connection and every
        re-upload of the script needs it again. False if the controller
        refused it.
        """
        if not self.control.setWatchdog(self.watchdog_hz):
            return False
        log.info("RTDE watchdog armed: the controller stops the arm if the bridge is silent for %.0f ms",
                 1e3 / self.watchdog_hz)
        return True

    def lost(self, reason: str) -> None:
        """The connection dropped: schedule a reconnection with backoff."""
        if self.connected:
            log.error("connection to the UR controller at %s lost: %s", self.robot_ip, reason)
        self.connected = False
        self.streaming = None
        self.courier.clear()  # nothing posted for this connection goes to the next one
        self.fault_reason = reason
        self.next_attempt = max(self.next_attempt, self.clock())

    def _try_reconnect(self) -> None:
        """Reconnect with backoff; with the real ur_rtde in a thread of its own, so that the control loop goes on
        publishing the state (``disconnected``) meanwhile: ur_rtde's constructors retry for as long as the
        controller refuses connections (2 s of a dropped connection blocked the loop 2 s)."""
        connector = self._connector
        if connector is not None:
            if connector.is_alive():
                return  # an attempt under way
            connector.join()
            self._connector = None
            self._finish_reconnect()
            return
        now = self.clock()
        if now < self.next_attempt or not self.courier.idle():  # (the lost interfaces are in use until it is)
            return
        self.reconnects += 1
        self._attempt_at = now
        # Fresh interfaces, never ur_rtde's reconnect(): after a dropped
        # connection, RTDEReceiveInterface.reconnect() / RTDEControlInterface.reconnect()
        # following failed attempts corrupted the heap (ur_rtde 1.6.5: "malloc(): mismatching
        # next->prev_size", the bridge killed by SIGABRT; tests/test_ur_bridge_e2e.py).
        old = [self.control, self.receive]
        self.control = self.receive = None
        if not self.reconnect_in_thread:
            self._attempt(old)
            self._finish_reconnect()
            return
        self._connector = threading.Thread(target=self._attempt, args=(old,), name="rtde-reconnect", daemon=True)
        self._connector.start()

    def _attempt(self, old: list[Any]) -> None:
        """One connection attempt (possibly in its own thread): the lost interfaces closed, fresh ones made.

        The lost interfaces are disconnected here, in this thread (it takes about 0.5 s each, the GIL released),
        and kept: ur_rtde's destructor holds the GIL for about 0.5 s each, whichever thread runs it
        (:meth:`_keep_lost`).
        """
        self._connected_pair = None
        self._connect_error = None
        try:
            self._discard(*old)
            self._keep_lost(old)
            old.clear()
            if self.factory is rtde_factory:
                # ur_rtde's constructors hold the GIL while they retry a refused connection (a second and
                # more: the loop stood still even with this attempt in its own thread): only once the
                # controller accepts connections again are they called.
                probe_rtde(self.robot_ip)
            self._connected_pair = self.factory(self.robot_ip, 1.0 / self.dt)
        except (RuntimeError, OSError) as exc:
            old.clear()
            self._connect_error = exc.with_traceback(None)

    def _keep_lost(self, interfaces: list[Any]) -> None:
        """Keep disconnected interfaces undestroyed (at most :data:`KEPT_LOST`; the oldest beyond are destroyed
        here, a pause of the whole process)."""
        self._lost_interfaces.extend(i for i in interfaces if i is not None)
        excess = len(self._lost_interfaces) - KEPT_LOST
        if excess > 0:
            log.warning("releasing %d lost ur_rtde interface(s) of earlier connections: ur_rtde's destructor stands "
                        "the bridge still for about 0.5 s each", excess)
            del self._lost_interfaces[:excess]

    def _finish_reconnect(self) -> None:
        """The attempt's outcome, in the control loop: the watchdog armed and the connection used, or backoff."""
        pair, error = self._connected_pair, self._connect_error
        self._connected_pair = self._connect_error = None
        ok = False
        if pair is not None:
            self.control, self.receive = pair
            try:
                ok = True
                if not self._arm_watchdog():
                    self.control.stopScript()  # never a running script the controller does not watch
                    raise RuntimeError(f"the controller refused the RTDE watchdog at {self.watchdog_hz:g} Hz")
            except (RuntimeError, OSError) as exc:
                error = exc
                ok = False
        if not ok:
            self.fault_reason = f"reconnection {self.reconnects} failed ({error})"
        if ok:
            log.info("reconnected to the UR controller at %s (attempt %d)", self.robot_ip, self.reconnects)
            self.connected = True
            self.watchdog_armed = True
            self.streaming = None
            self.backoff_s = self.reconnect_min_s
            self.last_sent = None
        else:
            self.next_attempt = self._attempt_at + self.backoff_s
            log.warning("%s: next attempt in %.1f s", self.fault_reason, self.backoff_s)
            self.backoff_s = min(2.0 * self.backoff_s, self.reconnect_max_s)

    @staticmethod
    def _discard(*interfaces: Any) -> None:
        """Close the interfaces of a lost connection (errors ignored: it is gone)."""
        for interface in interfaces:
            if interface is not None:
                try:
                    interface.disconnect()
                except RuntimeError as exc:
                    log.debug("closing a lost interface: %s", exc)

    def disconnect(self) -> None:
        """Release the robot: end the stream, stop the control script, close both interfaces."""
        self.take_over()
        self.progress_at = time.monotonic()  # releasing may hang too: the guard still watches
        connector = self._connector
        if connector is not None:  # an attempt under way: what it connects is released too
            connector.join(timeout=RECONNECT_JOIN_S)
            self._connector = None
            if self._connected_pair is not None and self.control is None:
                self.control, self.receive = self._connected_pair
                self._connected_pair = None
        control, receive = self.control, self.receive
        if control is not None and self.connected:
            self._end_stream()
        self.courier.close()  # what is under way and waiting ends first (the stall guard watches it)
        if (error := self.courier.error()) is not None:
            log.warning("while releasing the robot: %s", error)
        if control is not None:
            for call in (control.stopScript, control.disconnect):
                try:
                    call()
                except RuntimeError as exc:
                    log.warning("while releasing the robot: %s", exc)
        if receive is not None:
            try:
                receive.disconnect()
            except RuntimeError as exc:
                log.warning("while releasing the robot: %s", exc)
        self.control = self.receive = None
        self.connected = False
        self.streaming = None
        self._lost_interfaces.clear()  # their destructors, now that the loop has ended
        self._stop_guard()

    # -- observation ------------------------------------------------------------------
    def _read_q(self) -> np.ndarray:
        return np.asarray(self.receive.getActualQ(), dtype=float)

    def get_observation(self) -> Observation:
        with self._control_lock:
            return self._observe()

    def _observe(self) -> Observation:
        if self.connected and (error := self.courier.error()) is not None:
            self.lost(str(error))  # a command failed in the courier's thread: as it failed here before
        if not self.connected or self.receive is None or self.control is None:
            self._try_reconnect()
            if not self.connected:
                return Observation(self.last_q.copy(), np.zeros(self.env.n), "disconnected",
                                   f"{self.robot_ip}: {self.fault_reason}")
        try:
            if not (self.receive.isConnected() and self.control.isConnected()):
                self.lost("isConnected() is false")
                return Observation(self.last_q.copy(), np.zeros(self.env.n), "disconnected",
                                   f"{self.robot_ip}: connection lost, reconnecting")
            q = self._read_q()
            dq = np.asarray(self.receive.getActualQd(), dtype=float)
            stamp = float(self.receive.getTimestamp())  # the controller's clock: how far apart two reports are
            if q.shape != (self.env.n,) or dq.shape != (self.env.n,):
                self.lost(f"getActualQ returned {q.tolist()}, getActualQd {dq.tolist()}")
                return Observation(self.last_q.copy(), np.zeros(self.env.n), "disconnected", self.fault_reason)
            if np.isfinite(q).all():  # a non-finite report is passed on: the bridge's check stops the arm on it
                self.last_q = q
            if self.receive.isEmergencyStopped():
                self.streaming = None
                return Observation(q, dq, "emergency_stop", "emergency stop pressed: release it and restart the arm")
            if self.receive.isProtectiveStopped():
                self.streaming = None
                return Observation(q, dq, "protective_stop",
                                   "protective stop: check the cell, then unlock it on the pendant")
            if not self.control.isProgramRunning():
                self.streaming = None
                self.watchdog_armed = False  # the watchdog lives in the script
                if self.clock() >= self.next_attempt and self.courier.idle():
                    # Uploading the script moves nothing; the bridge sends a
                    # setpoint only after the fault has cleared and the
                    # script runs with the watchdog armed (below).
                    self.next_attempt = self.clock() + self.backoff_s
                    self.backoff_s = min(2.0 * self.backoff_s, self.reconnect_max_s)
                    if self.control.reuploadScript():
                        if self._arm_watchdog():
                            self.watchdog_armed = True
                            self.backoff_s = self.reconnect_min_s
                            log.info("control script re-uploaded")
                        else:  # never a running script the controller does not watch
                            self.control.stopScript()
                            log.warning("control script re-uploaded, but the RTDE watchdog could not be armed (the "
                                        "script not running yet, or the controller refuses it): stopped it again; "
                                        "retrying with backoff")
                return Observation(q, dq, "script_not_running",
                                   "the ur_rtde control script is not running (remote control mode? program stopped "
                                   "on the pendant?): re-uploading it with backoff")
            if not self.watchdog_armed and self.courier.idle():
                # A re-uploaded script that started after all: ur_rtde's
                # reuploadScript() does not wait for it to run, and
                # setWatchdog() fails until it does (so may stopScript()).
                if not self._arm_watchdog():  # never a running script the controller does not watch
                    self.control.stopScript()
                    log.warning("the controller refused the RTDE watchdog: stopped the control script again; "
                                "retrying with backoff")
                    return Observation(q, dq, "script_not_running",
                                       "the controller refused the RTDE watchdog: control script stopped, "
                                       "re-uploading it with backoff")
                self.watchdog_armed = True
                self.backoff_s = self.reconnect_min_s
                log.info("control script running again, RTDE watchdog armed")
        except RuntimeError as exc:
            self.lost(str(exc))
            return Observation(self.last_q.copy(), np.zeros(self.env.n), "disconnected", self.fault_reason)
        self.backoff_s = self.reconnect_min_s
        return Observation(q, dq, stamp_s=stamp)

    # -- commands ---------------------------------------------------------------------
    def _post(self, kind: Kind, what: str, call: Callable[..., Any], *args: Any) -> None:
        """Send ``call(*args)`` through the courier; a refusal (False) or a late answer is reported."""

        def send() -> None:
            started = time.monotonic()
            ok = call(*args)
            took = time.monotonic() - started
            if took > SLOW_COMMAND_S:
                self.slow_commands += 1
                log.warning("the controller answered %s after %.0f ms (its data stream stalled?); the control loop "
                            "went on meanwhile, sending nothing else", what, took * 1e3)
            if ok is False:
                log.warning("the controller refused %s (script not running?)", what)

        self.courier.post(kind, send)

    def kick(self) -> None:
        """Kick the controller's watchdog: called each control cycle, sent :data:`KICKS_PER_PERIOD` times per
        watchdog period (each kick is a wake of the courier's thread; the controller needs one per period)."""
        now = time.monotonic()
        if now - self._kicked_at < 1.0 / (KICKS_PER_PERIOD * self.watchdog_hz):
            return
        self._kicked_at = now
        self._post("kick", "a watchdog kick", self.control.kickWatchdog)

    def _end_stream(self) -> None:
        """End the stream (``servoStop`` / ``speedStop``)."""
        if self.streaming is None:
            return
        stop = self.control.servoStop if self.streaming == "servo" else self.control.speedStop
        self.streaming = None
        self._post("stop", "the stream's stop", stop, self.acceleration)

    def _send(self, setpoint: Setpoint) -> None:
        if not self.connected or self.control is None:
            return
        try:
            if setpoint.mode == "hold":
                self._end_stream()
            elif setpoint.mode == "position":
                # ur_rtde's Python servoJ takes positional arguments only:
                # (q, speed, acceleration, time, lookahead_time, gain); speed
                # and acceleration are not used by the controller in servoj.
                self._post("motion", "a position setpoint", self.control.servoJ, setpoint.q.tolist(), self.speed,
                           self.acceleration, self.dt, self.lookahead_s, self.gain)
                self.streaming = "servo"
            else:
                self._post("motion", "a velocity setpoint", self.control.speedJ, setpoint.dq.tolist(),
                           self.acceleration, self.dt)
                self.streaming = "speed"
        except RuntimeError as exc:  # (sent at once, without the courier's thread)
            self.lost(str(exc))

    def wind_down(self, timeout_s: float) -> bool:
        answered = self.courier.wait_idle(timeout_s)
        if self.connected and self.factory is rtde_factory:
            # The Zenoh session closes before disconnect(): kicked from a thread meanwhile, the controller's
            # watchdog does not stop the script on its own (a fault on its log) before disconnect() does.
            self._start_keepalive()
        return answered

    def resync(self, q: np.ndarray) -> None:
        super().resync(q)
        self.streaming = None

    def pacer(self, rate_hz: float) -> RtdePacer:
        return RtdePacer(self, rate_hz)
