"""Hostile input: every decoder of the key registry either returns a valid message or raises DecodeError."""

from __future__ import annotations

import math
import typing

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.errors import DecodeError

RELATIVE = [t.pattern.replace("*", "fuzz") for t in keys.TOPICS]
FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20), st.binary(max_size=20),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=8), st.dictionaries(st.text(max_size=12), inner, max_size=8)),
    max_leaves=30,
)

# Valid examples of every message, to mutate one field at a time.
TR = m.Trace(1, 2)
CONTACT = m.Contact(pad=1, name="p", region="forearm", change_hpa=3.0, level=2, gain=0.4)
EXAMPLES = {
    "skin/pressure": m.SkinPressure(seq=0, stamp_ns=1, absolute_hpa=[1.0], baseline_hpa=[1.0], change_hpa=[0.0],
                                    contact=[False]),
    "skin/touch": m.SkinTouch(seq=0, stamp_ns=1, pad=2, name="p", origin_ns=0, start_s=1.0, duration_s=0.3,
                              peak_hpa=9.0, shape="step", ramp_s=0.3, contact_point=[0.1, 0.2, 0.3],
                              normal=[0.0, 0.0, 1.0], q=[0.0] * 6),
    "skin/pain": m.SkinPain(seq=0, stamp_ns=1, trace=TR, model="continuous", level=[1], gain=[0.0], strongest=CONTACT),
    "world/skin": m.WorldSkin(seq=0, stamp_ns=1, world_ns=40, absolute_hpa=[1013.0], change_hpa=[0.0], force_n=[0.0]),
    "world/contacts": m.WorldContacts(seq=0, stamp_ns=1, world_ns=40, people=[m.WorldPerson(
        name="touch-0", kind="finger", touch=0, pads=[2], force_n=1.0, peak_force_n=2.0, pressure_n_cm2=0.5,
        peak_pressure_n_cm2=1.0, energy_j=0.0, pushed_m=0.001, peak_pushed_m=0.002)]),
    "robot/command/fuzz": m.PositionCommand(seq=0, stamp_ns=1, owner="cartesian", q=[0.0] * 6, trace=TR),
    "robot/state": m.RobotState(seq=0, stamp_ns=1, q=[0.0] * 6, dq=[0.0] * 6, status="ok", owner="c", backend="sim"),
    "reflex/fuzz/status": m.PlannerStatus(seq=0, stamp_ns=1, name="c", strategy="cartesian", mode="TASK",
                                          task_time_s=0.0),
    "reflex/fuzz/decision": m.PlannerDecision(seq=0, stamp_ns=1, name="c", trace=TR, pain_seq=0, pain_stamp_ns=1),
    "diag/fuzz": m.Diagnostic(seq=0, stamp_ns=1, service="s", level="info", code="c", message="m"),
    "journal/fuzz": m.Journal(seq=0, stamp_ns=1, service="s", run_ns=1, config="{}", entries=[
        m.JournalEntry("pain", [1, 2, 3], "skin/pain", 4, 5, 6), m.JournalEntry("token", [7], arg=1, text="p")]),
    "control/active": m.SwitchRequest(seq=0, stamp_ns=1, name="location", requested_by="fuzz"),
    "control/safety": m.SafetyModeRequest(seq=0, stamp_ns=1, mode="reduced", requested_by="fuzz"),
}


def types_of(topic_type: object) -> tuple[type, ...]:
    args = typing.get_args(topic_type)
    return tuple(args) if args else (topic_type,)  # type: ignore[return-value]


def decode_or_decode_error(relative: str, payload: bytes) -> None:
    codec = keys.codec(relative)
    try:
        message = codec.decode(payload)
    except DecodeError:
        return
    assert isinstance(message, types_of(codec.topic.type))
    # Whatever decodes is fully valid: every number finite, and it round-trips.
    assert all(math.isfinite(v) for v in _floats(msgspec.to_builtins(message)))
    assert codec.decode(codec.encode(message)) == message


def _floats(value: object) -> list[float]:
    if isinstance(value, float):
        return [value]
    if isinstance(value, dict):
        return [f for v in value.values() for f in _floats(v)]
    if isinstance(value, list):
        return [f for v in value for f in _floats(v)]
    return []


def test_every_topic_is_covered():
    assert sorted(EXAMPLES) == sorted(RELATIVE)


@pytest.mark.parametrize("relative", RELATIVE)
@FUZZ
@given(payload=st.binary(max_size=300))
def test_random_bytes(relative, payload):
    decode_or_decode_error(relative, payload)


@pytest.mark.parametrize("relative", RELATIVE)
@FUZZ
@given(value=values)
def test_random_msgpack_of_any_shape(relative, value):
    decode_or_decode_error(relative, msgspec.msgpack.encode(value))


@pytest.mark.parametrize("relative", RELATIVE)
@FUZZ
@given(data=st.data())
def test_valid_messages_with_one_field_mutated(relative, data):
    builtins = msgspec.to_builtins(EXAMPLES[relative])
    field = data.draw(st.sampled_from(sorted(builtins)))
    mutated = dict(builtins)
    if data.draw(st.booleans()):
        mutated[field] = data.draw(values)
    else:
        del mutated[field]
    decode_or_decode_error(relative, msgspec.msgpack.encode(mutated))


@pytest.mark.parametrize("relative", RELATIVE)
@FUZZ
@given(data=st.data())
def test_truncated_valid_messages(relative, data):
    payload = msgspec.msgpack.encode(EXAMPLES[relative])
    cut = data.draw(st.integers(min_value=0, max_value=len(payload) - 1))
    decode_or_decode_error(relative, payload[:cut])


@pytest.mark.parametrize("relative", RELATIVE)
def test_valid_examples_decode(relative):
    codec = keys.codec(relative)
    assert codec.decode(codec.encode(EXAMPLES[relative])) == EXAMPLES[relative]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 1e300])
def test_non_finite_numbers_are_decode_errors(bad):
    payload = msgspec.msgpack.encode({**msgspec.to_builtins(EXAMPLES["robot/command/fuzz"]), "q": [bad] * 6})
    with pytest.raises(DecodeError, match="NaN, infinite"):
        keys.codec("robot/command/fuzz").decode(payload)


def test_invalid_utf8_is_a_decode_error():
    # Found by the fuzzing above: msgspec raises UnicodeDecodeError for a
    # string that is not UTF-8.
    with pytest.raises(DecodeError):
        keys.codec("skin/pain").decode(b"\x81\xa2\x00\x80")
