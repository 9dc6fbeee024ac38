"""What a command starts from: the touch scripts of the simulated skin, the environment's overrides of the
profile (NWR_ROUTER, NWR_ROBOT, NWR_TLS_*, NWR_INSECURE) and the profile a command line names.

The profile itself, its sections and its checks are :mod:`nwr.common.config`.
"""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Literal

import msgspec

from nwr.common.config import (
    ENDPOINT,
    SCRIPTS_DIR,
    NonNegative,
    Positive,
    Profile,
    _decode,
    _Section,
    packaged_or_path,
)
from nwr.common.errors import ConfigError

# The fastest a touch's finger follows a moving pad, m/s: about a quick reach's peak hand speed.
MAX_FOLLOW_M_S = 1.0


class Touch(_Section):
    # Pad name (or id as a string) of the robot's skin.
    pad: str
    # Start time from the beginning of the session, s.
    start_s: NonNegative
    # Time at peak (steps) or between the ends of the ramps (ramps), s.
    duration_s: Positive
    # Peak pressure change, hPa.
    peak_hpa: Annotated[float, msgspec.Meta(gt=0, le=200)]
    shape: Literal["step", "ramp"] = "step"
    # Rise and fall time of a ramp, s.
    ramp_s: NonNegative = 0.3
    # The physics world only: a finger that follows the pad, its owner's hand keeping it on the pad as the arm
    # moves, at up to this speed, m/s (0: it stays where its owner holds it, so the pad can leave it).
    follow_m_s: Annotated[float, msgspec.Meta(ge=0, le=MAX_FOLLOW_M_S)] = 0.0
    # The physics world only: the ISO/TS 15066 body area the person touches with, whose limits the touch's force
    # figures are judged by (a name of services/worlds/data/iso_ts_15066.toml, e.g. "forearm_muscle"; empty: the body
    # part's own, a finger's: "forefinger_pad_d").
    body_area: str = ""


class TouchScript(_Section):
    # Length of the session, s.
    duration_s: Positive
    touch: list[Touch] = []


def resolve_script(name_or_path: str, robot: str = "") -> Path:
    """A touch script given by packaged name ("demo") or by path. Scripts name pads, so a packaged name is
    first the robot's own (``scripts/`` beside its robot.toml; ``robot``: a profile's robot.description), then
    the packaged scripts (the UR10e's pads)."""
    from nwr.common.robot import resolve_description

    own = resolve_description(robot or None).parent / "scripts"
    if robot and Path(name_or_path).suffix != ".toml" and (own / f"{name_or_path}.toml").is_file():
        return own / f"{name_or_path}.toml"
    return packaged_or_path(name_or_path, SCRIPTS_DIR, "touch script")


def load_script(name_or_path: str, robot: str = "") -> TouchScript:
    """The touch script by packaged name (the robot's own first, :func:`resolve_script`) or path."""
    script = _decode(resolve_script(name_or_path, robot), TouchScript)
    assert isinstance(script, TouchScript)
    for touch in script.touch:
        if touch.start_s + touch.duration_s + 2 * touch.ramp_s > script.duration_s:
            raise ConfigError(
                f"touch on {touch.pad} at {touch.start_s} s ends after the script's duration {script.duration_s} s"
            )
    return script


def encode_profile(profile: Profile) -> bytes:
    """The profile as JSON, for session metadata."""
    return msgspec.json.encode(profile)


# <protocol>/<address>[:port], Zenoh's endpoint syntax (tcp/10.0.0.2:7447, tcp/[::]:7447).


def parse_endpoints(text: str, what: str) -> list[str]:
    """Comma-separated Zenoh endpoints; ConfigError naming the bad one."""
    endpoints = [e.strip() for e in text.split(",") if e.strip()]
    for e in endpoints:
        if not ENDPOINT.match(e):
            raise ConfigError(f"{what}: {e!r} is not a Zenoh endpoint; write <protocol>/<host>:<port>, "
                              "e.g. tcp/0.0.0.0:7447 or tcp/10.0.0.2:7447")
    return endpoints


# Environment variables that override the profile (the compose deployment
# sets them per host): variable -> what it overrides.
ENV_OVERRIDES = {
    "NWR_ROUTER": "[zenoh] router: comma-separated router endpoints, e.g. tcp/10.0.0.2:7447",
    "NWR_ROBOT": "[robot] name: the key prefix nwr/<name>/",
    "NWR_SKIN": "[robot] skin: pads or taxels (nwr up/demo --skin passes it to their services)",
    "NWR_TLS_CA": "[zenoh] ca_certificate: the lab CA's ca.crt; any NWR_TLS_* turns secure mode on",
    "NWR_TLS_CERT": "[zenoh] certificate: this service's NAME.crt (nwr certs issue)",
    "NWR_TLS_KEY": "[zenoh] private_key: this service's NAME.key",
    "NWR_INSECURE": "1: secure mode off (no TLS, no access control), whatever the profile and NWR_TLS_* say",
}
# Spellings of NWR_INSECURE; anything else is an error rather than a guess.
_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


def env_overrides(environ: Mapping[str, str]) -> dict[str, str]:
    """The profile overrides set in ``environ`` (empty values are unset)."""
    return {name: environ[name].strip() for name in ENV_OVERRIDES if environ.get(name, "").strip()}


def apply_env_overrides(profile: Profile, overrides: Mapping[str, str]) -> Profile:
    """``profile`` with NWR_ROUTER, NWR_ROBOT, NWR_SKIN, NWR_TLS_* and NWR_INSECURE applied; ConfigError naming a
    bad value."""
    if "NWR_ROUTER" in overrides:
        profile.zenoh.router = parse_endpoints(overrides["NWR_ROUTER"], "NWR_ROUTER")
    if "NWR_ROBOT" in overrides:
        name = overrides["NWR_ROBOT"]
        if not re.fullmatch(r"[a-z][a-z0-9_-]{0,31}", name):
            raise ConfigError(f"NWR_ROBOT={name!r} is not a robot name: lower-case letters, digits, '_' and '-', "
                              "starting with a letter, at most 32 characters (e.g. ur10e)")
        profile.robot.name = name
    if "NWR_SKIN" in overrides:
        skin = overrides["NWR_SKIN"]
        if skin not in ("pads", "taxels"):
            raise ConfigError(f"NWR_SKIN={skin!r}: expected pads or taxels")
        profile.robot.skin = "taxels" if skin == "taxels" else "pads"
    for variable, field in (("NWR_TLS_CA", "ca_certificate"), ("NWR_TLS_CERT", "certificate"),
                            ("NWR_TLS_KEY", "private_key")):
        if variable in overrides:
            setattr(profile.zenoh, field, overrides[variable])
            profile.zenoh.secure = True
    ros2 = profile.ros2.router if profile.ros2.enabled or profile.gateway.source == "ros2" else []
    if insecure(overrides):
        profile.zenoh.secure = False
    elif beyond := [e for e in ros2 if not _loopback(e)]:
        raise ConfigError(
            f"[ros2] router {', '.join(beyond)} reaches beyond this machine, and the ROS 2 side has no TLS: anyone "
            "on that network could feed the skin. Run rmw_zenohd on this machine (the lab's routers link to it), "
            "or acknowledge the open network with NWR_INSECURE=1 (a trusted network only)")
    elif not profile.zenoh.secure:
        beyond = [e for e in [*profile.zenoh.router, f"tcp/{profile.zenoh.host}:{profile.zenoh.base_port}"]
                  if not _loopback(e)]
        if beyond:
            raise ConfigError(
                f"{', '.join(beyond)} reaches beyond this machine without TLS: anyone on that network could move "
                "the arm. Use the secure deployment (NWR_TLS_CA / NWR_TLS_CERT / NWR_TLS_KEY or [zenoh] secure, "
                "docs/security.md), or acknowledge the open network with NWR_INSECURE=1 (a trusted network only)")
    return profile


def _loopback(endpoint: str) -> bool:
    """Whether a Zenoh endpoint (``tcp/HOST:PORT``) names this machine (127.0.0.0/8, ::1, localhost)."""
    host = endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def insecure(overrides: Mapping[str, str]) -> bool:
    """Whether NWR_INSECURE asks for secure mode off; ConfigError for a value that is neither yes nor no."""
    value = overrides.get("NWR_INSECURE", "0").lower()
    if value not in _TRUE + _FALSE:
        raise ConfigError(f"NWR_INSECURE={value!r}: set it to 1 to run without TLS and access control, "
                          "or unset it (0)")
    return value in _TRUE
