"""nwr status and nwr router: the pure report, the environment overrides, and a real router on loopback."""

from __future__ import annotations

import threading

import msgspec
import pytest
import zenoh

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import load_profile
from nwr.common.errors import ConfigError
from nwr.common.launch import apply_env_overrides, env_overrides
from nwr.services.tools import router, status

ROBOT = "ur10e"


def state(status_: str = "ok", owner: str = "cartesian") -> m.RobotState:
    return m.RobotState(seq=1, stamp_ns=1, q=[0.0] * 6, dq=[0.0] * 6, status=status_, owner=owner,  # type: ignore[arg-type]
                        backend="sim")


def test_collector_counts_rates_and_keeps_the_latest_state_and_pain() -> None:
    c = status.StatusCollector(ROBOT)
    enc = msgspec.msgpack.encode
    contact = m.Contact(pad=3, name="forearm_top", region="forearm", change_hpa=9.1, level=3, gain=0.18)
    pain = m.SkinPain(seq=1, stamp_ns=1, trace=m.Trace(1, 1), model="continuous", level=[3], gain=[0.18],
                      strongest=contact)
    for i in range(50):
        c.observe(keys.key(ROBOT, "skin/pressure"), b"not decoded", i)
    c.observe(keys.key(ROBOT, "skin/pain"), enc(pain), 2_000_000_000)
    c.observe(keys.key(ROBOT, "robot/state"), enc(state("planner_lost")), 0)
    c.observe(keys.key(ROBOT, "robot/state"), b"\x92garbage", 0)
    c.observe("nwr/other/robot/state", enc(state()), 0)  # another arm's: ignored
    report = c.report(["bridge", "planner-cartesian"], 2.0, 3_000_000_000, ["tcp/router:7447"])
    assert report.rates_hz["skin/pressure"] == 25.0
    assert report.rates_hz["robot/state"] == 1.0
    assert report.undecodable == 1
    assert report.state is not None and report.state.status == "planner_lost"
    assert report.pain is not None and report.pain.contact.name == "forearm_top"
    assert report.active_planner == "cartesian"
    text = status.format_report(report)
    assert "alive (2): bridge, planner-cartesian" in text
    assert "not alive: recorder, gain, gateway" in text  # the graph's services nobody stands for
    assert "planner_lost" in text
    assert "last pain event: forearm_top (forearm) PL 3, gain 0.180, +9.1 hPa, 1.0 s ago" in text
    assert "1 samples did not decode" in text
    c.reset()
    assert c.report([], 1.0, 0, []).rates_hz == {}


def test_messages_of_two_pipeline_instances_are_named() -> None:
    c = status.StatusCollector(ROBOT)
    for instance, n in (("lab.1.100", 30), ("lab.2.200", 4), (keys.NO_INSTANCE, 2)):
        for _ in range(n):
            c.observe(keys.key(ROBOT, "skin/pressure"), b"not decoded", 0, instance)
    text = status.format_report(c.report([], 1.0, 0, []))
    assert "warning: messages of 2 pipeline instances on this robot's keys (lab.1.100: 30, lab.2.200: 4)" in text
    c.reset()
    c.observe(keys.key(ROBOT, "skin/pressure"), b"not decoded", 0, "lab.1.100")
    assert "pipeline instances" not in status.format_report(c.report([], 1.0, 0, []))


def test_report_without_traffic_says_so() -> None:
    text = status.format_report(status.StatusCollector(ROBOT).report([], 2.0, 0, []))
    assert "alive (0): none" in text and "no robot/state" in text and "no message in the window" in text


def test_not_alive_names_the_graphs_services_without_a_process() -> None:
    assert status.not_alive(["recorder", "bridge", "planner-uniform", "gain", "gateway"]) == []
    assert status.not_alive(["recorder", "bridge", "gain", "gateway", "view"]) == ["planner-*"]
    assert "view" not in status.not_alive([])  # read-only: optional


def test_matching_takes_names_and_globs() -> None:
    alive = ["bridge", "planner-cartesian", "planner-uniform"]
    assert status.matching(alive, "bridge") == ["bridge"]
    assert status.matching(alive, "planner-*") == ["planner-cartesian", "planner-uniform"]
    assert status.matching(alive, "planner") == []


def test_env_overrides_router_and_robot() -> None:
    overrides = env_overrides({"NWR_ROUTER": " tcp/10.0.0.2:7447,tcp/10.0.0.3:7447 ", "NWR_ROBOT": "arm2",
                               "NWR_OTHER": "x"})
    assert overrides == {"NWR_ROUTER": "tcp/10.0.0.2:7447,tcp/10.0.0.3:7447", "NWR_ROBOT": "arm2"}
    profile = apply_env_overrides(load_profile(), {**overrides, "NWR_INSECURE": "1"})
    assert profile.zenoh.router == ["tcp/10.0.0.2:7447", "tcp/10.0.0.3:7447"]
    assert profile.robot.name == "arm2"
    assert env_overrides({"NWR_ROUTER": ""}) == {}
    with pytest.raises(ConfigError, match="NWR_ROUTER: '10.0.0.2:7447' is not a Zenoh endpoint"):
        apply_env_overrides(load_profile(), {"NWR_ROUTER": "10.0.0.2:7447"})
    with pytest.raises(ConfigError, match="NWR_ROBOT='UR 10' is not a robot name"):
        apply_env_overrides(load_profile(), {"NWR_ROBOT": "UR 10"})


def test_router_listens_on_loopback_unless_told_and_names_every_interface() -> None:
    assert router.listen_choice(None, {}) == ("tcp/127.0.0.1:7447", "the default, loopback only")
    assert router.listen_choice(None, {"NWR_ROUTER_LISTEN": "tcp/10.0.0.2:7447"}) == (
        "tcp/10.0.0.2:7447", "NWR_ROUTER_LISTEN")
    assert router.listen_choice("tcp/0.0.0.0:7447", {"NWR_ROUTER_LISTEN": "tcp/10.0.0.2:7447"}) == (
        "tcp/0.0.0.0:7447", "--listen")
    assert router.listen_choice(None, {"NWR_ROUTER_LISTEN": ""})[1] == "the default, loopback only"
    listen = ["tcp/127.0.0.1:7447", "tcp/10.0.0.2:7447", "tcp/0.0.0.0:7447", "tls/[::]:7447",
              "tcp/[::1]:7447", "tcp/0.0.0.0:7448#iface=eth0"]
    assert router.wildcard_endpoints(listen) == ["tcp/0.0.0.0:7447", "tls/[::]:7447", "tcp/0.0.0.0:7448#iface=eth0"]


@pytest.mark.e2e
def test_router_status_and_check_on_loopback(capsys: pytest.CaptureFixture[str]) -> None:
    """A real `nwr router`, a client that announces itself and publishes, and `nwr status` through the router."""
    port = 17947
    endpoint = f"tcp/127.0.0.1:{port}"
    stop = threading.Event()
    session = zenoh.open(router.router_config([endpoint], []))
    token = session.liveliness().declare_token(keys.key(ROBOT, keys.alive("router")))
    try:
        profile = apply_env_overrides(load_profile(), {"NWR_ROUTER": endpoint})
        client = zenoh.open(status.zenoh_config(profile.zenoh))
        alive = client.liveliness().declare_token(keys.key(ROBOT, keys.alive("planner-cartesian")))
        pub = client.declare_publisher(keys.key(ROBOT, keys.ROBOT_STATE))

        def publish() -> None:
            while not stop.wait(0.01):
                pub.put(msgspec.msgpack.encode(state()))

        thread = threading.Thread(target=publish, daemon=True)
        thread.start()
        try:
            assert status.check(profile, "planner-*", timeout_s=2.0) == 0
            assert status.check(profile, "router", timeout_s=2.0) == 0
            assert status.check(profile, "bridge", timeout_s=0.5) == 1
            report = status.collect(profile, window_s=1.0, timeout_s=1.0)
        finally:
            stop.set()
            thread.join(2)
            alive.undeclare()
            client.close()
        assert report.alive == ["planner-cartesian", "router"]
        assert 50 < report.rates_hz["robot/state"] < 150  # 100 Hz
        assert report.state is not None and report.active_planner == "cartesian"
        err = capsys.readouterr().err
        assert "bridge is not alive (robot ur10e); alive: planner-cartesian, router" in err
    finally:
        token.undeclare()
        session.close()


def test_reaching_beyond_the_machine_without_tls_needs_nwr_insecure() -> None:
    with pytest.raises(ConfigError, match="tcp/10.0.0.2:7447 reaches beyond this machine without TLS.*NWR_INSECURE=1"):
        apply_env_overrides(load_profile(), {"NWR_ROUTER": "tcp/10.0.0.2:7447"})
    for endpoint in ("tcp/127.0.0.1:7447", "tcp/127.0.1.1:7447", "tcp/[::1]:7447", "tcp/localhost:7447"):
        assert apply_env_overrides(load_profile(), {"NWR_ROUTER": endpoint}).zenoh.router == [endpoint]
    lan = load_profile()
    lan.zenoh.host = "192.168.1.20"  # the embedded mesh on the LAN
    with pytest.raises(ConfigError, match="tcp/192.168.1.20:7450 reaches beyond this machine"):
        apply_env_overrides(lan, {})
    assert not apply_env_overrides(lan, {"NWR_INSECURE": "1"}).zenoh.secure
    secure = apply_env_overrides(load_profile(), {"NWR_ROUTER": "tcp/10.0.0.2:7447", "NWR_TLS_CA": "/c/ca.crt"})
    assert secure.zenoh.secure  # TLS: the secure deployment checks its own files where it connects

