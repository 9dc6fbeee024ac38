"""Every wire message of the pipeline, as msgspec Structs (msgpack on the wire).

This module is the single source of truth for what travels between the
services. The recorder derives its JSON Schemas from it, the key registry
(:mod:`nwr.common.keys`) maps each key expression to one type here.

Conventions
-----------
- Every message carries ``seq`` (a per-publisher counter starting at 0) and
  ``stamp_ns`` (the source's clock, ``time.monotonic_ns()`` by default: one
  clock shared by every process of a machine, so cross-process latencies are
  plain differences).
- Per-pad and per-joint payloads are flat lists of numbers, in pad id order
  and joint order of the robot description. Use :func:`as_array` to turn them
  into numpy arrays.
- Messages that share a key form a tagged union (``tag_field="kind"``).

Evolution rules
---------------
- A new field always gets a default, so older recordings still decode.
- No field ever changes its type or meaning; add a new field instead.
- Decoding is strict: unknown message kinds, missing required fields and
  wrong types are rejected whole (never half-used).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec
import numpy as np

# Every number on the wire is finite: NaN and infinities are rejected at
# decoding, so no service ever acts on one (and recordings stay valid JSON).
FINITE_BOUND = 1e12
Finite = Annotated[float, msgspec.Meta(ge=-FINITE_BOUND, le=FINITE_BOUND)]

# HOLDING: the withdrawal's motion is over and the arm stays away while the touch lasts (planner.sustained_contact).
MODES = ("TASK", "REFLEX", "RETURNING", "HOLDING")
Mode = Literal["TASK", "REFLEX", "RETURNING", "HOLDING"]

RobotStatus = Literal[
    "ok",  # following commands
    "idle",  # no command received yet: holding still
    "stale_command",  # commands stopped arriving: decelerating to rest and holding
    "stopped",  # stopped on request or at shutdown
    "stale_skin",  # skin data too old: task and return motions held (reflexes may finish)
    "planner_lost",  # the active planner's liveliness token vanished: decelerating to rest and holding
    "protective_stop",  # the robot controller is in a protective stop (ur_rtde backend)
    "emergency_stop",  # the robot's emergency stop is pressed (ur_rtde backend)
    "script_not_running",  # the ur_rtde control script is not running on the controller
    "disconnected",  # no connection to the robot controller: reconnecting with backoff
    "state_implausible",  # the robot's reported state is not believed (following error, jump, frozen): stopped
    "robot_reflex",  # the robot's own reflex stopped it (franky: Franka's collision or limit reflex)
    "motion_refused",  # the robot refused the bridge's motion, or is in no mode to be moved (franky)
]


class Trace(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Identifies the skin sample a decision was made on (sequence and stamp)."""

    seq: int
    stamp_ns: int


# A decision made on no skin sample yet: a planner's task commands before its first pain message.
NO_TRACE = Trace(-1, 0)


class SkinPressure(msgspec.Struct, tag="skin_pressure", tag_field="kind", forbid_unknown_fields=True):
    """Skin gateway output: one sample of every pad, in pad id order.

    ``change_hpa`` is the pressure change from each pad's no-contact baseline.
    """

    seq: int
    stamp_ns: int
    absolute_hpa: list[Finite]
    baseline_hpa: list[Finite]
    change_hpa: list[Finite]
    contact: list[bool]
    # False where a pad's reading was not a finite number (its change is 0).
    valid: list[bool] = []
    source: str = "sim"
    # Simulated skin only: the part of absolute_hpa that its touches added, per
    # pad (the ground truth a re-simulation replaces); empty for a real skin.
    touch_hpa: list[Finite] = []


class SkinTouch(msgspec.Struct, tag="skin_touch", tag_field="kind", forbid_unknown_fields=True):
    """Simulated skin only: the ground truth of one touch, published when it starts.

    The touch's pressure profile is the touch script's (``start_s``,
    ``duration_s``, ``peak_hpa``, ``shape``, ``ramp_s``) on the gateway's
    script clock, whose zero is ``origin_ns``: a skin sample stamped ``s``
    is at script time ``(s - origin_ns) / 1e9``. The finger is a point that
    stays where it met the pad: ``contact_point`` and the pad's outward
    ``normal`` there, in the robot's base frame, from the arm pose ``q`` the
    gateway knew (from ``robot/state``) when the touch started; all three
    are None if it knew none.
    """

    seq: int
    stamp_ns: int
    pad: int
    name: str
    origin_ns: int
    start_s: Finite
    duration_s: Finite
    peak_hpa: Finite
    shape: Literal["step", "ramp"]
    ramp_s: Finite
    contact_point: list[Finite] | None = None
    normal: list[Finite] | None = None
    q: list[Finite] | None = None
    # The robot state the pose came from (its stamp), 0 if none.
    pose_stamp_ns: int = 0
    # Whether this gateway's pressure fell as the pad withdrew from the finger
    # (gateway.sim.closed_loop), and the indentation depth it used, m.
    closed_loop: bool = False
    depth_m: Finite = 0.0
    # The physics world's finger follows the pad at up to this speed, m/s (the touch script's follow_m_s; 0: it
    # stays where its owner holds it).
    follow_m_s: Finite = 0.0
    # The ISO/TS 15066 body area the touch script names for it (its force figures' limits; "": the body part's own).
    body_area: str = ""


class WorldSkin(msgspec.Struct, tag="world_skin", tag_field="kind", forbid_unknown_fields=True,
                omit_defaults=True):
    """A physics world's skin: one sample of every pad as the device would report it, in pad id order.

    The bridge's ``physics`` backend hosts the world and publishes its samples
    (the skin's rate, 25 Hz by default); the gateway's ``physics`` source
    takes them as a device's. ``world_ns`` is the world's own time of the
    sample (its steps since it started); ``force_n`` the normal force on each
    pad and ``change_hpa`` the pressure change it makes (noise-free: the
    ground truth beside the noisy absolute reading).

    On a taxel skin (``robot.skin = "taxels"``) a sample is one reading per
    taxel instead, in taxel id order: ``taxels``, each taxel's pressure over
    its no-touch baseline in the skin file's unit, with noise (the taxel
    skin's rate, 1 kHz by default); the pad lists are then empty. Left off
    the wire when empty, so that a pad sample encodes byte for byte as
    before.
    """

    seq: int
    stamp_ns: int
    world_ns: int
    absolute_hpa: list[Finite]
    change_hpa: list[Finite]
    force_n: list[Finite]
    taxels: list[Finite] = []


class WorldPerson(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One body part in a physics world: what it feels now and at its worst since it entered."""

    # The body part's name (a touch's: "touch-<skin/touch seq>").
    name: str
    kind: str
    # The skin/touch seq the part stands for, -1 if none.
    touch: int
    # The pads it touches now.
    pads: list[int]
    # The contact force on it, N, and its peak.
    force_n: Finite
    peak_force_n: Finite
    # The force over the contact area, N/cm^2, and its peak.
    pressure_n_cm2: Finite
    peak_pressure_n_cm2: Finite
    # The work the arm's contacts did on it, J.
    energy_j: Finite
    # How far the arm has pushed it back from where it met the pad, along the pad's outward normal, m
    # (now, and the most since it entered): how far the pad moved into the finger.
    pushed_m: Finite
    peak_pushed_m: Finite


class WorldContacts(msgspec.Struct, tag="world_contacts", tag_field="kind", forbid_unknown_fields=True):
    """A physics world's people, with every skin sample while any is in the world (their contact figures)."""

    seq: int
    stamp_ns: int
    world_ns: int
    people: list[WorldPerson] = []


class Contact(msgspec.Struct, frozen=True, forbid_unknown_fields=True, omit_defaults=True):
    """The strongest contact of a skin sample.

    On a taxel skin (``robot.skin = "taxels"``) ``pad`` is the pad whose patch the contact is on, and the
    contact carries its own location: ``point`` and outward unit ``normal`` in the frame of ``link`` (the
    pressure-weighted centroid and normal of its taxels) and its ``force_n``; ``change_hpa`` is its peak
    taxel's change. On the pads ``link`` is empty and the pad's own point and normal are the contact's; the
    fields at their defaults are left off the wire, so the pads' messages encode as before these fields.
    """

    pad: int
    name: str
    region: str
    change_hpa: Finite
    level: int
    gain: Finite
    link: str = ""
    point: list[Finite] = []
    normal: list[Finite] = []
    force_n: Finite = 0.0


class SkinPain(msgspec.Struct, tag="skin_pain", tag_field="kind", forbid_unknown_fields=True):
    """Gain estimator output: per-pad pain level (1-4) and gain G(p) in [0, 1]."""

    seq: int
    stamp_ns: int
    trace: Trace
    model: str
    level: list[int]
    gain: list[Finite]
    strongest: Contact | None = None
    # The effective-mass model's prediction per pad (empty for the paper's models): the arm's effective mass
    # along the pad's direction of motion, kg (0: unknown), the impact force a collision at its speed would
    # cause, N (where unknown: its body region's limit), and the scale of its pain thresholds; impact_basis is
    # "state" (predicted from the robot state) or why no prediction could be made (every pad then unknown and
    # at its most sensitive: "no_state", "stale_state", "non_finite_state", "ill_conditioned").
    effective_mass_kg: list[Finite] = []
    impact_n: list[Finite] = []
    threshold_scale: list[Finite] = []
    impact_basis: str = ""
    # The pads whose gain came from the arm's external torques, the skin blind there (gain.torque).
    torque_pads: list[int] = []
    # The pads in contact below PL 2: the skin gateway's contact (a change above gateway.contact_hpa, with its
    # hysteresis; a taxel skin: a contact on the pad's taxels) at pain level 1, a touch too light for a pain
    # level. The planner keeps it as a touch: where a person is, a hand resting on the arm.
    light_touch: list[int] = []


class PositionCommand(msgspec.Struct, tag="position", tag_field="kind", forbid_unknown_fields=True):
    """Joint position target (rad) for the next control cycle.

    A planned motion (the task) may also carry the setpoints of the cycles
    after it: ``ahead[k]`` is the target ``(k + 1) * period_s`` after ``q``,
    so one message covers several cycles (the bridge interpolates between
    them and follows the next command as soon as it arrives).
    """

    seq: int
    stamp_ns: int
    owner: str
    q: list[Finite]
    trace: Trace
    reflex_seq: int = 0
    phase: Mode = "TASK"
    ahead: list[list[Finite]] = []
    period_s: Finite = 0.0


class VelocityCommand(msgspec.Struct, tag="velocity", tag_field="kind", forbid_unknown_fields=True):
    """Joint velocity target (rad/s) for the next control cycle."""

    seq: int
    stamp_ns: int
    owner: str
    dq: list[Finite]
    trace: Trace
    reflex_seq: int = 0
    phase: Mode = "REFLEX"


Command = PositionCommand | VelocityCommand


class SwitchRequest(msgspec.Struct, tag="switch_request", tag_field="kind", forbid_unknown_fields=True):
    """Make ``name`` the active planner (anyone may ask; the bridge decides when)."""

    seq: int
    stamp_ns: int
    name: str
    requested_by: str = ""


SafetyMode = Literal["normal", "reduced"]


class SafetyModeRequest(msgspec.Struct, tag="safety_mode_request", tag_field="kind", forbid_unknown_fields=True):
    """Switch the bridge's Cartesian limits to the normal or the reduced set (the operator's role only)."""

    seq: int
    stamp_ns: int
    mode: SafetyMode
    requested_by: str = ""


class Handover(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One switch of the active planner, as the bridge carried it out."""

    previous: str
    owner: str
    requested_ns: int  # the request's stamp
    switched_ns: int  # when the bridge made the new planner the owner
    first_command_ns: int = 0  # when it accepted the new owner's first command (0: not yet)


class RobotState(msgspec.Struct, tag="robot_state", tag_field="kind", forbid_unknown_fields=True):
    """Bridge output: the arm's joint state and what the bridge is doing.

    ``accepted`` / ``accepted_ns`` name the newest reflex whose first command
    the bridge accepted for its backend and when: the end of the reflex
    onset latency (``accepted_ns - accepted.stamp_ns``). The bridge publishes
    a state out of schedule the moment it accepts a new reflex.
    """

    seq: int
    stamp_ns: int
    q: list[Finite]
    dq: list[Finite]
    status: RobotStatus
    owner: str
    backend: str
    command_mode: Literal["none", "position", "velocity"] = "none"
    reflex_seq: int = 0
    accepted: Trace | None = None
    accepted_ns: int = 0
    rejected: int = 0
    clipped: int = 0
    # True while the bridge runs a controlled (jerk-limited) stop.
    stopping: bool = False
    # Per-joint distance (rad) and duration (s) of the current or last controlled stop.
    stop_distance: list[Finite] = []
    stop_time_s: Finite = 0.0
    # Age of the newest skin sample at the bridge, s; -1 before the first one.
    skin_age_s: Finite = -1.0
    # Why the status is what it is, readable (empty while following normally).
    detail: str = ""
    # A requested switch of the active planner not yet carried out (it waits
    # for the outgoing planner's reflex and return to end), and the last one.
    pending_owner: str = ""
    handover: Handover | None = None
    # The Cartesian limits in force, and how many control cycles they scaled.
    safety_mode: SafetyMode = "normal"
    limited: int = 0
    # The phase of the command being followed (a withdrawal is REFLEX).
    phase: Mode = "TASK"
    # True: q and dq are the last known ones, not a measurement of this moment
    # (the controller is unreachable, or its report was not finite; dq is 0).
    pose_stale: bool = False
    # The controller's estimated external torque per joint, N m (franky: Franka's tau_ext_hat_filtered);
    # empty when the backend has no such estimate.
    tau_ext: list[Finite] = []


class Retreat(msgspec.Struct, frozen=True, forbid_unknown_fields=True, omit_defaults=True):
    """Does the touched pad retreat? Computed from the kinematics of the planned reflex.

    Distances in m, speeds in m/s; "toward" is along the touched pad's outward
    normal at the onset, i.e. toward the person touching it. With other
    active contacts at the onset, ``contacts`` names their pads and
    ``contacts_toward_m`` how far each moves toward its own contact (along its
    own normal at the onset); with none both are empty and left off the wire,
    so a single touch's message encodes as before these fields.
    """

    sample_dt_s: Finite
    normal_speed_m_s: list[Finite]  # touched pad's speed along its normal, + toward the contact
    toward_m: Finite  # furthest the touched pad moves toward the contact (0: it only retreats)
    withdrawal_m: Finite  # where it ends, away from the contact
    approach_m: list[Finite]  # per pad: how much closer it gets to the contact point
    worst_pad: int
    worst_approach_m: Finite
    approached: bool  # the touched pad moved toward the contact
    corrected: bool  # guarded mode changed the reflex so that it retreats
    contacts: list[int] = []  # the other active contacts' pads
    contacts_toward_m: list[Finite] = []  # per such pad: furthest it moves toward its own contact (>= 0)


class ReflexInfo(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """The reflex a planner is executing."""

    reflex_seq: int
    strategy: str
    contact: Contact
    trace: Trace
    started_ns: int
    duration_s: Finite
    # Cartesian reflexes: the pad's commanded velocity v_c (m/s, base frame).
    direction: list[Finite] = []
    # Joint-space reflexes: the joint target (rad).
    target: list[Finite] = []
    retreat: Retreat | None = None
    # Computed by an inactive planner: what it would have done.
    shadow: bool = False
    # False: no motion of the joints can move the touched pad away from the contact in this pose (its
    # normal speed is below a centimetre a second at the joint limits); the arm holds still instead.
    withdraws: bool = True
    # Why the motion is not the strategy's plain withdrawal, when it is not ("" when it is): "sideways" (the
    # pad's joints cannot move it along its normal without another part of the arm coming toward the contact:
    # it withdraws across the normal, away from the contact point, along ``direction``), "short" (its joints
    # move it along its normal only a few millimetres without that: it withdraws the gain's share of that
    # reach, along ``direction``), "blocked" (nothing withdraws it without that: the arm holds still),
    # "failed" (the strategy's computation failed: stand-still commands). Set by the whole-arm withdrawal.
    reason: str = ""
    # How far the touched pad would withdraw along its normal at full gain (G = 1), m: what its joints allow
    # this reflex (the whole-arm withdrawal's distance_m, or a short one's reach), against which its
    # withdrawal is the gain's share. 0: the strategy does not say (the paper's; an older recording).
    reach_m: Finite = 0.0


class PlannerStatus(msgspec.Struct, tag="planner_status", tag_field="kind", forbid_unknown_fields=True):
    """A planner's state machine, published on every transition and periodically."""

    seq: int
    stamp_ns: int
    name: str
    strategy: str
    mode: Mode
    task_time_s: Finite
    saved_pose: list[Finite] | None = None
    reflex: ReflexInfo | None = None
    # False while another planner moves the arm: this one then mirrors the arm
    # and the active planner's task (ready to take over), and computes what it
    # would do on each touch (a shadow reflex, ``reflex.shadow``).
    active: bool = True
    # The study's target pad (the one whose LEDs turn red), -1 if none.
    target_pad: int = -1


class PlannerDecision(msgspec.Struct, tag="planner_decision", tag_field="kind", forbid_unknown_fields=True):
    """When a planner acted on one pain message: the end of the sample latency.

    One per pain message, published after any command it caused, so that it
    costs the reflex path nothing. ``stamp_ns`` is the moment the planner's
    decision was made (its state machine had taken the message in); the
    sample latency is ``stamp_ns - trace.stamp_ns`` and the gain -> planner
    hop ``stamp_ns - pain_stamp_ns``.
    """

    seq: int
    stamp_ns: int
    name: str
    trace: Trace  # the skin sample the pain message was computed from
    pain_seq: int
    pain_stamp_ns: int
    # When the pain message reached the planner's callback (before its lock).
    received_ns: int = 0
    # The reflex this message started or updated (its first command was sent), 0 if none.
    reflex_seq: int = 0
    # False while another planner moves the arm (the decision was a shadow one).
    active: bool = True


class Diagnostic(msgspec.Struct, tag="diagnostic", tag_field="kind", forbid_unknown_fields=True):
    """A warning or error of a service, with a stable code and a readable message."""

    seq: int
    stamp_ns: int
    service: str
    level: Literal["info", "warning", "error"]
    code: str
    message: str
    count: int = 1


class JournalEntry(msgspec.Struct, array_like=True, forbid_unknown_fields=True):
    """One input a service handled, in the order it handled them (see :mod:`nwr.common.journal`).

    ``key``, ``seq`` and ``stamp_ns`` name a recorded message (``key`` empty:
    an input that is no message, a tick or a liveliness token); ``now`` holds
    every clock reading the handler made, in order; ``arg``, ``text`` and
    ``data`` carry an input that is not recorded elsewhere (a token's name
    and whether it appeared, an arm's measured state).
    """

    input: str
    now: list[int] = []
    key: str = ""
    seq: int = -1
    stamp_ns: int = 0
    arg: int = 0
    text: str = ""
    data: list[Finite] = []


class Journal(msgspec.Struct, tag="journal", tag_field="kind", forbid_unknown_fields=True):
    """A batch of one service run's journal: what it needs to be re-run exactly (``nwr verify``).

    ``run_ns`` tells the runs of one service apart (a restart starts a new
    run, its batches from ``seq`` 0 again); the first batch of a run carries
    ``config`` (JSON: the effective profile and the service's own
    parameters), the last one (a clean exit) ``final``.
    """

    seq: int
    stamp_ns: int
    service: str
    run_ns: int
    entries: list[JournalEntry] = []
    config: str = ""
    final: bool = False


Message = (SkinPressure | SkinTouch | SkinPain | PositionCommand | VelocityCommand | RobotState | PlannerStatus
           | Diagnostic | SwitchRequest | PlannerDecision | Journal | WorldSkin | WorldContacts)


def as_array(values: list[float] | list[int] | list[bool]) -> np.ndarray:
    """The one place where a wire list becomes a numpy array (float64)."""
    return np.asarray(values, dtype=np.float64)


def json_schema(message_type: object) -> dict[str, Any]:
    """JSON Schema of a message type, in the form Foxglove and Lichtblick load.

    Both apps read the ``jsonschema`` of a ``json`` channel with one loader
    (``parseJsonSchema`` of their ``mcap-support`` package), which drops a
    channel whose schema it cannot read. It takes an object at the top whose
    properties each have a ``type``: boolean, string, number, integer, an
    object that lists its ``properties``, or an array of one of those (not of
    arrays); no ``$ref``, no ``anyOf``. msgspec's schema is rewritten to that:

    - definitions are inlined (no ``$ref``, no ``$defs``);
    - an enum (a ``Literal``, the ``kind`` tag) gets its ``type``;
    - an optional field gets the schema of its value (the apps read a
      ``null`` there as the field's absence);
    - a union of messages on one key (``nwr.Command``) becomes one object
      with the properties of every kind, ``kind`` the enum of their tags;
    - a field with no form in the loader (an array of arrays,
      ``PositionCommand.ahead``; of array-like records, ``Journal.entries``)
      is left out of ``properties`` and named in the object's ``$comment``,
      and that object drops ``additionalProperties: false``: the messages
      still carry it (the Raw Messages panel shows it), it just has no path
      to plot.

    The schema stays true of every message of the type as msgspec encodes it:
    only what the schema says changes, not the messages.
    """
    raw = msgspec.json.schema(message_type)
    schema = _loadable(raw, raw.get("$defs", {}))
    if schema is None or schema.get("type") != "object":
        raise TypeError(f"{message_type!r} has no JSON Schema Foxglove can load: its messages must be objects")
    return schema


# What Foxglove's loader takes besides objects and arrays.
_SCALARS = ("boolean", "string", "number", "integer")
_ENUM_TYPES = ((bool, "boolean"), (str, "string"), (int, "integer"), (float, "number"))
LEFT_OUT = "not described (no form in Foxglove's JSON Schema loader): "


def _loadable(schema: dict[str, Any], defs: dict[str, Any]) -> dict[str, Any] | None:
    """``schema`` (msgspec's) in the form :func:`json_schema` describes; None if it has none."""
    if "$ref" in schema:
        return _loadable(defs[schema["$ref"].rsplit("/", 1)[-1]], defs)
    if "anyOf" in schema:
        alternatives = [_loadable(a, defs) for a in schema["anyOf"] if a.get("type") != "null"]
        loaded = [a for a in alternatives if a is not None]
        if len(loaded) < len(alternatives):
            return None
        return loaded[0] if len(loaded) == 1 else _union(loaded)
    out = {k: v for k, v in schema.items() if k not in ("$defs", "discriminator")}
    if "enum" in out and "type" not in out:
        types = {next((name for t, name in _ENUM_TYPES if isinstance(v, t)), None) for v in out["enum"]}
        if len(types) != 1 or None in types:
            return None
        out = {"type": types.pop(), **out}
    kind = out.get("type")
    if kind == "object":
        if "properties" not in out:
            return None  # a dict: its keys are known only at run time
        properties: dict[str, Any] = {}
        for name, field in out["properties"].items():
            described = _loadable(field, defs)
            if described is not None:
                properties[name] = described
        return _with_properties(out, properties, [n for n in out["properties"] if n not in properties])
    if kind == "array":
        items = _loadable(out["items"], defs) if "items" in out else None  # prefixItems: a tuple, an array-like
        if items is None or items["type"] == "array":
            return None
        return {**out, "items": items}
    return out if kind in _SCALARS else None


def undescribed(schema: dict[str, Any]) -> list[str]:
    """The fields an object of :func:`json_schema` leaves out (named in its ``$comment``)."""
    comment = schema.get("$comment", "")
    return comment.removeprefix(LEFT_OUT).split(", ") if comment.startswith(LEFT_OUT) else []


def _with_properties(schema: dict[str, Any], properties: dict[str, Any], left_out: list[str]) -> dict[str, Any]:
    out = {**schema, "properties": properties}
    if left_out:
        out.pop("additionalProperties", None)
        out["$comment"] = LEFT_OUT + ", ".join(left_out)
    return out


def _union(kinds: list[dict[str, Any]]) -> dict[str, Any] | None:
    """One object with the properties of every kind of a tagged union (the tag's enum holds every tag).

    A property that two kinds describe differently (but for their enums and
    defaults), or that one of them leaves out, is left out.
    """
    if not kinds or any(k["type"] != "object" for k in kinds):
        return None
    left_out = list(dict.fromkeys(name for kind in kinds for name in undescribed(kind)))
    properties: dict[str, Any] = {}
    for kind in kinds:
        for name, field in kind["properties"].items():
            if name in left_out:
                continue
            merged = _same_field(properties[name], field) if name in properties else field
            if merged is None:
                del properties[name]
                left_out.append(name)
            else:
                properties[name] = merged
    titles = [str(k.get("title", "?")) for k in kinds]
    out: dict[str, Any] = {
        "title": " | ".join(titles),
        "description": f"one of {', '.join(titles)}, told apart by their tag: the properties of each",
        "type": "object", "properties": {},
        "required": [n for n in kinds[0].get("required", []) if all(n in k.get("required", []) for k in kinds)],
    }
    if all(k.get("additionalProperties") is False for k in kinds):
        out["additionalProperties"] = False
    return _with_properties(out, properties, left_out)


def _same_field(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any] | None:
    """One schema for a property two kinds share: enums joined, defaults dropped if they differ; else None."""
    if a == b:
        return a
    a, b = ({k: v for k, v in s.items() if k != "default"} for s in (a, b))
    if {k: v for k, v in a.items() if k != "enum"} != {k: v for k, v in b.items() if k != "enum"}:
        return None
    if "enum" in a and "enum" in b:
        return {**a, "enum": list(dict.fromkeys(a["enum"] + b["enum"]))}
    return a if a == b else None
