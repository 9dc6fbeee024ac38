"""Messages, key registry, configuration."""

import json

import msgspec
import pytest

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile, load_profile
from nwr.common.errors import ConfigError, DecodeError
from nwr.common.launch import load_script

TR = m.Trace(3, 100)


def test_command_union_round_trip():
    c = keys.codec("robot/command/cartesian")
    for msg in (m.PositionCommand(seq=1, stamp_ns=2, owner="p", q=[0.1, 0.2], trace=TR, reflex_seq=4,
                                  phase="RETURNING"),
                m.VelocityCommand(seq=1, stamp_ns=2, owner="p", dq=[0.1], trace=TR)):
        assert c.decode(c.encode(msg)) == msg


def test_strict_decoding_rejects_garbage_and_wrong_types():
    c = keys.codec("robot/command/cartesian")
    with pytest.raises(DecodeError, match="robot/command"):
        c.decode(b"\x00\x01garbage")
    wrong = msgspec.msgpack.encode({"kind": "position", "seq": 1, "stamp_ns": 2, "owner": "p", "q": ["x"],
                                    "trace": {"seq": 1, "stamp_ns": 2}})
    with pytest.raises(DecodeError):
        c.decode(wrong)
    unknown_kind = msgspec.msgpack.encode({"kind": "torque", "seq": 1})
    with pytest.raises(DecodeError):
        c.decode(unknown_kind)
    state = m.RobotState(seq=0, stamp_ns=0, q=[], dq=[], status="ok", owner="p", backend="sim")
    with pytest.raises(DecodeError):  # a state where a command is expected
        c.decode(keys.codec("robot/state").encode(state))


def test_registry_patterns():
    assert keys.topic_for("reflex/cartesian/status").type is m.PlannerStatus
    assert keys.topic_for("diag/gain").type is m.Diagnostic
    with pytest.raises(DecodeError):
        keys.topic_for("reflex/a/b/status")
    with pytest.raises(DecodeError):
        keys.topic_for("nothing/here")
    assert keys.key("arm2", keys.SKIN_PAIN) == "nwr/arm2/skin/pain"
    assert keys.relative_key("ur10e", "nwr/ur10e/skin/pain") == "skin/pain"


@pytest.mark.parametrize("topic", keys.TOPICS, ids=lambda t: t.pattern)
def test_json_schemas_are_objects(topic):
    schema = m.json_schema(topic.type)
    assert schema["type"] == "object"
    json.dumps(schema)


def test_default_profile_is_the_struct_default():
    from nwr.services import profile as services_profile

    assert services_profile.load_profile("default") == services_profile.resolve(Profile())
    # it spells out every plug-in's table that has settings (a backend without settings has none)
    spelled = load_profile("default")
    for kind in services_profile.kinds():
        with_settings = {n for n in kind.names() if kind.settings_class(n).__struct_fields__}
        assert set(getattr(spelled, kind.section).plugins) == with_settings, kind.section


def test_profile_errors_are_helpful(tmp_path):
    with pytest.raises(ConfigError, match="no profile 'nope'"):
        load_profile("nope")
    with pytest.raises(ConfigError, match="does not exist"):
        load_profile(str(tmp_path / "missing.toml"))
    bad = tmp_path / "bad.toml"
    bad.write_text("[gain]\nk = -1\n")
    with pytest.raises(ConfigError, match=r"gain.k"):
        load_profile(str(bad))
    bad.write_text("[gain]\nkk = 3\n")
    with pytest.raises(ConfigError, match="kk"):
        load_profile(str(bad))
    bad.write_text("[gain]\nthresholds_hpa = [2, 6, 5, 20]\n")
    with pytest.raises(ConfigError, match="increasing"):
        load_profile(str(bad))
    bad.write_text("not toml [")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_profile(str(bad))


def test_demo_script_loads():
    script = load_script("demo")
    assert script.duration_s == pytest.approx(30.0)
    assert len(script.touch) >= 6


# --------------------------------------------------------------------------- pacing: sleeping through cycles


def test_rate_take_steps_each_cycle_once_whoever_takes_it():
    from nwr.common.pacing import Rate

    rate = Rate(500, "loop")
    p = rate.period_ns
    rate.restart(0)
    assert rate.take(p - 1) == 0  # nothing due before the first deadline
    assert rate.take(5 * p + p // 2, limit=3) == 3  # an event takes what it may (deadlines 1-3) ...
    assert rate.take(5 * p + p // 2, limit=10) == 2  # ... the loop the rest (4-5), none twice
    assert rate.take(5 * p + p // 2) == 0
    assert rate.ticks == 5 and rate.overruns == 0
    assert rate.take(10 * p) == 5  # slept through 5 cycles: taken at once, on time
    assert rate.overruns == 0
    # A late loop: the cycles beyond what it takes are dropped, and that is an overrun.
    assert rate.take(14 * p, limit=1) == 1 and rate.skip(14 * p) == 3
    assert rate.overruns == 1 and rate.ticks == 11
    assert rate.take(15 * p) == 1
    assert "12 ticks at 500 Hz, period p50 2.000 ms" in rate.summary()


def test_overruns_while_starting_are_counted_apart_and_not_warned_about(caplog):
    """The pipeline's processes start one after the other and load the machine meanwhile: a loop late then
    printed 'overran' warnings at every start. Once the service's inputs flow, an overrun is a warning again."""
    import logging

    from nwr.common.pacing import Rate

    rate = Rate(500, "planner", starting=True)
    p = rate.period_ns
    t0 = 10**10
    rate.restart(t0)
    assert rate.take(t0 + p) == 1
    with caplog.at_level(logging.WARNING, logger="nwr.common.pacing"):
        assert rate.skip(t0 + 10 * p) == 9
        assert not caplog.records and rate.overruns == 1 and rate.start_overruns == 1
        rate.starting = False
        assert rate.skip(t0 + 10 * p + 10**10) > 0  # 10 s later (the warnings are at most one per 5 s)
    assert [r.getMessage() for r in caplog.records] == ["planner loop overran by 10000.0 ms (1 overruns so far)"]
    assert rate.summary().endswith("2 overruns (1 while starting)")


def test_rate_wait_sleeps_through_cycles_until_woken():
    import threading
    import time

    from nwr.common.pacing import Rate

    rate = Rate(100, "loop")  # 10 ms
    rate.restart(time.monotonic_ns())
    wake = threading.Event()
    t0 = time.monotonic()
    assert rate.wait(None, through=4, wake=wake)  # five deadlines: 50 ms
    assert time.monotonic() - t0 >= 0.049
    assert rate.take(time.monotonic_ns(), limit=5) == 5
    threading.Timer(0.01, wake.set).start()
    t0 = time.monotonic()
    assert rate.wait(None, through=50, wake=wake)  # woken after ~10 ms, not 0.5 s
    assert time.monotonic() - t0 < 0.4 and not wake.is_set()
    stop = threading.Event()
    stop.set()
    assert not rate.wait(stop)


def test_an_owner_token_names_its_service_pipeline_host_pid_and_start() -> None:
    from nwr.common import keys

    token = keys.owner("planner-cart", "lab pc/1", "host.local", 42, 1_795_000_000)
    assert token == "owner/planner-cart/lab_pc_1/host.local/42/1795000000"
    owner = keys.parse_owner(token)
    assert owner == keys.Owner("planner-cart", "lab_pc_1", "host.local", 42, 1_795_000_000)
    assert "pipeline lab_pc_1, host host.local, pid 42" in owner.describe()
    assert keys.parse_owner(keys.owner("bridge", "", "h", 1, 2)).instance == keys.NO_INSTANCE
    assert "started alone" in keys.Owner("bridge", keys.NO_INSTANCE, "h", 1, 2).describe()
    for bad in ("alive/bridge", "owner/bridge/x/h/pid/2", "owner/bridge/x/h/1"):
        assert keys.parse_owner(bad) is None


def test_a_plugin_kind_lists_its_package_and_says_what_a_module_lacks(tmp_path, monkeypatch) -> None:
    from nwr.common.errors import ConfigError
    from nwr.common.plugins import Kind

    package = tmp_path / "nwr_test_arms"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "good.py").write_text("NAME = 'good'\nREAL_ARM = False\ndef make(): return 1\n")
    (package / "bad.py").write_text("NAME = 'bad'\nREAL_ARM = 'no'\n")
    (package / "_helper.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    kind = Kind("nwr_test_arms", [str(package)], "bridge.backend", "backend", {"REAL_ARM": "bool", "make": "callable"})
    assert kind.names() == ["bad", "good"]
    assert kind.get("good").make() == 1
    with pytest.raises(ConfigError, match=r"bad.py is no backend: it lacks REAL_ARM \(bool\), make \(callable\)"):
        kind.get("bad")
    with pytest.raises(ConfigError, match="bridge.backend = 'other' is no backend; there are: bad, good"):
        kind.get("other")
