"""Every JSON channel we write loads in Foxglove and Lichtblick, and its schema describes its messages.

Foxglove Studio and Lichtblick read a ``json`` channel's ``jsonschema`` with
one loader, ``parseChannel`` -> ``parseJsonSchema`` of their ``mcap-support``
package; a channel whose schema it rejects is dropped (no raw messages, no
plots). :func:`parse_json_schema` below is a Python port of it, rule for rule
and with its error messages, from Lichtblick's
``packages/mcap-support/src/parseJsonSchema.ts`` and ``parseChannel.ts``
(github.com/lichtblick-suite/lichtblick, main at 9554e1e, March 2025; the
same file as foxglove/studio's before the fork). One rule is stricter than
that version, as Foxglove Studio was before its #7100 (November 2023; e.g.
``@foxglove/studio-base`` 1.48.0, the newest on npm): an object must list its
``properties`` (those versions throw on ``Object.entries(undefined)``; the
later ones read it as an object with no fields, so nothing under it can be
plotted either).

Why a port and not the loader itself: ``@foxglove/mcap-support`` and
``@lichtblick/mcap-support`` were never published to npm (private
workspace packages), nor is ``@lichtblick/suite-base``; ``@foxglove/studio-base``
is, but only as a 36 MB webpack bundle for the browser in which the loader is
an inlined function, not a module node can import, and CI installs only pip
packages (``.ci/run`` -> ``make test``). The port was checked against the
function cut out of that bundle (1.48.0, ``assets/8790.*.js``): same verdict
and message on every schema here and every case of
:func:`test_the_port_rejects_what_the_loader_rejects`.

Then the data: every message of a short lockstep session (plus hand-made
messages that fill what it leaves empty), as the recorder wrote it, as the
export copied it and as the view made it, has only properties its channel's
schema lists, of the listed type, and every property of every schema occurs
in some message.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest
from mcap.reader import make_reader

from nwr.common import keys, recordings
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.launch import Touch, TouchScript
from nwr.common.recordings import McapRecorder, read_recording, schema_for
from nwr.common.robot import RobotModel, load_description
from nwr.services.gateway.stepped import SimulatedSkin
from nwr.services.pipeline.lockstep import Lockstep
from nwr.services.view import core as c
from nwr.services.view.export import export_foxglove
from nwr.services.view.server import STATS_SCHEMA, STATS_TOPIC

ROBOT = keys.DEFAULT_ROBOT
DESC = load_description()
PLANNER = "cartesian"
# The fields json_schema leaves out (it names them in the object's $comment): arrays of arrays, which the
# loader has no type for. A new one must be a decision, not an accident.
UNDESCRIBED = {"nwr.Command": ["ahead"], "nwr.Journal": ["entries"]}


# -- the loader, ported ------------------------------------------------------------------------------------------


class LoaderError(Exception):
    """What parseChannel / parseJsonSchema throws (the app drops the channel)."""


def _js(value: Any) -> str:
    """``JSON.stringify`` as the loader's messages show it (``undefined`` for a missing key)."""
    return "undefined" if value is _MISSING else json.dumps(value, separators=(",", ":"))


_MISSING = object()


def _integer(schema: dict[str, Any]) -> str:
    low = schema.get("minimum", schema.get("exclusiveMinimum"))
    return "uint32" if isinstance(low, int | float) and not isinstance(low, bool) and low >= 0 else "int32"


def parse_json_schema(root: dict[str, Any], root_type_name: str) -> dict[str, list[tuple[str, str, bool]]]:
    """``parseJsonSchema(rootJsonSchema, rootTypeName).datatypes``: type name -> fields (name, type, is array)."""
    datatypes: dict[str, list[tuple[str, str, bool]]] = {}

    def add_fields(schema: dict[str, Any], type_name: str, key_path: list[str]) -> None:
        fields: list[tuple[str, str, bool]] = []
        if schema.get("type", _MISSING) != "object":
            raise LoaderError(f'Expected "type": "object" for schema {type_name}, '
                              f'got {_js(schema.get("type", _MISSING))}')
        if "properties" not in schema:  # Foxglove Studio before #7100: Object.entries(undefined)
            raise LoaderError("TypeError: Cannot convert undefined or null to object")
        for name, field in schema["properties"].items():
            path = ".".join([*key_path, name])
            one_of = field.get("oneOf")
            if isinstance(one_of, list):
                if all(isinstance(a.get("const"), int | float) and not isinstance(a.get("const"), bool)
                       for a in one_of):
                    fields += [(str(a.get("title")), "uint32", False) for a in one_of]
                    fields.append((name, "uint32", False))
                    continue
                raise LoaderError(f"Unsupported type for {path}: oneOf alternatives must have number values")
            kind = field.get("type", _MISSING)
            if kind == "boolean":
                fields.append((name, "bool", False))
            elif kind == "string":
                encoding = field.get("contentEncoding", _MISSING)
                if encoding is _MISSING:
                    fields.append((name, "string", False))
                elif encoding == "base64":
                    fields.append((name, "uint8", True))
                else:
                    raise LoaderError(f"Unsupported contentEncoding {_js(encoding)} in {path}")
            elif kind == "number":
                fields.append((name, "float64", False))
            elif kind == "integer":
                fields.append((name, _integer(field), False))
            elif kind == "object":
                nested = f"{type_name}.{name}"
                add_fields(field, nested, [*key_path, name])
                fields.append((name, nested, False))
            elif kind == "array":
                items = field.get("items", _MISSING)
                if not isinstance(items, dict):
                    raise LoaderError("TypeError: Cannot read properties of undefined (reading 'type')")
                item_kind = items.get("type", _MISSING)
                if item_kind == "boolean":
                    fields.append((name, "bool", True))
                elif item_kind == "string":
                    if "contentEncoding" in items:
                        raise LoaderError(f"Unsupported contentEncoding {_js(items['contentEncoding'])} "
                                          f"for array item {path}")
                    fields.append((name, "string", True))
                elif item_kind == "number":
                    fields.append((name, "float64", True))
                elif item_kind == "integer":
                    fields.append((name, _integer(items), True))
                elif item_kind == "object":
                    nested = f"{type_name}.{name}"
                    add_fields(items, nested, [*key_path, name])
                    fields.append((name, nested, True))
                else:
                    raise LoaderError(f"Unsupported type {_js(item_kind)} for array item {path}")
            else:  # "null", a missing type ($ref, anyOf, an enum without a type), a list of types
                raise LoaderError(f"Unsupported type {_js(kind)} for {path}")
        datatypes[type_name] = fields

    add_fields(root, root_type_name, [])
    return datatypes


def parse_channel(message_encoding: str, schema_name: str, schema_encoding: str,
                  data: bytes) -> dict[str, list[tuple[str, str, bool]]]:
    """``parseChannel`` for a ``json`` channel: its datatypes, or LoaderError."""
    assert message_encoding == "json", message_encoding
    if schema_encoding != "jsonschema":
        raise LoaderError(f"Message encoding json with schema encoding '{schema_encoding}' is not supported "
                          "(expected jsonschema or no schema)")
    if not data:
        return {}
    schema = json.loads(data)
    if not isinstance(schema, dict):
        raise LoaderError(f"Invalid schema, expected JSON object, got {type(schema).__name__}")
    return parse_json_schema(schema, schema_name)


def resolve(datatypes: dict[str, list[tuple[str, str, bool]]], root: str, path: list[str]) -> str:
    """The type a message path (``.a.b``, no indexing) resolves to in the datatypes, as a panel resolves it."""
    type_name = root
    for name in path:
        found = [f for f in datatypes.get(type_name, []) if f[0] == name]
        assert found, f"{root}.{'.'.join(path)}: {type_name} has no field {name!r}"
        type_name = found[0][1]
    return type_name


# -- the data ----------------------------------------------------------------------------------------------------


class Fit:
    """Checks messages against their schema (only listed properties, of the listed type) and collects which
    properties occurred, so that a schema with a property no message has shows too."""

    def __init__(self) -> None:
        self.seen: dict[str, set[str]] = {}

    def check(self, schema_name: str, schema: dict[str, Any], message: Any, *, nullable: bool) -> None:
        seen = self.seen.setdefault(schema_name, set())
        self._value(schema, message, schema_name, seen, nullable)

    def _value(self, schema: dict[str, Any], value: Any, path: str, seen: set[str], nullable: bool) -> None:
        kind = schema["type"]
        if kind == "object":
            assert isinstance(value, dict), f"{path}: {value!r} is no object"
            properties = schema["properties"]
            left_out = m.undescribed(schema)
            assert not (left_out and schema.get("additionalProperties") is False), path
            assert set(schema.get("required", [])) <= set(value), f"{path}: a required property is missing"
            for name, item in value.items():
                where = f"{path}.{name}"
                if name in left_out:  # left out because the loader has no type for it: an array of arrays
                    assert isinstance(item, list) and all(isinstance(x, list) for x in item), where
                    seen.add(where)
                    continue
                assert name in properties, f"{where} is written but not in the schema"
                if item is None:
                    # An optional field (the typed decoder proves it may be null); the apps read it as absent.
                    assert nullable, f"{where} is null"
                    continue
                seen.add(where)
                self._value(properties[name], item, where, seen, nullable)
        elif kind == "array":
            assert isinstance(value, list), f"{path}: {value!r} is no array"
            for item in value:
                seen.add(f"{path}[]")
                self._value(schema["items"], item, f"{path}[]", seen, nullable)
        elif kind == "boolean":
            assert isinstance(value, bool), f"{path}: {value!r} is no boolean"
        elif kind == "string":
            assert isinstance(value, str), f"{path}: {value!r} is no string"
            assert "enum" not in schema or value in schema["enum"], f"{path}: {value!r} not in {schema['enum']}"
        else:
            types: tuple[type, ...] = (int,) if kind == "integer" else (int, float)
            assert isinstance(value, types) and not isinstance(value, bool), f"{path}: {value!r} is no {kind}"
            assert schema.get("minimum", value) <= value <= schema.get("maximum", value), path

    def assert_all_seen(self, schema_name: str, schema: dict[str, Any]) -> None:
        missing = sorted(set(property_paths(schema, schema_name)) - self.seen.get(schema_name, set()))
        assert not missing, f"{schema_name}: no message has {missing}"


def property_paths(schema: dict[str, Any], path: str) -> Iterator[str]:
    if schema["type"] == "object":
        for name, item in schema["properties"].items():
            yield f"{path}.{name}"
            yield from property_paths(item, f"{path}.{name}")
    elif schema["type"] == "array":
        yield f"{path}[]"
        yield from property_paths(schema["items"], f"{path}[]")


def relative(pattern: str) -> str:
    return pattern.replace("*", PLANNER)


TRACE = m.Trace(seq=3, stamp_ns=1_000)
# A taxel skin's contact: every optional field of a Contact filled (a pad's leaves them at their defaults).
CONTACT = m.Contact(pad=4, name="forearm_top", region="forearm", change_hpa=9.0, level=3, gain=0.185,
                    link="forearm_link", point=[-0.2, 0.05, 0.04], normal=[0.0, 1.0, 0.0], force_n=3.1)


def hand_made(stamp_ns: int) -> list[tuple[str, Any]]:
    """A message of each kind with every optional part filled (what a short session may leave empty)."""
    q = [0.1, -1.2, 1.3, -1.6, -1.5, 0.0]
    retreat = m.Retreat(sample_dt_s=0.01, normal_speed_m_s=[-0.1, -0.2], toward_m=0.0, withdrawal_m=0.05,
                        approach_m=[0.0] * 10, worst_pad=2, worst_approach_m=0.0, approached=False, corrected=False,
                        contacts=[3], contacts_toward_m=[0.0])  # a second touched pad's
    reflex = m.ReflexInfo(reflex_seq=1, strategy="uniform", contact=CONTACT, trace=TRACE, started_ns=stamp_ns,
                          duration_s=0.5, direction=[0.0, 0.0, 0.1], target=q, retreat=retreat)
    return [
        (keys.SKIN_TOUCH, m.SkinTouch(seq=0, stamp_ns=stamp_ns, pad=4, name="forearm_top", origin_ns=0, start_s=1.0,
                                      duration_s=0.4, peak_hpa=9.0, shape="ramp", ramp_s=0.2,
                                      contact_point=[0.5, 0.1, 0.6], normal=[0.0, 0.0, 1.0], q=q,
                                      pose_stamp_ns=stamp_ns, closed_loop=True, depth_m=0.01)),
        (keys.SKIN_PAIN, m.SkinPain(seq=0, stamp_ns=stamp_ns, trace=TRACE, model="effective-mass", level=[1, 3],
                                    gain=[0.0, 0.185], strongest=CONTACT, effective_mass_kg=[12.5, 3.1],
                                    impact_n=[0.0, 88.1], threshold_scale=[1.0, 0.874], impact_basis="state",
                                    torque_pads=[1], light_touch=[0])),
        (keys.robot_command(PLANNER), m.PositionCommand(seq=0, stamp_ns=stamp_ns, owner=PLANNER, q=q, trace=TRACE,
                                                        ahead=[q, q], period_s=0.002)),
        (keys.robot_command(PLANNER), m.VelocityCommand(seq=1, stamp_ns=stamp_ns, owner=PLANNER, dq=[0.0] * 6,
                                                        trace=TRACE, reflex_seq=1)),
        (keys.ROBOT_STATE, m.RobotState(
            seq=0, stamp_ns=stamp_ns, q=q, dq=[0.0] * 6, status="ok", owner=PLANNER, backend="sim",
            command_mode="velocity", reflex_seq=1, accepted=TRACE, accepted_ns=stamp_ns, stopping=True,
            stop_distance=[0.01] * 6, stop_time_s=0.1, pending_owner="uniform",
            handover=m.Handover(previous="uniform", owner=PLANNER, requested_ns=1, switched_ns=2, first_command_ns=3),
            safety_mode="reduced", limited=2, phase="REFLEX", tau_ext=[0.5] * 6)),
        (keys.planner_status(PLANNER), m.PlannerStatus(seq=0, stamp_ns=stamp_ns, name=PLANNER, strategy="uniform",
                                                       mode="REFLEX", task_time_s=1.5, saved_pose=q, reflex=reflex,
                                                       target_pad=4)),
        (keys.planner_decision(PLANNER), m.PlannerDecision(seq=0, stamp_ns=stamp_ns, name=PLANNER, trace=TRACE,
                                                           pain_seq=3, pain_stamp_ns=1_100, received_ns=1_200,
                                                           reflex_seq=1)),
        (keys.CONTROL_ACTIVE, m.SwitchRequest(seq=0, stamp_ns=stamp_ns, name=PLANNER, requested_by="operator")),
        (keys.WORLD_SKIN, m.WorldSkin(seq=0, stamp_ns=stamp_ns, world_ns=40_000_000, absolute_hpa=[1013.0] * 10,
                                      change_hpa=[0.0] * 9 + [9.0], force_n=[0.0] * 9 + [11.3])),
        (keys.WORLD_SKIN, m.WorldSkin(seq=1, stamp_ns=stamp_ns, world_ns=41_000_000, absolute_hpa=[], change_hpa=[],
                                      force_n=[], taxels=[0.01] * 299 + [5.2])),  # a taxel skin's
        (keys.WORLD_CONTACTS, m.WorldContacts(seq=0, stamp_ns=stamp_ns, world_ns=40_000_000, people=[m.WorldPerson(
            name="touch-0", kind="finger", touch=0, pads=[9], force_n=11.3, peak_force_n=12.0, pressure_n_cm2=20.0,
            peak_pressure_n_cm2=25.0, energy_j=0.01, pushed_m=0.002, peak_pushed_m=0.004)])),
        (keys.CONTROL_SAFETY, m.SafetyModeRequest(seq=0, stamp_ns=stamp_ns, mode="reduced", requested_by="operator")),
        (keys.diag("gain"), m.Diagnostic(seq=0, stamp_ns=stamp_ns, service="gain", level="warning",
                                         code="decode_error", message="dropped a malformed sample")),
        (keys.journal("gain"), m.Journal(seq=0, stamp_ns=stamp_ns, service="gain", run_ns=1, config="{}",
                                         entries=[m.JournalEntry("pain", now=[1, 2], key="skin/pressure", seq=3,
                                                                 data=[1.0])], final=True)),
    ]


@pytest.fixture(scope="module")
def session() -> list[tuple[str, Any, int]]:
    """A 2 s lockstep session with one touch (every key the pipeline writes), then the hand-made messages."""
    profile = Profile()
    script = TouchScript(duration_s=1.5, touch=[Touch(pad="forearm_top", start_s=0.5, duration_s=0.4,
                                                      peak_hpa=9.0)])
    out: list[tuple[str, Any, int]] = []
    Lockstep(profile, strategy=PLANNER).run(SimulatedSkin(profile, script, RobotModel(DESC)),
                                            lambda key, message, t: out.append((key, message, t)), settle_s=0.5)
    end = max(t for _k, _m, t in out)
    out += [(key, message, end + 1 + i) for i, (key, message) in enumerate(hand_made(end + 1))]
    return out


@pytest.fixture(scope="module")
def recording(session: list[tuple[str, Any, int]], tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("schemas") / "session.mcap"
    with path.open("wb") as f:
        recorder = McapRecorder(f, ROBOT)
        recorder.metadata(recordings.SESSION_METADATA, {"robot": ROBOT})
        for key, message, t in sorted(session, key=lambda x: x[2]):
            recorder.write(keys.key(ROBOT, key), message, t)
        recorder.finish()
    return path


@pytest.fixture(scope="module")
def exported(recording: Path) -> Path:
    path = recording.with_name("session-foxglove.mcap")
    export_foxglove(recording, path)
    return path


def check_file(path: Path, fit: Fit) -> dict[str, dict[str, Any]]:
    """Every JSON channel of a file loads, every message fits its schema; the schemas by name."""
    schemas: dict[str, dict[str, Any]] = {}
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        for channel in summary.channels.values():
            if channel.message_encoding != "json":
                continue
            schema = summary.schemas[channel.schema_id]
            parse_channel(channel.message_encoding, schema.name, schema.encoding, schema.data)
            schemas[schema.name] = json.loads(schema.data)
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "json":
                assert schema is not None
                pipeline = channel.topic.startswith(keys.prefix(ROBOT) + "/")
                fit.check(schema.name, json.loads(schema.data), json.loads(message.data), nullable=pipeline)
    return schemas


# -- tests -------------------------------------------------------------------------------------------------------


def _obj(**properties: Any) -> dict[str, Any]:
    return {"type": "object", "properties": properties}


@pytest.mark.parametrize(("schema", "error"), [
    ({"type": "object", "properties": {"mode": {"enum": ["TASK", "REFLEX"]}}}, 'Unsupported type undefined for mode'),
    (_obj(trace={"$ref": "#/$defs/Trace"}), "Unsupported type undefined for trace"),
    (_obj(reflex={"anyOf": [{"type": "object", "properties": {}}, {"type": "null"}]}),
     "Unsupported type undefined for reflex"),
    (_obj(q={"type": ["array", "null"], "items": {"type": "number"}}), 'Unsupported type ["array","null"] for q'),
    ({"anyOf": [{"$ref": "#/$defs/A"}, {"$ref": "#/$defs/B"}]},
     'Expected "type": "object" for schema t, got undefined'),
    ({"type": "object", "anyOf": [{"$ref": "#/$defs/A"}]}, "Cannot convert undefined or null to object"),
    (_obj(gain={"type": "object", "additionalProperties": {"type": "number"}}),
     "Cannot convert undefined or null to object"),
    (_obj(ahead={"type": "array", "items": {"type": "array", "items": {"type": "number"}}}),
     'Unsupported type "array" for array item ahead'),
    (_obj(entries={"type": "array", "items": {"type": "array", "prefixItems": [{"type": "string"}]}}),
     'Unsupported type "array" for array item entries'),
    (_obj(entries={"type": "array", "prefixItems": [{"type": "string"}]}), "reading 'type'"),
    (_obj(a=_obj(b={"type": "null"})), 'Unsupported type "null" for a.b'),
    (_obj(level={"oneOf": [{"const": "low"}, {"const": "high"}]}), "oneOf alternatives must have number values"),
])
def test_the_port_rejects_what_the_loader_rejects(schema: dict[str, Any], error: str) -> None:
    with pytest.raises(LoaderError, match=re.escape(error)):
        parse_json_schema(schema, "t")


def test_the_port_reads_what_the_loader_reads() -> None:
    schema = _obj(flag={"type": "boolean"}, name={"type": "string", "enum": ["a"]}, x={"type": "number"},
                  n={"type": "integer"}, u={"type": "integer", "minimum": 0},
                  q={"type": "array", "items": {"type": "number"}}, pads=_obj(wrist_1={"type": "number"}),
                  contacts={"type": "array", "items": _obj(pad={"type": "integer"})},
                  level={"oneOf": [{"title": "LOW", "const": 1}]}, empty={"type": "object", "properties": {}})
    datatypes = parse_json_schema(schema, "t")
    assert datatypes["t"] == [("flag", "bool", False), ("name", "string", False), ("x", "float64", False),
                              ("n", "int32", False), ("u", "uint32", False), ("q", "float64", True),
                              ("pads", "t.pads", False), ("contacts", "t.contacts", True), ("LOW", "uint32", False),
                              ("level", "uint32", False), ("empty", "t.empty", False)]
    assert datatypes["t.pads"] == [("wrist_1", "float64", False)] and datatypes["t.empty"] == []
    with pytest.raises(LoaderError, match="expected jsonschema"):
        parse_channel("json", "t", "protobuf", b"{}")


@pytest.mark.parametrize("topic", keys.TOPICS, ids=lambda t: t.pattern)
def test_every_recording_channel_loads(topic: keys.Topic) -> None:
    name, data = schema_for(relative(topic.pattern))
    datatypes = parse_channel("json", name, "jsonschema", data)
    schema = json.loads(data)
    assert "$defs" not in data.decode() and "$ref" not in data.decode() and "anyOf" not in data.decode()
    assert [f[0] for f in datatypes[name]] == list(schema["properties"])
    assert ("kind", "string", False) in datatypes[name]  # the tag: a typed enum


def test_schemas_leave_out_only_what_the_loader_has_no_type_for() -> None:
    def left_out(schema: dict[str, Any]) -> list[str]:
        inner = [*schema.get("properties", {}).values(), *([schema["items"]] if "items" in schema else [])]
        return m.undescribed(schema) + [name for item in inner for name in left_out(item)]

    found = {}
    for topic in keys.TOPICS:
        name, data = schema_for(relative(topic.pattern))
        if names := left_out(json.loads(data)):
            found[name] = names
    assert found == UNDESCRIBED


def test_a_union_of_messages_is_one_object_with_every_kinds_properties() -> None:
    schema = m.json_schema(m.PositionCommand | m.VelocityCommand)
    assert schema["properties"]["kind"] == {"type": "string", "enum": ["position", "velocity"]}
    assert {"q", "dq", "period_s", "trace"} <= set(schema["properties"])
    # The kinds' defaults differ ("TASK", "REFLEX"): none is kept.
    assert schema["properties"]["phase"] == {"type": "string", "enum": sorted(m.MODES)}
    assert schema["required"] == ["kind", "seq", "stamp_ns", "owner", "trace"]  # what both kinds require
    # Every message of either kind decodes as before: only the schema changed.
    for message in (m.PositionCommand(seq=0, stamp_ns=0, owner="a", q=[0.0], trace=m.NO_TRACE),
                    m.VelocityCommand(seq=0, stamp_ns=0, owner="a", dq=[0.0], trace=m.NO_TRACE)):
        data = msgspec.json.encode(message)
        assert msgspec.json.decode(data, type=m.PositionCommand | m.VelocityCommand) == message
        Fit().check("nwr.Command", schema, json.loads(data), nullable=True)


def test_the_recorded_messages_fit_their_schemas_and_still_decode(
        recording: Path, session: list[tuple[str, Any, int]]) -> None:
    fit = Fit()
    schemas = check_file(recording, fit)
    assert set(schemas) == {schema_for(relative(t.pattern))[0] for t in keys.TOPICS}  # every key was written
    for name, schema in schemas.items():
        fit.assert_all_seen(name, schema)
    records, _ = read_recording(recording)  # strictly, into each key's type
    encode = msgspec.json.encode
    assert sorted((r.key, r.log_time_ns, encode(r.message)) for r in records) == \
        sorted((key, t, encode(message)) for key, message, t in session)


def test_every_export_channel_loads_and_its_messages_fit(exported: Path, recording: Path) -> None:
    fit = Fit()
    schemas = check_file(exported, fit)
    view = {s.schema_name: s for s in c.channel_specs([p.name for p in DESC.pads]) if s.message_encoding == "json"}
    assert set(view) <= set(schemas) and len(schemas) == len(view) + len(keys.TOPICS)
    for name, schema in schemas.items():
        if name != "std_msgs/String":
            fit.assert_all_seen(name, schema)
    again, _ = read_recording(exported)
    assert len(again) == len(read_recording(recording)[0])


def test_an_older_recordings_export_gets_schemas_that_load(
        tmp_path: Path, session: list[tuple[str, Any, int]], monkeypatch: pytest.MonkeyPatch) -> None:
    """A recording made before the schemas took the loader's form (msgspec's own, with $ref, anyOf and enums
    without a type): the export gives its channels the current schemas, and those fit its messages."""
    def msgspec_schema(relative_key: str) -> tuple[str, bytes]:
        name, _ = schema_for(relative_key)
        return name, json.dumps(msgspec.json.schema(keys.topic_for(relative_key).type)).encode()

    old = tmp_path / "old.mcap"
    with monkeypatch.context() as patch:
        patch.setattr(recordings, "schema_for", msgspec_schema)
        with old.open("wb") as f:
            recorder = McapRecorder(f, ROBOT)
            for key, message, t in sorted(session, key=lambda x: x[2]):
                recorder.write(keys.key(ROBOT, key), message, t)
            recorder.finish()
    with old.open("rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        for schema in summary.schemas.values():
            with pytest.raises(LoaderError):
                parse_channel("json", schema.name, schema.encoding, schema.data)
    export_foxglove(old, tmp_path / "old-foxglove.mcap")
    fit = Fit()
    check_file(tmp_path / "old-foxglove.mcap", fit)
    assert fit.seen


def test_every_live_view_channel_loads_and_its_messages_fit(session: list[tuple[str, Any, int]]) -> None:
    core = c.ViewCore(DESC, RobotModel(DESC))
    json_channels = [s for s in core.channels if s.message_encoding == "json"]
    assert {s.topic for s in json_channels} == {"/robot_description", "/nwr/skin", "/nwr/planner", "/nwr/robot",
                                                "/nwr/onset"}
    for spec in json_channels:
        parse_channel(spec.message_encoding, spec.schema_name, spec.schema_encoding, spec.schema)
    parse_channel("json", "nwr.view.Stats", "jsonschema", json.dumps(STATS_SCHEMA).encode())  # STATS_TOPIC
    assert STATS_TOPIC not in c.VIEW_TOPICS
    # What the live view serves: the newest messages, a frame at a time (the same bytes as the export's).
    fit = Fit()
    schemas = {s.topic: (s.schema_name, json.loads(s.schema)) for s in json_channels}
    outputs = [core.description(0)]
    for i, (_key, message, t) in enumerate(sorted(session, key=lambda x: x[2])):
        core.apply(message)
        if i % 10 == 0:
            outputs += c.encode_frame(core.frame(t))
    for output in outputs:
        if output.topic in schemas:
            name, schema = schemas[output.topic]
            fit.check(name, schema, json.loads(output.data), nullable=False)
    for name, schema in schemas.values():
        if name != "std_msgs/String":
            fit.assert_all_seen(name, schema)


def test_the_layouts_plots_address_fields_the_loader_reads() -> None:
    layout = json.loads((Path(__file__).parents[1] / "deploy" / "foxglove" / "nwr-layout.json").read_text())
    specs = {s.topic: s for s in c.channel_specs([p.name for p in DESC.pads])}
    paths = [p["value"] for config in layout["configById"].values() for p in config.get("paths", [])]
    assert any(p.startswith("/nwr/skin.change_hpa.") for p in paths)
    for path in paths:
        topic, *fields = path.split(".")
        spec = specs[topic]
        datatypes = parse_channel(spec.message_encoding, spec.schema_name, spec.schema_encoding, spec.schema)
        assert resolve(datatypes, spec.schema_name, fields) in ("float64", "int32", "uint32", "string", "bool"), path
