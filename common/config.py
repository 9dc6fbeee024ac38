"""Configuration: one TOML profile decoded into Structs with bounds.

A profile has one table per service. Every field has a default, a bound and
a comment; unknown fields are errors (a typo must not be silently ignored).
The packaged ``default`` profile (``common/profiles/default.toml``) spells
every field out. Command-line flags and environment variables override the
profile in each service's ``main``, never at import.

:func:`load_profile` checks a profile in three steps, each a one-line
:class:`ConfigError` naming the field (docs/profile.md has every field's
default, hard bound and safe range):

1. hard bounds: the Structs' ``Meta`` bounds and the cross-checks of
   :func:`_check_profile` refuse what is never safe or never meaningful;
2. the robot: :func:`check_against_robot` checks every per-joint list, pad
   and region name, the task's range and its fastest point against the robot
   description the profile names;
3. safety beside a person: a value of :data:`~nwr.common.guards.GUARDS` past its default, on the
   side that loosens it, must be acknowledged in ``[safety]`` (by its dotted
   name, with a reason); an acknowledgement of a value that is not loosened
   is refused too. Each acknowledged value is logged as a warning at load,
   and the recorder keeps the list in the session's metadata.
"""

from __future__ import annotations

import functools
import logging
import math
import re
import tomllib
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import msgspec

from nwr.common.errors import ConfigError
from nwr.common.guards import GUARDS, Guarded, Loosened, loosens, pattern_of, toml_value
from nwr.common.rmw_zenoh import Ros2Section
from nwr.common.section import Section
from nwr.common.task import TaskSection, check_task

if TYPE_CHECKING:
    from nwr.common.robot import RobotDescription

log = logging.getLogger(__name__)

PACKAGE_DIR = Path(__file__).resolve().parent
PROFILES_DIR = PACKAGE_DIR / "profiles"
SCRIPTS_DIR = PACKAGE_DIR / "scripts"

Positive = Annotated[float, msgspec.Meta(gt=0)]
NonNegative = Annotated[float, msgspec.Meta(ge=0)]
Fraction = Annotated[float, msgspec.Meta(gt=0, le=1)]
Port = Annotated[int, msgspec.Meta(ge=1024, le=65000)]
Name = Annotated[str, msgspec.Meta(pattern=r"^[a-z][a-z0-9_-]{0,31}$")]
# The sigmoid's steepness: below 0.1 the scaled sigmoid is a straight line (to
# 4e-5), above 50 it rises from 10 % to 90 % within 9 % of a pain level: a step.
Steepness = Annotated[float, msgspec.Meta(ge=0.1, le=50)]


_Section = Section


class Plugged(_Section):
    """A section whose plug-ins keep their own tables: ``[<section>.<plug-in>]``, each decoded by the plug-in's
    Settings where the profile is loaded (:mod:`nwr.common.plugins`; docs/profile.md lists their fields)."""

    # The plug-ins' tables by plug-in name, as the profile gives them.
    plugins: dict[str, dict[str, Any]] = {}


class RobotSection(_Section):
    # Robot name: the key prefix is nwr/<name>/, so two arms can share a LAN.
    name: Name = "ur10e"
    # The robot description (URDF + skin + limits): a packaged robot's name (a
    # folder of common/robots/: "ur10e", "fr3") or a robot.toml's path; empty =
    # the packaged UR10e.
    description: str = ""
    # The skin the pipeline runs on: "pads" (the description's pad file, the
    # paper's AIRSKIN) or "taxels" (skin-taxels.toml beside robot.toml:
    # hundreds of small sensors, contacts located by them; docs/skins.md).
    skin: Literal["pads", "taxels"] = "pads"


class ZenohSection(_Section):
    # "peer": the embedded mesh on loopback (default). "client": connect to a router.
    mode: Literal["peer", "client"] = "peer"
    # Router endpoint(s) for the LAN deployment, e.g. ["tcp/10.0.0.2:7447"].
    # When set, services connect only to these and listen nowhere.
    router: list[str] = []
    # Address the embedded mesh listens and connects on. Keep it loopback
    # unless every service really runs on another host: without secure mode,
    # an address beyond loopback (and a router endpoint beyond it) is refused
    # at start unless NWR_INSECURE=1 acknowledges the open network.
    host: str = "127.0.0.1"
    # First port of the embedded mesh: service i listens on base_port + i.
    base_port: Port = 7450
    # Secure mode (the LAN deployment): mutual TLS to the router, whose access
    # control decides by the certificate's common name (ROLE:NAME) what this
    # service may put. Needs router; tcp/ router endpoints are dialled as tls/.
    # The environment variable NWR_INSECURE=1 turns it off (with a warning).
    secure: bool = False
    # PEM files from `nwr certs`: the lab CA's certificate, this service's
    # certificate and its private key (mode 0600).
    ca_certificate: str = ""
    certificate: str = ""
    private_key: str = ""



class GatewaySection(Plugged):
    # Skin sample rate, Hz (AIRSKIN delivers about 25 Hz).
    rate_hz: Annotated[float, msgspec.Meta(gt=0, le=2000)] = 25.0
    # The skin source, a module of services/gateway/sources/ (checked where the
    # gateway starts): "sim", the simulated skin; "ros1", a real skin's
    # pressures on a ROS 1 topic ([gateway.ros1]); "ros2", on a ROS 2 topic
    # through rmw_zenoh ([gateway.ros2], [ros2]).
    source: Name = "sim"
    # A change above this marks the pad as touched and freezes its baseline.
    # Below every pad's PL 2 threshold: a press the gain feels must freeze it.
    contact_hpa: Positive = 1.0
    # The contact ends when the change falls below this (hysteresis).
    release_hpa: Positive = 0.5
    # Time constant of the baseline's tracking of slow drift while untouched.
    baseline_tau_s: Positive = 5.0
    # The baseline never moves faster than this, so it cannot follow a press.
    max_drift_hpa_s: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.05
    # A "contact" longer than this is taken as a new no-contact level (a pad
    # that changed, not a hand): the baseline is re-acquired, with a warning.
    max_contact_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 120.0
    # A physics world's skin sample (gateway.source = "physics") that reaches
    # the gateway later than this after the world took it is dropped, counted
    # and reported: a gateway behind a fast stream (1 kHz taxels on a busy
    # machine) catches up instead of passing on old pressures as new, s.
    max_sample_age_s: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.05


class PadGainOverride(_Section):
    # Pain-level thresholds for this pad, hPa: [PL2, PL3, PL4, saturation].
    thresholds_hpa: list[float] | None = None
    # Sigmoid steepness for this pad (0.1-50, as gain.k).
    k: Steepness | None = None


class BodyRegion(_Section):
    # A body region of the person beside the arm in ISO/TS 15066's power and
    # force limiting model (docs/reflexes.md, "Effective-mass sensitivity").
    # Effective spring constant k, N/m: stiffer, a larger predicted force.
    k_n_m: Annotated[float, msgspec.Meta(gt=0, le=1e7)] = 75_000.0
    # Effective mass m_H, kg: heavier, a larger predicted force.
    mass_kg: Annotated[float, msgspec.Meta(gt=0, le=1000)] = 5.6
    # The transient contact force limit, N: a pad whose predicted impact force
    # reaches it feels with its thresholds at gain.effective_mass.floor.
    transient_n: Annotated[float, msgspec.Meta(gt=0, le=10_000)] = 280.0


# The default body region's name (its values are BodyRegion's defaults).
DEFAULT_BODY_REGION = "hand"


class EffectiveMassSection(_Section):
    # gain.model = "effective-mass": each pad's thresholds scaled by
    # 1 - (1 - floor) * min(1, F / transient_n), F the impact force a
    # collision at the pad's speed would cause; floor: the most sensitive
    # scale (thresholds x floor, where F reaches the region's limit).
    floor: Annotated[float, msgspec.Meta(ge=0.1, le=1)] = 0.6
    # A pad slower than this is at rest: its direction of motion is undefined
    # (the outward normal is used for its effective mass) and its force is 0.
    rest_speed_m_s: Annotated[float, msgspec.Meta(gt=0, le=0.1)] = 0.005
    # A robot state older than this (or none yet, or one the bridge marks as
    # not measured) gives every pad the most sensitive scale, s.
    state_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.1
    # The body region each pad would meet, by pad name; a pad not named meets
    # default_region. Every name must be one of regions.
    default_region: str = DEFAULT_BODY_REGION
    pad_regions: dict[str, str] = {}
    # The body regions, by name.
    regions: dict[str, BodyRegion] = msgspec.field(default_factory=lambda: {DEFAULT_BODY_REGION: BodyRegion()})


class TorqueContactSection(_Section):
    # The arm's own contact detection as a proprioceptive fallback (off by
    # default): a pad that is invalid in a skin sample (the skin blind there)
    # gets the gain of a contact the controller's estimated external torques
    # (RobotState.tau_ext: a Franka's) locate on it, gain = force / full_force_n
    # (services/gain/torque.py, docs/robots.md). A robot whose states carry no
    # tau_ext never triggers it.
    enabled: bool = False
    # "none": tau_ext is already external (a real Franka); "gravity": the
    # controller reports the torque it applies (franky-sim), the URDF's gravity
    # torques are removed first; "dynamics": the same, and the torques of the
    # arm's own motion (inverse dynamics, the acceleration from the states).
    baseline: Literal["none", "gravity", "dynamics"] = "none"
    # A contact starts when the residual reaches this on any joint, N m, and
    # ends once it is below on_nm x off_ratio on every joint.
    on_nm: Annotated[float, msgspec.Meta(gt=0, le=100)] = 6.0
    off_ratio: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.65
    # The force estimate (N, along minus the located pad's normal) that gives gain 1.
    full_force_n: Annotated[float, msgspec.Meta(gt=1, le=200)] = 30.0
    # A robot state older than this when a skin sample arrives is not used, s.
    state_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.1


class GainSection(_Section):
    # "continuous": the paper's piecewise scaled sigmoid; "discrete": PL steps;
    # "effective-mass": the continuous model with each pad's thresholds scaled
    # down by the impact force its motion predicts ([gain.effective_mass]).
    model: Literal["continuous", "discrete", "effective-mass"] = "continuous"
    # Upper thresholds of PL 1, 2, 3 and the saturation of PL 4, hPa.
    thresholds_hpa: list[float] = msgspec.field(default_factory=lambda: [2.0, 6.0, 12.0, 20.0])
    # Sigmoid steepness k (the paper's 3). 0.1-50: below, the scaled sigmoid
    # is a straight line; above, a step in the middle of each pain level.
    k: Steepness = 3.0
    # Gain at the start of PL 4 (the ratio of PL 3 to PL 4 displacements).
    pl3_gain: Fraction = 0.35
    # Per-pad overrides, by pad name.
    overrides: dict[str, PadGainOverride] = {}
    # The effective-mass model's parameters (used with model = "effective-mass").
    effective_mass: EffectiveMassSection = msgspec.field(default_factory=EffectiveMassSection)
    # The arm's external torques as a fallback where the skin is blind.
    torque: TorqueContactSection = msgspec.field(default_factory=TorqueContactSection)


class RestartSection(_Section):
    # Reflex storms: when a new or stronger contact may (re)start a reflex
    # (docs/reflexes.md, "Restarts"). A start from the task is never delayed
    # or refused: any contact with a gain stops the task at its first sample.
    # A pad's touch ends only once its gain has been 0 for gap_s: a pad that
    # flickers between pressed and not pressed faster than that is one touch
    # (not a new contact at each press). 0: every press is a new contact.
    gap_s: Annotated[float, msgspec.Meta(ge=0, le=0.5)] = 0.1
    # A contact this much stronger than the current reflex's gain restarts it
    # at once, whatever the pad's own rate limit says (the overall one still
    # applies): the reflex's gain never lags the touch by more than this.
    escalate_at_once: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.25
    # Rate limit per pad (a token bucket): the reflexes one pad may start or
    # restart at once, then one per pad_interval_s. The demo's firm press
    # escalates in 6 samples of 40 ms.
    pad_burst: Annotated[int, msgspec.Meta(ge=1, le=20)] = 6
    pad_interval_s: Annotated[float, msgspec.Meta(gt=0, le=5)] = 0.5
    # Rate limit over every pad: restarts at once, then one per interval_s.
    # A restart refused by either waits for the next pain message that still
    # shows it (a new contact stays new until it restarts or its touch ends).
    burst: Annotated[int, msgspec.Meta(ge=2, le=100)] = 12
    interval_s: Annotated[float, msgspec.Meta(gt=0, le=5)] = 0.25
    # A pad pressed again flicker_presses times within flicker_window_s, each
    # time after a gap shorter than gap_s, is reported faulty on
    # diag/planner-<name> (pad_flicker: once, then at most every 10 s).
    flicker_presses: Annotated[int, msgspec.Meta(ge=2, le=1000)] = 5
    flicker_window_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 1.0


class PlannerSection(Plugged):
    # Instance name: the planner publishes reflex/<name>/status and signs its
    # commands with it; the bridge follows the planner named active_planner.
    name: Name = "cartesian"
    # Reflex: "uniform" (UR), "location" (LR), "cartesian" (CR),
    # "cartesian-smooth" (CR with its velocity ramped in and out) or
    # "whole-arm" (a QP each cycle; [planner.whole_arm]): the name of one of
    # the planner's strategies (services/planner/strategies/), checked where
    # the planner starts.
    strategy: str = "cartesian"
    # Command rate, Hz (the UR e-Series control period is 2 ms).
    rate_hz: Annotated[float, msgspec.Meta(gt=0, le=1000)] = 500.0
    # The task is planned ahead: one command every this many control cycles,
    # carrying the setpoints of the cycles until the next (the bridge
    # interpolates). Reflexes and returns stream one command per cycle.
    # 1 = one command per cycle in the task too. At most 0.1 s of cycles.
    task_ahead_cycles: Annotated[int, msgspec.Meta(ge=1, le=50)] = 10
    # Joint-space reflexes: the human range of motion q_max, degrees, one per
    # joint (0-180); empty = the robot's reflex_range_deg (robot.toml; the
    # UR10e's is the paper's [40, 70, 146, 73, 0, 0]). UR adds
    # uniform_fraction of it (the paper's 1/2), LR adds G(p) W(PL, region)
    # q_max; both in the robot description's reflex_direction, clipped to the
    # joint limits.
    q_max_deg: list[Annotated[float, msgspec.Meta(ge=0, le=180)]] = []
    # Guarded mode (off: the paper's behaviour): correct a reflex whose planned
    # motion would move the touched pad, or any other touched pad (contacts =
    # "every"), toward its contact, and report it.
    guarded: bool = False
    # The study's target pads in the order they light up (names of the robot's
    # pads); empty = every pad, in an order shuffled with target_seed. The
    # target moves on after each touch of it.
    target_order: list[str] = []
    target_seed: int = 1
    # Cartesian reflex: speed of the pad at G(p) = 1, m/s (the paper leaves it
    # open; 0.25 m/s withdraws the pad 12.5 cm in the 0.5 s reflex). At most
    # bridge.limits.withdrawal_speed_m_s.
    v_max_m_s: Annotated[float, msgspec.Meta(gt=0, le=1.0)] = 0.25
    # Duration of a Cartesian reflex, s (the paper's 0.5 s; a withdrawal, not
    # a motion: at most 2 s).
    reflex_duration_s: Annotated[float, msgspec.Meta(gt=0, le=2.0)] = 0.5
    # Sustained contact. "hold" (this project's behaviour): once a withdrawal's
    # motion ends the arm stays away (mode HOLDING) while the touch lasts; the
    # return begins once no pad it would approach has felt a touch (pain level
    # 2 or more) for release_s, or after max_hold_s along directions that bring
    # no pad closer to a touch still felt; a return that feels a touch ahead
    # stops there and holds. A pad the arm cannot move away from its contact
    # (its joints cannot move it along its normal) holds still, reported.
    # "paper": the paper's exact behaviour, for a lab reproducing its study:
    # the return begins as soon as the withdrawal's motion ends.
    sustained_contact: Literal["hold", "paper"] = "hold"
    # Several contacts at once. "every" (this project's): each strategy reacts
    # to every active contact, not only the strongest (LR: the joint-space
    # sum; UR: the same target; CR: one row set per touched pad; whole-arm:
    # kept away from each; guarded mode and the retreat check: every touched
    # pad; docs/reflexes.md "Every contact counts"). "strongest": the
    # paper's, every strategy is given the reflex's own contact only (a new
    # touch elsewhere still restarts it).
    contacts: Literal["every", "strongest"] = "every"
    release_s: Annotated[float, msgspec.Meta(ge=0, le=5)] = 0.3
    max_hold_s: Annotated[float, msgspec.Meta(gt=0, le=600)] = 30.0
    # Hold: a touch stays *recent* this long after it was last felt; the
    # return waits while it would take any pad more than contact_margin_m past
    # where a recent touch met it (toward the person: along that pad's normal
    # then), rather than sweep it through the place a person was a moment ago.
    recent_contact_s: Annotated[float, msgspec.Meta(ge=0, le=60)] = 3.0
    contact_margin_m: Annotated[float, msgspec.Meta(ge=0, le=0.1)] = 0.01
    # Returns and approaches (to the saved pose, to the task's start): no point
    # of the arm faster than return_speed_m_s (at most bridge.limits.speed_m_s),
    # the touched pad no faster than approach_speed_m_s within
    # approach_distance_m of where it was touched, and no pad nor the flange
    # toward any recent touch's place (recent_contact_s, both modes) faster
    # than approach_speed_m_s while within approach_distance_m of it.
    return_speed_m_s: Annotated[float, msgspec.Meta(gt=0, le=0.25)] = 0.2
    approach_speed_m_s: Annotated[float, msgspec.Meta(gt=0, le=0.25)] = 0.05
    approach_distance_m: Annotated[float, msgspec.Meta(ge=0, le=0.5)] = 0.05
    # During a reflex, a contact must exceed the current reflex's gain by this
    # much to update it (a new pad always updates it).
    update_margin: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.05
    # Cartesian reflex: ask for zero angular velocity of the pad, as the paper's
    # q_dot = J^+ [v_c; 0] does (true), or only for its linear velocity (false).
    hold_orientation: bool = True
    # Damped least squares: the damping grows to this as the smallest singular
    # value of the pad Jacobian (m/rad) falls below singular_threshold.
    damping_max: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.05
    singular_threshold: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.05
    # Fraction of the joint speed and acceleration limits reflexes may use.
    speed_fraction: Fraction = 0.9
    # Planner status rate, Hz (transitions are published at once as well).
    status_rate_hz: Annotated[float, msgspec.Meta(gt=0, le=1000)] = 20.0
    # Real-time scheduling of the planner's threads: SCHED_FIFO at this
    # priority (1-99), as on a lab PC with a real-time kernel; 0 = off. Needs
    # CAP_SYS_NICE or an rtprio limit; without it, a warning and no change.
    realtime_priority: Annotated[int, msgspec.Meta(ge=0, le=99)] = 0
    restarts: RestartSection = msgspec.field(default_factory=RestartSection)
    task: TaskSection = msgspec.field(default_factory=TaskSection)


class CartesianLimits(_Section):
    # The fastest any point of the arm (each pad's reference point, the elbow,
    # the flange) may move outside a withdrawal (task, return, rejoining the
    # task), m/s. 0.25 m/s is the reduced speed of ISO 10218-1 (5.6) for a
    # person beside the arm; the paper's task peaks at 0.19 m/s.
    speed_m_s: Annotated[float, msgspec.Meta(gt=0)] = 0.25
    # The fastest any point may move during a withdrawal (phase REFLEX), m/s:
    # away from the contact a withdrawal may go faster than it approaches;
    # its speed toward the contact stays within speed_m_s.
    withdrawal_speed_m_s: Annotated[float, msgspec.Meta(gt=0)] = 0.5
    # The arm's momentum: the sum over the moving links of mass (the URDF's)
    # times the speed of its centre of mass, kg m/s. The UR10e's 29.1 kg of
    # moving links all at speed_m_s carry 7.3 kg m/s.
    momentum_kg_m_s: Annotated[float, msgspec.Meta(gt=0)] = 10.0
    # The power the joints put into the arm's motion (the rate of change of
    # its kinetic energy, from the URDF's inertias: dq . (tau - g)), W: how
    # fast the arm may gather the energy a contact would transfer. The
    # paper's reflexes within the speed limits need at most 16 W, the task 10 W.
    power_w: Annotated[float, msgspec.Meta(gt=0)] = 50.0
    # The jerk-limited stop the bridge would make from the cycle's velocity
    # (its controlled stop, at the envelope's acceleration and jerk limits)
    # must end within stopping_time_s, s, and move no point farther than
    # stopping_distance_m, m (each point's speed times half the stop's time).
    # The paper's reflexes within the speed limits stop in at most 0.13 s and
    # 30 mm, the task in 0.09 s and 10 mm.
    stopping_time_s: Annotated[float, msgspec.Meta(gt=0, le=1.0)] = 0.25
    stopping_distance_m: Annotated[float, msgspec.Meta(gt=0, le=0.5)] = 0.08

    def describe(self) -> str:
        return (f"every point at most {self.speed_m_s} m/s ({self.withdrawal_speed_m_s} m/s withdrawing), "
                f"momentum at most {self.momentum_kg_m_s} kg m/s, power at most {self.power_w} W, a stop within "
                f"{self.stopping_time_s} s and {self.stopping_distance_m} m")

    def checked(self, where: str) -> CartesianLimits:
        """Itself; a ConfigError naming the field for a value that is not finite."""
        for field in self.__struct_fields__:
            value = getattr(self, field)
            if not math.isfinite(value):
                raise ConfigError(f"{where}.{field} = {value}: must be a finite number")
        return self


class ReducedLimits(CartesianLimits):
    """The reduced mode's limits (a UR's safety "reduced mode"): each at most the normal one.

    Its own defaults, so that a [bridge.reduced] table that gives some fields
    keeps the reduced defaults for the others (not the normal limits).
    """

    speed_m_s: Annotated[float, msgspec.Meta(gt=0)] = 0.15
    withdrawal_speed_m_s: Annotated[float, msgspec.Meta(gt=0)] = 0.25
    momentum_kg_m_s: Annotated[float, msgspec.Meta(gt=0)] = 5.0
    power_w: Annotated[float, msgspec.Meta(gt=0)] = 25.0
    stopping_time_s: Annotated[float, msgspec.Meta(gt=0, le=1.0)] = 0.15
    stopping_distance_m: Annotated[float, msgspec.Meta(gt=0, le=0.5)] = 0.04


class BridgeSection(Plugged):
    # The arm, a module of services/bridge/backends/ (checked where the bridge
    # or a launch starts): "sim", the simulated arm; "ur_rtde", a real UR (or
    # URSim) through ur_rtde, which also needs --robot-ip and
    # --i-am-next-to-the-robot on the command line.
    backend: Name = "sim"
    # Simulation and control rate, Hz (the UR e-Series controller runs at 500 Hz).
    rate_hz: Annotated[float, msgspec.Meta(gt=0, le=1000)] = 500.0
    # Robot state publication rate, Hz (plus one out of schedule per reflex
    # onset and per switch). Every state costs a put and a receive in each
    # subscriber (planners, gateway, recorder, view): 50 Hz keeps the idle
    # pipeline cheap; raise it for finer recorded arm motion.
    state_rate_hz: Annotated[float, msgspec.Meta(gt=0, le=1000)] = 50.0
    # Real-time scheduling of the bridge's threads: SCHED_FIFO at this priority
    # (1-99); 0 = off. On by default: a bridge starved of CPU for 1 / watchdog_hz
    # has the controller stop the arm, and on a loaded machine it keeps the
    # control cycle on time (docs/bridge.md). Where it is not permitted, a
    # warning at start and the normal scheduler. As planner.realtime_priority.
    realtime_priority: Annotated[int, msgspec.Meta(ge=0, le=99)] = 20
    # The only planner whose commands move the arm.
    active_planner: Name = "cartesian"
    # No command for this long: decelerate to rest and hold, s (10 control
    # cycles). Longer than a planner cycle (1 / planner.rate_hz).
    command_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=1.0)] = 0.02
    # Skin data older than this holds task and return motions, s (three periods
    # of the 25 Hz AIRSKIN stream). Reflexes already under way may finish.
    # Longer than a skin period (1 / gateway.rate_hz).
    skin_timeout_s: Annotated[float, msgspec.Meta(gt=0, le=5.0)] = 0.12
    # Fractions of the robot description's joint speed / acceleration / jerk limits.
    speed_fraction: Fraction = 1.0
    acceleration_fraction: Fraction = 1.0
    jerk_fraction: Fraction = 1.0
    # Tighter per-joint limits than the robot description's (rad, rad/s, rad/s^2,
    # rad/s^3), one per joint; empty = the description's. Values looser than the
    # description's are a configuration error, never silently used.
    q_min: list[float] = []
    q_max: list[float] = []
    v_max: list[float] = []
    a_max: list[float] = []
    j_max: list[float] = []
    # A position target farther than this from the commanded pose is rejected,
    # rad: a planner that lost track of the arm must not swing it there.
    position_jump_rad: Annotated[float, msgspec.Meta(gt=0, le=1.0)] = 0.1
    # The robot's reported joint state is a claim, checked every cycle
    # (docs/bridge.md, "The reported state"); a report beyond these bounds
    # stops the arm (state_implausible). Following error: a reported position
    # this far from the bridge's model of the commanded motion (through the
    # backend's lag), rad, ...
    following_error_rad: Annotated[float, msgspec.Meta(gt=0, le=0.5)] = 0.05
    # ... plus this times the joint's commanded speed, s (the lag model's error).
    following_lag_s: Annotated[float, msgspec.Meta(ge=0, le=0.5)] = 0.05
    # Between two reports a joint may move no farther than the robot
    # description's v_max allows in the time between them, plus this, rad ...
    report_jump_rad: Annotated[float, msgspec.Meta(gt=0, le=0.2)] = 0.01
    # ... and change its speed no more than its a_max allows, plus this, rad/s.
    report_speed_jump_rad_s: Annotated[float, msgspec.Meta(gt=0, le=5.0)] = 0.2
    # A report that does not change for this long while the commands move a
    # joint is a frozen stream, s (50 control cycles: 40 ms tripped on a
    # loaded machine whose client received late, docs/bridge.md).
    report_frozen_s: Annotated[float, msgspec.Meta(gt=0, le=0.5)] = 0.1
    # A pad whose readings stay invalid (not finite, or outside what a pad can
    # report: a skin read in Pa, say) this long is blind, s (5 samples at 25 Hz).
    # A sample without any valid pad never counts as fresh skin data.
    blind_pad_s: Annotated[float, msgspec.Meta(gt=0, le=5.0)] = 0.2
    # While any pad is blind: "reduced", the arm moves within the reduced
    # Cartesian limits (bridge.reduced, as `nwr safety reduced`); "stop",
    # task and return are held as with stale skin (reflexes may finish).
    blind_pads: Literal["reduced", "stop"] = "reduced"
    # A command whose seq is at most the last accepted one is a duplicate or out
    # of order and is rejected, unless it is this far below it: a restarted planner.
    seq_restart_gap: Annotated[int, msgspec.Meta(ge=1, le=1_000_000)] = 500
    # Initial pose of the simulated arm, rad, one per joint within the joint
    # limits; empty = the robot description's home pose.
    initial_q: list[float] = []
    # Cartesian limits on every point of the arm and on its momentum, in the
    # normal and the reduced mode (nwr safety reduced|normal switches at
    # runtime). Tighter than the robot description's max_point_speed, never
    # looser (a configuration error names the field).
    limits: CartesianLimits = msgspec.field(default_factory=CartesianLimits)
    reduced: ReducedLimits = msgspec.field(default_factory=ReducedLimits)


class RecorderSection(_Section):
    # Directory for recordings (created if missing).
    directory: str = "recordings"
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    # Chunks are closed at this size, bytes: small chunks lose little on a crash.
    chunk_size: Annotated[int, msgspec.Meta(ge=1024, le=64 * 1024 * 1024)] = 256 * 1024
    # ... and once their first message is this old, s, however small they are,
    # and flushed to the OS: a kill -9 loses at most about this much.
    chunk_interval_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 0.5
    # Split a session into <session>-000.mcap, -001, ... when a file reaches this
    # size, MB (1 MB = 2^20 bytes), or spans this long, s; 0 = never.
    split_size_mb: Annotated[float, msgspec.Meta(ge=0, le=1024 * 1024)] = 0.0
    split_duration_s: Annotated[float, msgspec.Meta(ge=0, le=7 * 24 * 3600)] = 0.0


class SafetySection(_Section):
    # The safety-relevant values this profile loosens past their documented
    # defaults (docs/profile.md: the side that loosens each), every one by its
    # dotted name, e.g. ["bridge.skin_timeout_s", "planner.task.period_s"]. A
    # loosened value missing here is refused at load; so is a name here whose
    # value is not loosened (a stale acknowledgement would hide a later change).
    acknowledge: list[str] = []
    # Who loosened them, when and why; required with acknowledge, e.g. "bench
    # test without a person in the cell, 2026-11-23, J. Doe". Every service
    # logs it with each loosened value at start; the recorder keeps both in
    # the session's metadata (loosened_safety).
    reason: str = ""


# The sections whose plug-ins keep their own tables (Plugged), by name.
PLUGGED: dict[str, type[Plugged]] = {"gateway": GatewaySection, "planner": PlannerSection, "bridge": BridgeSection}


class Profile(_Section):
    robot: RobotSection = msgspec.field(default_factory=RobotSection)
    zenoh: ZenohSection = msgspec.field(default_factory=ZenohSection)
    gateway: GatewaySection = msgspec.field(default_factory=GatewaySection)
    gain: GainSection = msgspec.field(default_factory=GainSection)
    planner: PlannerSection = msgspec.field(default_factory=PlannerSection)
    bridge: BridgeSection = msgspec.field(default_factory=BridgeSection)
    recorder: RecorderSection = msgspec.field(default_factory=RecorderSection)
    safety: SafetySection = msgspec.field(default_factory=SafetySection)
    ros2: Ros2Section = msgspec.field(default_factory=Ros2Section)


# Fields that moved into a plug-in's table: (section, old key) -> (plug-in, its field; "" = the whole table). A
# profile (or a session's journaled one) written before still loads, as if it had written the new place.
MOVED: dict[tuple[str, str], tuple[str, str]] = {
    ("planner", "uniform_fraction"): ("uniform", "fraction"),
    ("planner", "location_weights"): ("location", ""),
    ("planner", "smooth_ramp_s"): ("cartesian-smooth", "ramp_s"),
    ("planner", "whole_arm"): ("whole-arm", ""),
    **{("bridge", key): ("ur_rtde", key)
       for key in ("servo_lookahead_s", "servo_gain", "reconnect_min_s", "reconnect_max_s", "watchdog_hz")},
}


def _moved(name: str) -> str:
    """A dotted field name written before its field moved into a plug-in's table, as it is now."""
    section, _, rest = name.partition(".")
    key, _, tail = rest.partition(".")
    if (section, key) not in MOVED:
        return name
    plugin, field = MOVED[section, key]
    return ".".join(part for part in (section, plugin, field, tail) if part)


def decode_profile(raw: Any, where: str) -> Profile:
    """A profile from plain data (TOML's or a session's journaled JSON): every table under a plugged section
    that is no field of it is a plug-in's (:class:`Plugged`); fields that moved into a plug-in's table
    (:data:`MOVED`) are read where they were. ConfigError naming ``where`` and the field."""
    if isinstance(raw, dict):
        raw = dict(raw)
        for name, kind in PLUGGED.items():
            if not isinstance(raw.get(name), dict):
                continue
            table = dict(raw[name])
            plugins = {key: dict(value) for key, value in dict(table.pop("plugins", {}) or {}).items()}
            for key in list(table):
                if (name, key) in MOVED:
                    plugin, field = MOVED[name, key]
                    value = table.pop(key)
                    if field:
                        plugins.setdefault(plugin, {})[field] = value
                    else:
                        plugins[plugin] = {**value, **plugins.get(plugin, {})}
                elif key not in kind.__struct_fields__ and isinstance(table[key], dict):
                    plugins[key] = {**table.pop(key), **plugins.get(key, {})}
            table["plugins"] = plugins
            raw[name] = table
        safety = raw.get("safety")
        if isinstance(safety, dict) and isinstance(safety.get("acknowledge"), list):
            raw["safety"] = {**safety, "acknowledge": [_moved(n) if isinstance(n, str) else n
                                                      for n in safety["acknowledge"]]}
    try:
        return msgspec.convert(raw, Profile)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{where}: {exc} (docs/profile.md gives every field's bounds)") from exc


def _decode(path: Path, kind: type) -> object:
    try:
        text = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{kind.__name__} file {path} does not exist") from None
    except OSError as exc:
        raise ConfigError(f"cannot read {kind.__name__} file {path}: {exc}") from exc
    try:
        raw = tomllib.loads(text.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from exc
    if kind is Profile:
        return decode_profile(raw, str(path))
    try:
        return msgspec.convert(raw, kind)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def packaged_or_path(name_or_path: str, folder: Path, what: str) -> Path:
    """A TOML file given by path, or by the name of one packaged in ``folder``; ConfigError naming the packaged
    ones (``what``: "profile", "touch script")."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        return path
    packaged = folder / f"{name_or_path}.toml"
    if not packaged.exists():
        known = sorted(p.stem for p in folder.glob("*.toml"))
        raise ConfigError(f"no {what} {name_or_path!r}: give a path to a .toml file or one of {known}")
    return packaged


def resolve_profile(name_or_path: str | None) -> Path:
    """A profile given by packaged name ("default") or by path."""
    return packaged_or_path(name_or_path or "default", PROFILES_DIR, "profile")


# What checks a profile's plug-in tables against the robot, giving their safety-relevant fields
# (nwr.services.profile.check_plugins: the plug-ins are the services').
PluginCheck = Callable[["Profile", "RobotDescription"], "list[Guarded]"]


def load_profile(name_or_path: str | None = None, plugins: PluginCheck | None = None,
                 deferred: Iterable[str] = ()) -> Profile:
    """The profile by packaged name or path, checked in full (the module docstring's three steps); ``plugins``
    checks the plug-ins' tables (without it, they are left as written, unchecked); the plug-ins under the
    sections ``deferred`` are another process's (:func:`check_acknowledgements`).

    Each acknowledged loosened value is logged as one warning: every service
    and tool that loads a profile says so at start.
    """
    from nwr.common.robot import load_description  # pinocchio's import only where a profile is loaded

    profile = _decode(resolve_profile(name_or_path), Profile)
    assert isinstance(profile, Profile)
    _check_profile(profile)
    desc = load_description(profile.robot.description or None)
    check_against_robot(profile, desc)
    plugged = plugins(profile, desc) if plugins else []
    ranges = {item.field: safe_range(item) for item in [*guarded(profile), *plugged]}
    for item in check_acknowledgements(profile, plugged, deferred):
        log.warning("safety: %s = %s is loosened past its default %s (safe range %s), acknowledged in [safety]: %s",
                    item.field, toml_value(item.value), toml_value(item.default), ranges[item.field], item.reason)
    return profile


# A threshold no pad's change can reach (the door refuses larger changes as
# impossible, nwr.common.door.CHANGE_HPA) would never be crossed, hPa.
THRESHOLD_TOP_HPA = 2000.0


def _check_thresholds(where: str, thresholds: list[float]) -> None:
    if (len(thresholds) != 4 or any(not b > a for a, b in zip(thresholds, thresholds[1:]))
            or not all(0 < t <= THRESHOLD_TOP_HPA for t in thresholds)):
        raise ConfigError(
            f"{where}: thresholds_hpa must be four increasing positive values [PL2, PL3, PL4, saturation] "
            f"up to {THRESHOLD_TOP_HPA:g} hPa, got {thresholds}"
        )


def check_profile(profile: Profile) -> None:
    """The hard cross-checks again, for a profile a command-line flag changed after it loaded."""
    _check_profile(profile)


def _check_profile(profile: Profile) -> None:
    """The hard cross-checks that need nothing but the profile (ConfigError naming the field)."""
    gain, gateway, planner, bridge = profile.gain, profile.gateway, profile.planner, profile.bridge
    for endpoint in profile.zenoh.router:
        if not ENDPOINT.match(endpoint):
            raise ConfigError(f"zenoh.router: {endpoint!r} is not a Zenoh endpoint; write <protocol>/<host>:<port>, "
                              "e.g. tcp/10.0.0.2:7447")
    _check_thresholds("gain", gain.thresholds_hpa)
    felt = [("gain.thresholds_hpa", gain.thresholds_hpa[0])]
    for pad, override in gain.overrides.items():
        if override.thresholds_hpa is not None:
            _check_thresholds(f"gain.overrides.{pad}", override.thresholds_hpa)
            felt.append((f"gain.overrides.{pad}.thresholds_hpa", override.thresholds_hpa[0]))
    if gateway.release_hpa > gateway.contact_hpa:
        raise ConfigError(
            f"gateway: release_hpa ({gateway.release_hpa}) must not exceed contact_hpa "
            f"({gateway.contact_hpa})"
        )
    if gain.model == "effective-mass":
        em = gain.effective_mass
        for where in ("default_region", *(f"pad_regions.{pad}" for pad in em.pad_regions)):
            region = dotted_get(em, where)
            if region not in em.regions:
                raise ConfigError(f"gain.effective_mass.{where} = {region!r} is no body region of "
                                  f"gain.effective_mass.regions ({', '.join(sorted(em.regions))})")
        # The most sensitive thresholds: the floor's share of each pad's own.
        felt = [(f"gain.effective_mass.floor x {where}", round(pl2 * em.floor, 9)) for where, pl2 in felt]
    for where, pl2 in felt:
        if gateway.contact_hpa >= pl2:
            raise ConfigError(
                f"gateway.contact_hpa = {gateway.contact_hpa} hPa is not below {where}[0] = {pl2} hPa (PL 2): a press "
                "the gain feels would not freeze the pad's baseline, which would drift into it; lower contact_hpa"
            )
    if 1.0 / gateway.rate_hz >= bridge.skin_timeout_s:
        raise ConfigError(
            f"gateway.rate_hz = {gateway.rate_hz:g} Hz samples the skin every {1e3 / gateway.rate_hz:.0f} ms, "
            f"not within bridge.skin_timeout_s = {bridge.skin_timeout_s} s: the bridge would hold the task between "
            "every two samples; raise the rate"
        )
    if planner.task_ahead_cycles > 1 and planner.task_ahead_cycles / planner.rate_hz > 0.1 + 1e-9:
        raise ConfigError(
            f"planner.task_ahead_cycles = {planner.task_ahead_cycles} at {planner.rate_hz:g} Hz plans more than "
            "0.1 s ahead, which the bridge refuses: lower it"
        )
    if 1.0 / planner.rate_hz >= bridge.command_timeout_s:
        raise ConfigError(
            f"planner.rate_hz = {planner.rate_hz:g} Hz sends a reflex command every {1e3 / planner.rate_hz:.0f} ms, "
            f"not within bridge.command_timeout_s = {bridge.command_timeout_s} s: the bridge would stop the arm "
            "between every two; raise the rate"
        )
    normal = bridge.limits.checked("bridge.limits")
    reduced = bridge.reduced.checked("bridge.reduced")
    for field in normal.__struct_fields__:
        if getattr(reduced, field) > getattr(normal, field):
            raise ConfigError(f"bridge.reduced.{field} = {getattr(reduced, field)} is above bridge.limits.{field} = "
                              f"{getattr(normal, field)}: the reduced mode may only tighten the limits")
    for field, value, bound, bound_name, what in (
        ("planner.v_max_m_s", planner.v_max_m_s, normal.withdrawal_speed_m_s, "bridge.limits.withdrawal_speed_m_s",
         "the bridge would slow every full reflex"),
        ("planner.return_speed_m_s", planner.return_speed_m_s, normal.speed_m_s, "bridge.limits.speed_m_s",
         "the bridge would slow every return"),
        ("planner.approach_speed_m_s", planner.approach_speed_m_s, planner.return_speed_m_s,
         "planner.return_speed_m_s", "the approach is the slow end of a return"),
    ):
        if value > bound:
            raise ConfigError(f"{field} = {value} m/s is above {bound_name} = {bound} m/s ({what}): lower it")


def check_against_robot(profile: Profile, desc: RobotDescription) -> None:
    """What the profile says of the robot ``desc`` must hold for it; else a ConfigError naming the field.

    Every per-joint list has one value per joint (the bridge's tighter limits
    and initial pose: or none) and stays within the joint limits; every pad
    the profile names is one of the skin's; every body region of the skin has
    its location weights; the task stays within the joint limits and its
    fastest point (pads, elbow, flange) within bridge.limits.speed_m_s and the
    robot's max_point_speed; the Cartesian limits within max_point_speed.
    :func:`load_profile` calls it with the description the profile names.
    """
    from nwr.common.robot import RobotModel

    planner, task, bridge = profile.planner, profile.planner.task, profile.bridge
    n = len(desc.joints)
    robot = f"robot {desc.name!r} has {n} joints ({', '.join(desc.joints)})"
    per_joint: tuple[tuple[str, list[float] | list[int], bool], ...] = (
        ("planner.q_max_deg", planner.q_max_deg, True),
        ("planner.task.amplitude_rad", task.amplitude_rad, True),
        ("planner.task.double_frequency", task.double_frequency, True),
        ("bridge.q_min", bridge.q_min, True),
        ("bridge.q_max", bridge.q_max, True),
        ("bridge.v_max", bridge.v_max, True),
        ("bridge.a_max", bridge.a_max, True),
        ("bridge.j_max", bridge.j_max, True),
        ("bridge.initial_q", bridge.initial_q, True),
    )
    for field, values, optional in per_joint:
        if len(values) != n and not (optional and not values):
            raise ConfigError(f"{field} has {len(values)} values, the {robot}: give one per joint"
                              + (" or none" if optional else ""))
        if not all(math.isfinite(v) for v in values):
            raise ConfigError(f"{field} = {values}: every value must be a finite number")
    described = {"q_min": desc.q_min, "q_max": desc.q_max, "v_max": desc.v_max, "a_max": desc.a_max,
                 "j_max": desc.j_max}
    for name, limit in described.items():
        for i, (value, base) in enumerate(zip(getattr(bridge, name), limit)):
            if value < base if name == "q_min" else value > base:
                raise ConfigError(f"bridge.{name}[{i}] = {value} is looser than the robot description's {base:g} "
                                  f"for {desc.joints[i]}: the profile may only tighten the limits")
            if name not in ("q_min", "q_max") and value <= 0:
                raise ConfigError(f"bridge.{name}[{i}] = {value} for {desc.joints[i]}: must be positive")
    # The joint ranges the bridge enforces: the description's, tightened by the profile's.
    q_lo = [float(b) for b in desc.q_min] if not bridge.q_min else [max(float(b), v) for b, v in zip(desc.q_min,
                                                                                                    bridge.q_min)]
    q_hi = [float(b) for b in desc.q_max] if not bridge.q_max else [min(float(b), v) for b, v in zip(desc.q_max,
                                                                                                    bridge.q_max)]
    for i, joint in enumerate(desc.joints):
        if q_lo[i] >= q_hi[i]:
            raise ConfigError(f"bridge.q_min/q_max leave {joint} no range: [{q_lo[i]:g}, {q_hi[i]:g}] rad")
        if bridge.initial_q and not q_lo[i] <= bridge.initial_q[i] <= q_hi[i]:
            raise ConfigError(f"bridge.initial_q[{i}] = {bridge.initial_q[i]} is outside {joint}'s limits "
                              f"[{q_lo[i]:g}, {q_hi[i]:g}] rad")

    pads = {pad.name for pad in desc.pads}
    for field, names in (("gain.overrides", list(profile.gain.overrides)),
                         ("gain.effective_mass.pad_regions", list(profile.gain.effective_mass.pad_regions)),
                         ("planner.target_order", planner.target_order)):
        unknown = [name for name in names if name not in pads]
        if unknown:
            raise ConfigError(f"{field} names {unknown}, which robot {desc.name!r} has no pad of; "
                              f"its pads: {', '.join(sorted(pads))}")
    model = RobotModel(desc)
    top = desc.max_point_speed
    moving = float(model.link_masses.sum())
    for field, value, bound, unit in (
        ("speed_m_s", bridge.limits.speed_m_s, top, "m/s"),
        ("withdrawal_speed_m_s", bridge.limits.withdrawal_speed_m_s, top, "m/s"),
        ("momentum_kg_m_s", bridge.limits.momentum_kg_m_s, moving * top, "kg m/s"),
    ):
        if value > bound:
            raise ConfigError(f"bridge.limits.{field} = {value} {unit} is beyond what the robot description allows "
                              f"({bound:.3g} {unit}: max_point_speed {top} m/s"
                              + (f" times the moving links' {moving:.3g} kg)" if unit == "kg m/s" else ")"))

    check_task(task, desc, model, q_lo, q_hi, bridge.limits.speed_m_s)


ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/\S+$")


def dotted_get(obj: Any, dotted: str) -> Any:
    """The field of ``obj`` at a dotted name ("bridge.limits.speed_m_s"), through sections and tables."""
    for part in dotted.split("."):
        obj = obj[part] if isinstance(obj, dict) else getattr(obj, part)
    return obj


# ------------------------------------------------------------------------------ safety beside a person
# (the fields and what loosens them: nwr.common.guards; the profile's defaults and acknowledgements here)


_DEFAULT = Profile()  # read only: the documented defaults


# The per-joint fields whose default (empty) is the robot's own value, robot.toml's attribute of it.
ROBOT_HELD: dict[str, str] = {
    "planner.q_max_deg": "reflex_range_deg",
    "planner.task.amplitude_rad": "task_amplitude_rad",
    "planner.task.double_frequency": "task_double_frequency",
}


@functools.lru_cache(maxsize=8)
def _robot_values(description: str) -> dict[str, list[Any]]:
    """The robot-held defaults (:data:`ROBOT_HELD`) of the robot a profile's robot.description names."""
    from nwr.common.robot import load_description

    desc = load_description(description or None)
    return {field: list(getattr(desc, attribute)) for field, attribute in ROBOT_HELD.items()}


def robot_default(profile: Profile, name: str) -> list[Any]:
    """The value a robot-held field (:data:`ROBOT_HELD`) of ``profile`` takes where the profile leaves it empty:
    the robot's own (robot.toml)."""
    return list(_robot_values(profile.robot.description)[name])


def _default(name: str, profile: Profile | None = None) -> Any:
    """The documented default of a safety-relevant field (a pad's override: the profile-wide default; a
    robot-held one: the robot's value, the profile's robot or else the default robot's)."""
    if name in ROBOT_HELD:
        return robot_default(profile or _DEFAULT, name)
    pattern = pattern_of(name)
    if pattern == "gain.overrides.<pad>.thresholds_hpa":
        value = _DEFAULT.gain.thresholds_hpa
    elif pattern is not None and "<region>" in pattern:
        # Every body region is held against the default region's values (any region less conservative than
        # the reference's must be acknowledged).
        value = getattr(BodyRegion(), name.rpartition(".")[2])
    else:
        value = dotted_get(_DEFAULT, name)
    return list(value) if isinstance(value, list) else value  # a copy: the defaults stay the defaults


def safe_range(field: str | Guarded) -> str:
    """What a safety-relevant field (a profile section's by dotted name, or a plug-in's) may hold without an
    acknowledgement (docs/profile.md prints the same)."""
    if isinstance(field, Guarded):
        guard, default = field.guard, field.default
    else:
        pattern = pattern_of(field)
        if pattern is None:
            raise KeyError(field)
        guard, default = GUARDS[pattern], _default(field)
    unit = f" {guard.unit}" if guard.unit else ""
    each = "each " if isinstance(default, list) else ""
    if guard.loosens == "other":
        return f"= {toml_value(default)}"
    if guard.loosens == "wider":
        return f"{each}magnitude <= {toml_value([abs(v) for v in default])}{unit}"
    return f"{each}{'<=' if guard.loosens == 'above' else '>='} {toml_value(default)}{unit}"


def guarded(profile: Profile) -> list[Guarded]:
    """Every safety-relevant field of the profile's own sections (the plug-ins' come from their tables)."""
    found = []
    for pattern, guard in GUARDS.items():
        if "<pad>" in pattern:
            for pad, override in profile.gain.overrides.items():
                if override.thresholds_hpa is not None:
                    name = pattern.replace("<pad>", pad)
                    found.append(Guarded(name, override.thresholds_hpa, _default(name), guard))
        elif "<region>" in pattern:
            for region, values in profile.gain.effective_mass.regions.items():
                name = pattern.replace("<region>", region)
                found.append(Guarded(name, dotted_get(values, name.rpartition(".")[2]), _default(name), guard))
        elif pattern in ROBOT_HELD:
            found.append(Guarded(pattern, dotted_get(profile, pattern) or robot_default(profile, pattern),
                                 _default(pattern, profile), guard))
        else:
            found.append(Guarded(pattern, dotted_get(profile, pattern), _default(pattern), guard))
    return found


def loosened(profile: Profile, plugins: Iterable[Guarded] = ()) -> list[Loosened]:
    """Every safety-relevant value of ``profile`` (and of its plug-ins' tables, ``plugins``) past its default on
    the side that loosens it."""
    return [Loosened(item.field, item.value, item.default, profile.safety.reason)
            for item in [*guarded(profile), *plugins] if loosens(item.guard, item.value, item.default)]


def loosened_safety(profile: Profile, plugins: Iterable[Guarded] = ()) -> list[dict[str, Any]]:
    """:func:`loosened` as plain data, for the session's metadata (``loosened_safety``)."""
    return [msgspec.to_builtins(item) for item in loosened(profile, plugins)]


def _deferred(name: str, sections: Iterable[str]) -> bool:
    """Whether ``name`` is a field of a plug-in's table under one of ``sections``."""
    section, _, rest = name.partition(".")
    plugged = PLUGGED.get(section)
    return section in sections and plugged is not None and rest.partition(".")[0] not in plugged.__struct_fields__


def check_acknowledgements(profile: Profile, plugins: Iterable[Guarded] = (),
                           deferred: Iterable[str] = ()) -> list[Loosened]:
    """The loosened values (the plug-ins' among them: ``plugins``), each acknowledged in ``[safety]``; else a
    ConfigError naming the field. Acknowledgements of plug-in fields under the sections ``deferred`` are left to
    the services that load those plug-ins."""
    safety = profile.safety
    given = [name for name in safety.acknowledge if not _deferred(name, tuple(deferred))]
    held = {item.field: item for item in [*guarded(profile), *plugins]}
    for name in given:
        if pattern_of(name) is None and name not in held:
            raise ConfigError(f"safety.acknowledge names {name!r}, which is no safety-relevant field "
                              "(docs/profile.md lists them, e.g. \"bridge.skin_timeout_s\")")
    repeated = sorted({name for name in given if given.count(name) > 1})
    if repeated:
        raise ConfigError(f"safety.acknowledge names {repeated} more than once: name each loosened value once")
    found = loosened(profile, plugins)
    names = [item.field for item in found]
    missing = [item for item in found if item.field not in given]
    if missing:
        values = "; ".join(f"{item.field} = {toml_value(item.value)} (default {toml_value(item.default)}, safe range "
                           f"{safe_range(held[item.field])})" for item in missing)
        raise ConfigError(
            f"{values}: loosened past the default, which is unsafe beside a person. Keep the safe range, or, with "
            f"nobody in the cell, acknowledge every loosened value in the profile: [safety] acknowledge = "
            f"{toml_value(names)} and reason = \"who, when, why\" (docs/profile.md)"
        )
    for name in given:
        if name not in names:
            item = held.get(name)
            raise ConfigError(
                f"safety.acknowledge names {name}, which this profile does not loosen ({name} = "
                f"{toml_value(item.value if item else None)}, safe range {safe_range(item or name)}): remove it; a "
                "stale acknowledgement would hide a later change"
            )
    if given and not safety.reason.strip():
        raise ConfigError(f"safety.reason is empty: say who loosened {names}, when and why "
                          "(e.g. \"bench test without a person in the cell, 2026-11-23, J. Doe\")")
    if safety.reason.strip() and not safety.acknowledge:
        raise ConfigError("safety.reason is set but safety.acknowledge names nothing, and nothing is loosened: "
                          "remove the reason")
    return found
