"""A Franka arm (FR3, Panda) through franky (``franky-control``: libfranka inside), or franky-sim.

- libfranka's 1 kHz real-time loop stays in franky's C++ thread: the bridge
  starts one joint impedance tracking motion (``JointImpedanceTrackingMotion``,
  torque control with Franka's gravity compensation) and streams each control
  cycle's setpoint to it as its reference (``set_reference(q, dq)``), which
  the C++ loop picks up at its next cycle. Position and velocity setpoints are
  both sent as a position and a velocity (the bridge integrates its velocity
  setpoints); a "hold" keeps the reference at rest where the bridge's stop
  ended, so the arm is held stiffly, not released. Re-targeting franky's
  ``JointMotion`` with ``asynchronous=True`` every cycle instead followed a
  0.5 Hz sine of 0.2 rad in franky-sim with a median error of 131 mrad,
  against 5.7 mrad for the tracking motion (docs/bridge.md).
- The state is read every cycle from franky's last robot state: joint
  positions and velocities, Franka's estimated external torques
  (``tau_ext_hat_filtered``, recorded in ``RobotState.tau_ext``), the
  controller's time (the bridge's check of the reports times them by it) and
  the robot's mode.
- Faults, each a status with the reason (``RobotState.detail``):

  * ``robot_reflex``: Franka's own reflex stopped the arm (a collision
    threshold, a limit, a discontinuity: libfranka's errors in the detail).
    Once the arm has rested ``recover_rest_s``, the bridge calls libfranka's
    automatic error recovery (``recover_from_errors``) with backoff, then
    waits for a fresh command as after any fault.
  * ``emergency_stop``: the user stop (the external activation device) is
    pressed; a person releases it.
  * ``motion_refused``: the robot is in no mode to be moved (guiding, brakes
    locked, FCI off: its mode in the detail) or refused the bridge's motion;
    tried again with backoff.
  * ``disconnected``: no new state for ``state_timeout_s`` (libfranka takes
    about a second to notice a dead connection), or the connection failed:
    a fresh ``franky.Robot`` is made with backoff, in a thread of its own, the
    bridge publishing its state (the last pose, stale) meanwhile. The arm:
    libfranka's controller stops it when its commands stop arriving.

- ``disconnect()`` ends the motion with franky's ``TorqueStopMotion`` (the
  last torque blended into damping, the arm at rest) and releases the robot.

``franky`` is imported only when this backend connects; the tests pass a
``factory`` returning a test double of :class:`FrankyLink`.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import msgspec
import numpy as np

from nwr.common import messages as m
from nwr.common.config import BridgeSection, Profile
from nwr.common.errors import ConfigError, NwrError
from nwr.common.guards import Guard
from nwr.common.robot import RobotDescription
from nwr.common.section import Section
from nwr.services.bridge.backend import Backend, Observation
from nwr.services.bridge.backends import KIND
from nwr.services.bridge.core import Setpoint
from nwr.services.bridge.envelope import Envelope

log = logging.getLogger(__name__)

NAME = "franky"
REAL_ARM = True
JOINTS = 7  # franky drives Franka's 7-joint arms

Stiffness = Annotated[float, msgspec.Meta(gt=0, le=3000)]


class Settings(Section):
    """The Franka backend's settings: ``[bridge.franky]``."""

    # libfranka's check for a real-time kernel: "enforce" on the lab PC of a real arm (Franka requires a
    # PREEMPT_RT kernel), "ignore" for franky-sim on an ordinary machine.
    realtime: Literal["enforce", "ignore"] = "enforce"
    # The joint impedance that tracks the bridge's setpoints, N m/rad per joint (Franka's joint impedance
    # example's gains); damping is critical.
    stiffness_nm_rad: list[Stiffness] = msgspec.field(
        default_factory=lambda: [600.0, 600.0, 600.0, 600.0, 250.0, 150.0, 50.0])
    # Franka's collision reflex: an estimated external torque above this on a joint, N m, or a force at the
    # end effector above collision_force_n, N, stops the arm (robot_reflex).
    collision_torque_nm: Annotated[float, msgspec.Meta(gt=0, le=100)] = 20.0
    collision_force_n: Annotated[float, msgspec.Meta(gt=0, le=200)] = 30.0
    # No new state from the controller (1 kHz) for this long is a lost connection, s (the bridge's check of a
    # frozen report, bridge.report_frozen_s, is 0.1 s too).
    state_timeout_s: Annotated[float, msgspec.Meta(ge=0.005, le=1)] = 0.1
    # After Franka's reflex, the arm rests this long before the bridge calls libfranka's error recovery, s.
    recover_rest_s: Annotated[float, msgspec.Meta(ge=0, le=60)] = 1.0
    # Reconnection and recovery backoff, doubling from min to max (min <= max), s.
    reconnect_min_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 0.5
    reconnect_max_s: Annotated[float, msgspec.Meta(gt=0, le=600)] = 8.0


# Safety-relevant beside a person ([safety] acknowledges a value past its default on this side).
GUARDS = {
    "collision_torque_nm": Guard("above", "N m"),
    "collision_force_n": Guard("above", "N"),
    "state_timeout_s": Guard("above", "s"),
    "recover_rest_s": Guard("below", "s"),
}


def check_settings(cfg: Settings, profile: Profile, desc: RobotDescription) -> None:
    if profile.bridge.backend == NAME and len(desc.joints) != JOINTS:
        raise ConfigError(f"bridge.backend = \"franky\" drives Franka's {JOINTS}-joint arms: the robot "
                          f"{desc.name} has {len(desc.joints)} joints (robot.description = \"fr3\")")
    if len(cfg.stiffness_nm_rad) != JOINTS:
        raise ConfigError(f"bridge.franky.stiffness_nm_rad has {len(cfg.stiffness_nm_rad)} values: give one per "
                          f"joint ({JOINTS})")
    if cfg.reconnect_min_s > cfg.reconnect_max_s:
        raise ConfigError(f"bridge.franky.reconnect_min_s = {cfg.reconnect_min_s} s is above "
                          f"bridge.franky.reconnect_max_s = {cfg.reconnect_max_s} s: the backoff doubles from min "
                          "to max")


def make(cfg: BridgeSection, env: Envelope, q0: np.ndarray, args: argparse.Namespace,
         desc: RobotDescription) -> Backend:
    """The Franka arm at ``--robot-ip`` (franky-sim: 127.0.0.1), with its ``[bridge.franky]`` settings."""
    return FrankyBackend(env, 1.0 / cfg.rate_hz, args.robot_ip, KIND.settings(cfg, NAME, Settings))


class RobotConnectionError(NwrError):
    """The Franka controller cannot be reached, or refuses the connection."""


# The impedance law's lag behind a moving reference (franky-sim, default stiffness: 5.7 mrad at 0.63 rad/s),
# s: the bridge's model of where the arm should be (checks.StateCheck).
LAG_S = 0.01
# Below this speed on every joint the arm is at rest (before a recovery), rad/s.
REST_RAD_S = 0.01
# A frozen stream is read this often from its thread, s.
PROBE_EVERY_S = 0.002
# At release: how long the stop motion may take, s.
RELEASE_S = 3.0


@dataclass(frozen=True)
class Report:
    """One state of the controller, as the backend uses it."""

    q: np.ndarray
    dq: np.ndarray
    tau_ext: np.ndarray  # estimated external torque per joint, N m
    time_s: float  # the controller's clock
    mode: str  # franky.RobotMode's name: Idle, Move, Reflex, UserStopped, Guiding, AutomaticErrorRecovery, Other
    errors: str  # libfranka's current errors, readable ("" when none)


class LinkLost(NwrError):
    """The connection to the controller failed (libfranka's network error)."""


class MotionRefused(NwrError):
    """The controller refused or ended a motion (libfranka's control or command error)."""


class FrankyLink:
    """The few calls into franky, in one place: connect, read, stream, recover, stop. franky's exceptions leave
    it as :class:`LinkLost` (the network) or :class:`MotionRefused` (anything else the controller says)."""

    def __init__(self, host: str, settings: Settings) -> None:
        try:
            import franky
        except ImportError as exc:  # pragma: no cover - depends on the installation
            raise RobotConnectionError(f"the franky backend needs franky-control ({exc}): pip install "
                                       "franky-control") from exc
        self.franky = franky
        self.settings = settings
        self.network = (franky.NetworkException, franky.ProtocolException, RuntimeError)
        self.refusals = (franky.Exception, franky.InvalidMotionTypeException, franky.MotionReuseException,
                         franky.TorqueSignalTimeoutException, franky.ReactionRecursionException)
        realtime = franky.RealtimeConfig.Enforce if settings.realtime == "enforce" else franky.RealtimeConfig.Ignore
        try:
            self.robot = franky.Robot(host, realtime_config=realtime,
                                      default_torque_threshold=settings.collision_torque_nm,
                                      default_force_threshold=settings.collision_force_n)
        except self.refusals + self.network as exc:
            raise RobotConnectionError(f"cannot connect to the Franka controller at {host} ({exc}): check the "
                                       "address, that FCI is activated in Desk and the brakes are open, and "
                                       "(a real arm) a real-time kernel") from None
        self.motion: Any = None

    def _call(self, call: Callable[[], Any]) -> Any:
        try:
            return call()
        except self.network as exc:
            raise LinkLost(f"{type(exc).__name__}: {exc}") from None
        except self.refusals as exc:
            raise MotionRefused(f"{type(exc).__name__}: {exc}") from None

    def read(self) -> Report:
        state = self._call(lambda: self.robot.state)
        errors = str(state.current_errors)
        return Report(np.asarray(state.q, dtype=float), np.asarray(state.dq, dtype=float),
                      np.asarray(state.tau_ext_hat_filtered, dtype=float), state.time.to_sec(),
                      state.robot_mode.name, "" if errors == "[]" else errors)

    def motion_error(self) -> str:
        """Why the streaming motion ended ("" while it runs, or when there is none)."""
        if self.motion is None:
            return ""
        try:
            self._call(lambda: self.robot.join_motion(0.0))
        except MotionRefused as exc:
            self.motion = None
            return str(exc)
        if not self._call(lambda: self.robot.is_in_control):
            self.motion = None
            return "the motion ended"
        return ""

    def start(self, q: np.ndarray) -> None:
        """The tracking motion, its reference at ``q``."""
        f = self.franky
        motion = f.JointImpedanceTrackingMotion(stiffness=np.asarray(self.settings.stiffness_nm_rad, dtype=float))
        motion.set_reference(f.JointReference(q, np.zeros(JOINTS)))
        self._call(lambda: self.robot.move(motion, asynchronous=True))
        self.motion = motion

    def target(self, q: np.ndarray, dq: np.ndarray) -> None:
        reference = self.franky.JointReference(q, dq)
        self._call(lambda: self.motion.set_reference(reference))

    def recover(self) -> bool:
        return bool(self._call(self.robot.recover_from_errors))

    def stop(self) -> None:
        """End the motion at rest (franky's TorqueStopMotion: the last torque blended into damping)."""
        if self.motion is not None and self._call(lambda: self.robot.is_in_control):
            self._call(lambda: self.robot.move(self.franky.TorqueStopMotion(), asynchronous=True))
            self._call(lambda: self.robot.join_motion(RELEASE_S))
        self.motion = None


Factory = Callable[[str, Settings], Any]


class FrankyBackend(Backend):
    """A Franka arm through franky: one impedance tracking motion, its reference streamed each cycle."""

    name = NAME
    lag_s = LAG_S

    def __init__(self, env: Envelope, dt: float, host: str, settings: Settings, *,
                 factory: Factory = FrankyLink, clock: Callable[[], float] = time.monotonic,
                 reconnect_in_thread: bool | None = None) -> None:
        """``reconnect_in_thread``: reconnection attempts in a thread of their own, the control loop going on
        meanwhile (default: with the real franky only)."""
        super().__init__(env, dt)
        if not host:
            raise RobotConnectionError("the franky backend needs the controller's address (--robot-ip)")
        self.host = host
        self.settings = settings
        self.factory = factory
        self.clock = clock
        self.reconnect_in_thread = reconnect_in_thread if reconnect_in_thread is not None else \
            factory is FrankyLink
        self.link: Any = None
        self.connected = False
        self.streaming = False
        self.reason = ""  # why the link was lost, or the last attempt failed
        self.refused = ""  # why the last motion was refused (until retry_at)
        self.reflex = ""  # libfranka's errors of the reflex under way
        self.faulted = False  # the last observation was a fault of the robot's: nothing is sent
        self.retry_at = 0.0
        self.backoff_s = settings.reconnect_min_s
        self.rest_since: float | None = None  # the arm at rest since (in a reflex, before a recovery)
        self.last_q = np.zeros(env.n)
        self.last_time_s: float | None = None  # the controller's clock of the newest report
        self.fresh_at = 0.0  # when a report last advanced it (the bridge's clock)
        self.reconnects = 0
        self.recoveries = 0
        self._connector: threading.Thread | None = None
        self._probe: threading.Thread | None = None
        self._probe_error = ""
        self._probe_stop = threading.Event()
        self._connected: Any = None
        self._connect_error = ""

    # -- connection -------------------------------------------------------------------
    def connect(self) -> None:
        """Connect, or raise RobotConnectionError with what to check."""
        self.link = self.factory(self.host, self.settings)
        try:
            report = self.link.read()
        except LinkLost as exc:
            raise RobotConnectionError(f"the Franka controller at {self.host} sent no state ({exc})") from exc
        self.connected = True
        self.last_q = report.q.copy()
        self.last_sent = report.q.copy()
        self.fresh_at = self.clock()
        log.info("connected to the Franka controller at %s (mode %s)", self.host, report.mode)

    def disconnect(self) -> None:
        """End the motion at rest and release the robot (safe to call twice)."""
        self._probe_stop.set()
        probe, self._probe = self._probe, None
        if probe is not None:
            probe.join(timeout=RELEASE_S)
        connector = self._connector
        if connector is not None:
            connector.join(timeout=RELEASE_S)
            self._connector = None
        link, self.link = self.link, None
        if link is not None and self.connected:
            try:
                link.stop()
            except NwrError as exc:
                log.warning("while releasing the robot: %s", exc)
        self.connected = False
        self.streaming = False

    def lost(self, reason: str) -> None:
        if self.connected:
            log.error("connection to the Franka controller at %s lost: %s", self.host, reason)
        self.connected = False
        self.streaming = False
        self.reason = reason
        self.retry_at = max(self.retry_at, self.clock())

    def _backoff(self) -> None:
        self.retry_at = self.clock() + self.backoff_s
        self.backoff_s = min(2.0 * self.backoff_s, self.settings.reconnect_max_s)

    def _try_reconnect(self) -> None:
        connector = self._connector
        if connector is not None:
            if connector.is_alive():
                return
            self._connector = None
            self._finish_reconnect()
            return
        if self.clock() < self.retry_at:
            return
        self.reconnects += 1
        self.link = None  # the lost link is dropped (franky closes its connection when it is collected)
        if not self.reconnect_in_thread:
            self._attempt()
            self._finish_reconnect()
            return
        self._connector = threading.Thread(target=self._attempt, name="franky-reconnect", daemon=True)
        self._connector.start()

    def _attempt(self) -> None:
        self._connected, self._connect_error = None, ""
        try:
            self._connected = self.factory(self.host, self.settings)
        except (NwrError, OSError) as exc:
            self._connect_error = str(exc)

    def _finish_reconnect(self) -> None:
        link, self._connected = self._connected, None
        if link is None:
            self.reason = f"reconnection {self.reconnects} failed ({self._connect_error})"
            log.warning("%s: next attempt in %.1f s", self.reason, self.backoff_s)
            self._backoff()
            return
        log.info("reconnected to the Franka controller at %s (attempt %d)", self.host, self.reconnects)
        self.link = link
        self.connected = True
        self.streaming = False
        self.last_time_s = None
        self.fresh_at = self.clock()
        self.backoff_s = self.settings.reconnect_min_s
        self.last_sent = None

    # -- a frozen stream -----------------------------------------------------------------
    def _frozen(self) -> str:
        return f"no state from the controller for {1e3 * (self.clock() - self.fresh_at):.0f} ms"

    def _start_probe(self) -> None:
        """Read a frozen stream from a thread of its own (with the real franky): once libfranka has noticed a dead
        connection, its next read blocks for about a second before it fails, which would stand the bridge's loop
        still."""
        self._probe_error = ""
        if not self.reconnect_in_thread:
            return  # (the test doubles' reads never block: the loop reads on)
        link, frozen_at = self.link, self.last_time_s

        def probe() -> None:
            while not self._probe_stop.is_set():
                try:
                    if link.read().time_s != frozen_at:
                        return
                except LinkLost as exc:
                    self._probe_error = str(exc)
                    return
                self._probe_stop.wait(PROBE_EVERY_S)

        self._probe_stop.clear()
        self._probe = threading.Thread(target=probe, name="franky-probe", daemon=True)
        self._probe.start()

    # -- observation ------------------------------------------------------------------
    def _stale(self, detail: str) -> Observation:
        return Observation(self.last_q.copy(), np.zeros(self.env.n), "disconnected", f"{self.host}: {detail}")

    def get_observation(self) -> Observation:
        if not self.connected or self.link is None:
            self._try_reconnect()
            if not self.connected:
                return self._stale(f"{self.reason}; reconnecting")
        probe = self._probe
        if probe is not None:  # the stream froze: a thread reads it until it flows again or the link fails
            if probe.is_alive():
                return self._stale(self._frozen())
            self._probe = None
            if self._probe_error:
                self.lost(self._probe_error)
                return self._stale(f"{self._probe_error}; reconnecting")
        try:
            report = self.link.read()
            ended = self.link.motion_error() if self.streaming else ""
        except LinkLost as exc:
            self.lost(str(exc))
            return self._stale(f"{exc}; reconnecting")
        now = self.clock()
        if report.time_s != self.last_time_s:
            self.last_time_s, self.fresh_at = report.time_s, now
        elif now - self.fresh_at > self.settings.state_timeout_s:
            # The motion is kept: the stream may flow again (libfranka's controller stops the arm if the bridge's
            # commands stop reaching it; the bridge sends none while the fault lasts).
            self._start_probe()
            return self._stale(self._frozen())
        q, dq = report.q, report.dq
        if np.isfinite(q).all():  # a non-finite report is passed on: the bridge's check stops the arm on it
            self.last_q = q
        if ended:
            self.streaming = False
            if report.mode not in ("Reflex", "AutomaticErrorRecovery"):
                self.refused = f"the controller ended the motion ({ended})"
                self._backoff()
            else:
                self.reflex = ended
        try:
            fault = self._fault(report, now)
        except LinkLost as exc:
            self.lost(str(exc))
            return self._stale(f"{exc}; reconnecting")
        self.faulted = fault is not None
        if fault is not None:
            return Observation(q, dq, fault[0], fault[1], stamp_s=report.time_s, tau_ext=report.tau_ext)
        self.backoff_s = self.settings.reconnect_min_s
        return Observation(q, dq, stamp_s=report.time_s, tau_ext=report.tau_ext)

    def _fault(self, report: Report, now: float) -> tuple[m.RobotStatus, str] | None:
        """The robot's fault from its mode, and any recovery or retry it is time for."""
        mode = report.mode
        if mode in ("Reflex", "AutomaticErrorRecovery"):
            self.streaming = False
            why = self.reflex or report.errors or "libfranka reported no error"
            at_rest = bool(np.all(np.abs(report.dq) < REST_RAD_S))
            self.rest_since = (self.rest_since if self.rest_since is not None else now) if at_rest else None
            if self.rest_since is not None and now - self.rest_since >= self.settings.recover_rest_s and \
                    now >= self.retry_at:
                self.recoveries += 1
                try:
                    ok = self.link.recover()
                except MotionRefused as exc:
                    ok, why = False, f"{why}; recovery failed: {exc}"
                self._backoff()
                if ok:
                    log.info("Franka's reflex cleared by libfranka's error recovery (%s)", why)
                    self.reflex, self.rest_since = "", None
                    return None
            return "robot_reflex", (f"Franka's reflex stopped the arm: {why}; libfranka's error recovery once the "
                                    f"arm has rested {self.settings.recover_rest_s:g} s")
        self.reflex, self.rest_since = "", None
        if mode == "UserStopped":
            self.streaming = False
            return "emergency_stop", "user stop pressed (the external activation device): release it"
        if mode not in ("Idle", "Move"):
            self.streaming = False
            return "motion_refused", (f"the robot is in mode {mode} (guiding, brakes locked, FCI deactivated?): "
                                      "nothing is sent until it is Idle")
        if self.refused:
            if now < self.retry_at:
                return "motion_refused", f"{self.refused}; trying again"
            self.refused = ""
        return None

    # -- commands ---------------------------------------------------------------------
    def _send(self, setpoint: Setpoint) -> None:
        if not self.connected or self.link is None or self.refused or self.faulted:
            return  # (the core sends nothing in a fault either)
        try:
            if not self.streaming:
                # Started at once, a hold included: the impedance law's gains and torque ramp up over the first
                # tenth of a second (franky), and the arm must be tracking before the first motion arrives.
                self.link.start(setpoint.q)
                self.streaming = True
            self.link.target(setpoint.q, setpoint.dq if setpoint.mode != "hold" else np.zeros(self.env.n))
        except LinkLost as exc:
            self.lost(str(exc))
        except MotionRefused as exc:
            self.streaming = False
            self.refused = f"the controller refused the motion ({exc})"
            log.error("%s", self.refused)
            self._backoff()
