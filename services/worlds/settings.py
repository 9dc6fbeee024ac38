"""The physics world's settings (``[bridge.physics]``) and its divergence error, apart from the world itself:
a profile is checked, and a bridge started, without importing MuJoCo (:mod:`.physics` imports it)."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from nwr.common.errors import ConfigError, NwrError
from nwr.common.section import Section
from nwr.services.worlds import mjcf


class WorldUnstable(NwrError):
    """The simulation diverged: the world stopped, its readings are the last good step's."""


class PhysicsSettings(Section):
    """The physics world's step, servos, skin, people and divergence checks (a profile section once wired)."""

    # The world's fixed time step, s. 1 ms gives the 500 Hz bridge two steps
    # per cycle; the default gains stay stable up to the 5 ms bound.
    timestep_s: Annotated[float, msgspec.Meta(ge=0.0002, le=0.005)] = 0.001
    # Servo stiffness: the position error (rad) at which a joint's servo
    # reaches its effort limit; kp = effort limit / this.
    servo_error_rad: Annotated[float, msgspec.Meta(ge=0.005, le=1.0)] = 0.05
    # Servo damping: kv = kp * this, s (the weight of the speed error).
    servo_damping_s: Annotated[float, msgspec.Meta(ge=0.0, le=0.5)] = 0.04
    # Rotor inertia reflected through each joint's gearbox, kg m^2.
    armature_kg_m2: Annotated[float, msgspec.Meta(ge=0.0, le=10.0)] = 0.1
    # The arm's collision shapes; empty: the packaged ones of the robot (by
    # its name), else capsules between its joint origins.
    shapes: list[mjcf.LinkShape] = msgspec.field(default_factory=list)
    # The radius of those capsules between joint origins, m.
    skeleton_radius_m: Annotated[float, msgspec.Meta(gt=0, le=0.5)] = 0.05
    # Each pad's cushion: its depth under the pad's surface point, m.
    cushion_thickness_m: Annotated[float, msgspec.Meta(gt=0, le=0.1)] = 0.03
    # Each pad's cushion: the half width of its square face, m.
    cushion_half_width_m: Annotated[float, msgspec.Meta(gt=0, le=0.3)] = 0.05
    # The skin's softness, cushions and covered housings alike: MuJoCo's
    # solref time constant, s (at least two steps; MuJoCo raises it if not).
    cushion_timeconst_s: Annotated[float, msgspec.Meta(ge=0.002, le=0.2)] = 0.02
    # ... and its damping ratio (1: no bounce).
    cushion_dampratio: Annotated[float, msgspec.Meta(gt=0, le=10)] = 1.0
    # Friction coefficient between people and the arm.
    friction: Annotated[float, msgspec.Meta(ge=0, le=3)] = 0.8
    # The pads' pressure model: the effective area a normal force spreads
    # over, cm^2 (dP = F / A_eff for small forces).
    effective_area_cm2: Annotated[float, msgspec.Meta(ge=1, le=5000)] = 125.0
    # The pressure change a pad saturates toward, hPa.
    saturation_hpa: Annotated[float, msgspec.Meta(ge=25, le=1000)] = 80.0
    # The skin's sample rate, Hz (AIRSKIN: about 25 Hz).
    skin_rate_hz: Annotated[float, msgspec.Meta(ge=1, le=1000)] = 25.0
    # A taxel skin's sample rate (robot.skin = "taxels"), Hz: at most the
    # world's step rate (1 / timestep_s).
    taxel_rate_hz: Annotated[float, msgspec.Meta(ge=1, le=5000)] = 1000.0
    # From a sample's instant to its delivery, s (0: none modelled; a lab
    # that measured its skin's latency puts it here).
    skin_latency_s: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.0
    # What a sample holds: "instant", the pressure at the sample's own world
    # step (a light touch on a moving pad that loses contact for that one
    # step reads 0 there); "mean", the mean of each pad's pressure over the
    # steps since the last sample (a device that averages between readings:
    # such a step dims a sample, never blanks it, and a light touch that
    # keeps losing contact averages below the contact threshold).
    skin_sample: Literal["mean", "instant"] = "instant"
    # White noise on every pad's reading, standard deviation, hPa.
    skin_noise_hpa: Annotated[float, msgspec.Meta(ge=0, le=5)] = 0.08
    # The pads' absolute no-contact pressure, hPa.
    skin_base_hpa: Annotated[float, msgspec.Meta(gt=0, le=5000)] = 1013.0
    # How far each pad's no-contact pressure is off the base, at most, hPa.
    skin_spread_hpa: Annotated[float, msgspec.Meta(ge=0, le=100)] = 3.0
    # Seed of the skin's noise and baselines (the same seed, the same run).
    seed: int = 7
    # How many fingers can be in the world at once.
    fingers: Annotated[int, msgspec.Meta(ge=0, le=32)] = 4
    # How many palms can be in the world at once.
    palms: Annotated[int, msgspec.Meta(ge=0, le=32)] = 2
    # How many forearms can be in the world at once.
    forearms: Annotated[int, msgspec.Meta(ge=0, le=32)] = 2
    # A person's spring toward a body part's target, N/m, unless the body
    # part gives its own (a human arm's endpoint: a few hundred N/m).
    person_stiffness_n_m: Annotated[float, msgspec.Meta(ge=10, le=20000)] = 500.0
    # The damping ratio of that spring with the body part's mass.
    person_damping_ratio: Annotated[float, msgspec.Meta(ge=0.1, le=5)] = 1.0
    # Divergence: a joint faster than this times its speed limit.
    max_speed_factor: Annotated[float, msgspec.Meta(ge=1, le=10)] = 1.5
    # Divergence: a body part faster than this, m/s.
    max_body_speed_m_s: Annotated[float, msgspec.Meta(ge=0.5, le=100)] = 10.0
    # Divergence: a contact deeper than this, m (a body passing through the arm).
    max_penetration_m: Annotated[float, msgspec.Meta(ge=0.001, le=0.2)] = 0.02


def check_taxel_rate(settings: PhysicsSettings) -> None:
    """A taxel skin's rate is at most the world's step rate (a sample is taken at a step); ConfigError."""
    if settings.taxel_rate_hz * settings.timestep_s > 1.0 + 1e-9:
        raise ConfigError(f"bridge.physics.taxel_rate_hz = {settings.taxel_rate_hz:g} Hz is faster than the world's "
                          f"steps (timestep_s = {settings.timestep_s} s: {1.0 / settings.timestep_s:g} Hz); lower "
                          "one or the other")
