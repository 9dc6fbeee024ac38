"""Which pipeline a message comes from: the instance each put carries, what a consumer takes, which planners a
bridge follows; a restarted service saying so. The live check, with real sessions on loopback, is in
``test_wrong_messages_e2e.py``."""

from __future__ import annotations

import os
import threading
import time

import pytest
import zenoh
from pipeline import free_base_port

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import ZenohSection
from nwr.common.node import RESTART_ENV, RESTARTED_WAIT_S, Node, from_this_pipeline, sender_instance
from nwr.services.bridge.main import PipelinePlanners

MINE, OTHER, ALONE = "lab.1.100", "lab.2.200", keys.NO_INSTANCE


def test_the_sender_instance_is_the_attachment_or_none() -> None:
    assert sender_instance(None) == ALONE
    assert sender_instance(b"lab.1.100") == "lab.1.100"
    assert sender_instance(b"") == ALONE
    assert sender_instance(b"\xff\xfe") == ALONE  # not UTF-8
    assert sender_instance(b"a/b") == ALONE  # no instance could be named so


@pytest.mark.parametrize("relative", ["skin/pressure", "skin/pain", "robot/state", "robot/command/cartesian",
                                      "reflex/uniform/status", "control/active", "diag/gain", "journal/bridge"])
def test_another_pipelines_message_never_feeds_a_launched_one(relative: str) -> None:
    assert from_this_pipeline(MINE, MINE, relative)
    assert not from_this_pipeline(MINE, OTHER, relative)
    assert from_this_pipeline(ALONE, OTHER, relative)  # a process started alone takes all: its claim guards it


def test_a_process_started_alone_feeds_a_launched_pipeline_only_where_it_may_stand() -> None:
    # The operator's tools, a planner added with `nwr run planner`, diagnostics: yes.
    for relative in ("control/active", "control/safety", "robot/command/extra", "reflex/extra/status",
                     "diag/switch", "skin/pressure"):  # skin/pressure: a live nwr replay
        assert from_this_pipeline(MINE, ALONE, relative), relative
    # The skin, the pain and the arm's state come from the pipeline's own gateway, gain estimator and bridge.
    for relative in ("skin/pain", "robot/state", "world/skin", "no/such/key"):
        assert not from_this_pipeline(MINE, ALONE, relative), relative


def owner(name: str, instance: str, pid: int = 1) -> str:
    return keys.owner(f"planner-{name}", instance, "host", pid, 1_700_000_000)


def test_the_bridge_follows_only_its_pipelines_planners() -> None:
    planners = PipelinePlanners(MINE)
    assert planners.on_owner(owner("cartesian", MINE), True) is None  # no liveliness yet
    assert planners.on_alive("cartesian", True) == ("cartesian", True)
    # A stranger's liveliness token alone, or with another pipeline's owner token: never followed.
    assert planners.on_alive("stranger", True) is None
    assert planners.on_owner(owner("stranger", OTHER), True) is None
    assert planners.strangers() == ["stranger"]
    # A planner started alone beside the pipeline (nwr run planner): followed, in either order of its tokens.
    assert planners.on_alive("uniform", True) is None
    assert planners.on_owner(owner("uniform", ALONE), True) == ("uniform", True)
    # Its owner token gone: no longer followed; tokens of other services are none of this.
    assert planners.on_owner(owner("uniform", ALONE), False) == ("uniform", False)
    assert planners.on_owner(keys.owner("bridge", MINE, "host", 1, 1), True) is None
    assert planners.on_alive("cartesian", False) == ("cartesian", False)
    assert planners.strangers() == ["stranger", "uniform"]


def test_a_bridge_started_alone_follows_every_planner_token() -> None:
    planners = PipelinePlanners(ALONE)
    assert planners.on_alive("cartesian", True) == ("cartesian", True)
    assert planners.strangers() == []


def test_a_service_its_launcher_restarted_says_so_on_its_diag_channel(monkeypatch: pytest.MonkeyPatch) -> None:
    """``nwr up`` restarts a service with ``NWR_RESTART`` (why); the service's first Node says it on diag/<service>
    once a subscriber hears (a real session on loopback); a second Node of the same process does not repeat it."""
    zc = ZenohSection(base_port=free_base_port())
    got: list[m.Diagnostic] = []
    heard = threading.Event()

    def keep(sample: zenoh.Sample) -> None:
        got.append(keys.codec("diag/gain").decode(sample.payload.to_bytes()))
        heard.set()

    monkeypatch.delenv(RESTART_ENV, raising=False)
    with Node("recorder", "ur10e", zc, listen_slot="recorder", token=False) as recorder:
        sub = recorder.session.declare_subscriber(keys.key("ur10e", "diag/gain"), keep)
        why = "its last process ended with code -11 (restart 1)"
        monkeypatch.setenv(RESTART_ENV, why)
        with Node("gain", "ur10e", zc, listen_slot="gain", token=False):
            assert heard.wait(RESTARTED_WAIT_S + 3.0), "no diagnostic"
            assert RESTART_ENV not in os.environ
            with Node("gain", "ur10e", zc, token=False):
                time.sleep(0.5)
        sub.undeclare()
    assert [(d.service, d.level, d.code) for d in got] == [("gain", "warning", "restarted")]
    assert got[0].message == f"gain was restarted by its launcher: {why}"
