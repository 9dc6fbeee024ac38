"""A catalogue of wrong-but-decodable messages: every one decodes on its key, none can be true.

Used by ``test_door.py`` (the door and every service's handling, in process)
and ``test_wrong_messages_e2e.py`` (published into a running ``nwr up``).
``refused`` says whether the door itself refuses it; the others are the
receiving service's own business (the bridge's command check, its switch
rules), and the tests check what it does with them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from msgspec.structs import replace

from nwr.common import messages as m
from nwr.common.robot import RobotDescription


@dataclass(frozen=True)
class Wrong:
    name: str
    key: str  # relative key
    message: Any
    refused: bool = True  # by the door


def catalogue(desc: RobotDescription, *, active: str = "cartesian", seq: int = 1, stamp_ns: int = 1) -> list[Wrong]:
    """The wrong messages for ``desc``'s robot, each with ``seq`` and ``stamp_ns`` unless it is about them."""
    n, pads = len(desc.joints), len(desc.pads)
    home = [float(x) for x in desc.home]
    tr = m.Trace(seq, stamp_ns)
    contact = m.Contact(pad=1, name=desc.pads[1].name, region=desc.pads[1].region, change_hpa=30.0, level=4, gain=1.0)
    pressure = m.SkinPressure(seq=seq, stamp_ns=stamp_ns, absolute_hpa=[1013.0] * pads, baseline_hpa=[1013.0] * pads,
                              change_hpa=[0.0] * pads, contact=[False] * pads)
    pain = m.SkinPain(seq=seq, stamp_ns=stamp_ns, trace=tr, model="continuous", level=[1] * pads, gain=[0.0] * pads)
    state = m.RobotState(seq=seq, stamp_ns=stamp_ns, q=home, dq=[0.0] * n, status="ok", owner=active, backend="sim")
    position = m.PositionCommand(seq=seq, stamp_ns=stamp_ns, owner=active, q=home, trace=tr)
    status = m.PlannerStatus(seq=seq, stamp_ns=stamp_ns, name="intruder", strategy="uniform", mode="TASK",
                             task_time_s=1.0)
    touch = m.SkinTouch(seq=seq, stamp_ns=stamp_ns, pad=2, name=desc.pads[2].name, origin_ns=0, start_s=0.0,
                        duration_s=0.3, peak_hpa=20.0, shape="step", ramp_s=0.0)
    far = [x + 1.0 for x in home]

    def pain_with(**kw: Any) -> m.SkinPain:
        return replace(pain, **kw)

    out = [
        # skin/pressure
        Wrong("pressure seq 2^32", "skin/pressure", replace(pressure, seq=2**32)),
        Wrong("pressure seq 2^63", "skin/pressure", replace(pressure, seq=2**63)),
        Wrong("pressure seq -1", "skin/pressure", replace(pressure, seq=-1)),
        Wrong("pressure stamp -1", "skin/pressure", replace(pressure, stamp_ns=-1)),
        Wrong("pressure stamp 2^63", "skin/pressure", replace(pressure, stamp_ns=2**63)),
        Wrong("pressure with one pad too few", "skin/pressure",
              replace(pressure, absolute_hpa=[1013.0] * (pads - 1))),
        Wrong("pressure with one pad too many", "skin/pressure",
              replace(pressure, change_hpa=[0.0] * (pads + 1))),
        Wrong("pressure with no pads", "skin/pressure",
              replace(pressure, absolute_hpa=[], baseline_hpa=[], change_hpa=[], contact=[])),
        Wrong("pressure contact flags too short", "skin/pressure", replace(pressure, contact=[True])),
        Wrong("pressure valid flags too long", "skin/pressure", replace(pressure, valid=[True] * (pads + 3))),
        Wrong("pressure negative absolute", "skin/pressure", replace(pressure, absolute_hpa=[-5.0] * pads)),
        Wrong("pressure absolute 1e9 hPa", "skin/pressure", replace(pressure, absolute_hpa=[1e9] * pads)),
        Wrong("pressure change 1e6 hPa", "skin/pressure", replace(pressure, change_hpa=[1e6] * pads)),
        Wrong("pressure change -1e6 hPa", "skin/pressure", replace(pressure, change_hpa=[-1e6] * pads)),
        Wrong("pressure baseline 1e12", "skin/pressure", replace(pressure, baseline_hpa=[1e12] * pads)),
        # skin/pain
        Wrong("pain strongest pad -1", "skin/pain", pain_with(strongest=replace(contact, pad=-1))),
        Wrong("pain strongest pad -11", "skin/pain", pain_with(strongest=replace(contact, pad=-11))),
        Wrong("pain strongest pad 99", "skin/pain", pain_with(strongest=replace(contact, pad=99))),
        Wrong("pain strongest pad 2^40", "skin/pain", pain_with(strongest=replace(contact, pad=2**40))),
        Wrong("pain strongest level 7", "skin/pain", pain_with(strongest=replace(contact, level=7))),
        Wrong("pain strongest gain 5", "skin/pain", pain_with(strongest=replace(contact, gain=5.0))),
        Wrong("pain strongest gain -1", "skin/pain", pain_with(strongest=replace(contact, gain=-1.0))),
        Wrong("pain level 0", "skin/pain", pain_with(level=[0] * pads)),
        Wrong("pain level 5", "skin/pain", pain_with(level=[5] * pads)),
        Wrong("pain level -3", "skin/pain", pain_with(level=[-3] * pads)),
        Wrong("pain gain 2", "skin/pain", pain_with(gain=[2.0] * pads)),
        Wrong("pain gain -0.5", "skin/pain", pain_with(gain=[-0.5] * pads)),
        Wrong("pain levels of 3 pads", "skin/pain", pain_with(level=[1, 1, 1])),
        Wrong("pain gains of 11 pads", "skin/pain", pain_with(gain=[0.0] * (pads + 1))),
        Wrong("pain trace seq 2^40", "skin/pain", pain_with(trace=m.Trace(2**40, 1))),
        Wrong("pain seq 2^32", "skin/pain", pain_with(seq=2**32)),
        # robot/state
        Wrong("state q 1e12", "robot/state", replace(state, q=[1e12] * n)),
        Wrong("state q -1e12", "robot/state", replace(state, q=[-1e12] * n)),
        Wrong("state q 100 rad", "robot/state", replace(state, q=[100.0] * n)),
        Wrong("state with 5 joints", "robot/state", replace(state, q=home[:-1], dq=[0.0] * (n - 1))),
        Wrong("state with 7 joints", "robot/state", replace(state, q=[*home, 0.0], dq=[0.0] * (n + 1))),
        Wrong("state dq 1e6", "robot/state", replace(state, dq=[1e6] * n)),
        Wrong("state seq 2^32", "robot/state", replace(state, seq=2**32)),
        Wrong("state owner with spaces", "robot/state", replace(state, owner="Not A Planner!")),
        Wrong("state stop distance of 3 joints", "robot/state", replace(state, stop_distance=[0.0] * 3)),
        # robot/command/<active>: lengths at the door; values, owner and seq are the bridge's check
        Wrong("position with 5 joints", f"robot/command/{active}", replace(position, q=home[:-1])),
        Wrong("position ahead rows of 5 joints", f"robot/command/{active}",
              replace(position, ahead=[home[:-1]], period_s=0.002)),
        Wrong("position seq 2^32", f"robot/command/{active}", replace(position, seq=2**32)),
        Wrong("position owner with spaces", f"robot/command/{active}", replace(position, owner="Bad Owner")),
        Wrong("position trace seq -5", f"robot/command/{active}", replace(position, trace=m.Trace(-5, 1))),
        Wrong("velocity with 8 joints", f"robot/command/{active}",
              m.VelocityCommand(seq=seq, stamp_ns=stamp_ns, owner=active, dq=[0.0] * 8, trace=tr)),
        Wrong("position 1 rad away", f"robot/command/{active}", replace(position, q=far), refused=False),
        Wrong("position 1e12 rad", f"robot/command/{active}", replace(position, q=[1e12] * n), refused=False),
        Wrong("velocity 1e6 rad/s", f"robot/command/{active}",
              m.VelocityCommand(seq=seq, stamp_ns=stamp_ns, owner=active, dq=[1e6] * n, trace=tr), refused=False),
        Wrong("position ahead period 10 s", f"robot/command/{active}",
              replace(position, ahead=[home], period_s=10.0), refused=False),
        Wrong("position from another owner", f"robot/command/{active}", replace(position, owner="intruder"),
              refused=False),
        # control/active, control/safety
        Wrong("switch to an upper-case name", "control/active",
              m.SwitchRequest(seq=seq, stamp_ns=stamp_ns, name="ATTACKER")),
        Wrong("switch to an empty name", "control/active", m.SwitchRequest(seq=seq, stamp_ns=stamp_ns, name="")),
        Wrong("switch to a 100-character name", "control/active",
              m.SwitchRequest(seq=seq, stamp_ns=stamp_ns, name="x" * 100)),
        Wrong("switch seq 2^32", "control/active", m.SwitchRequest(seq=2**32, stamp_ns=stamp_ns, name="uniform")),
        Wrong("switch to a planner that does not run", "control/active",
              m.SwitchRequest(seq=seq, stamp_ns=stamp_ns, name="nobody"), refused=False),
        Wrong("safety mode stamp -1", "control/safety",
              m.SafetyModeRequest(seq=seq, stamp_ns=-1, mode="reduced")),
        # reflex/<name>/status
        Wrong("status saved pose of 3 joints", "reflex/intruder/status",
              replace(status, mode="REFLEX", saved_pose=[0.0] * 3)),
        Wrong("status saved pose 1e12", "reflex/intruder/status",
              replace(status, mode="REFLEX", saved_pose=[1e12] * n)),
        Wrong("status target pad 99", "reflex/intruder/status", replace(status, target_pad=99)),
        Wrong("status task time -5", "reflex/intruder/status", replace(status, task_time_s=-5.0)),
        Wrong("status task time 1e11", "reflex/intruder/status", replace(status, task_time_s=1e11)),
        Wrong("status planner name with spaces", "reflex/intruder/status", replace(status, name="In Truder")),
        Wrong("status reflex on pad 99", "reflex/intruder/status",
              replace(status, mode="REFLEX", reflex=m.ReflexInfo(reflex_seq=1, strategy="uniform",
                                                                  contact=replace(contact, pad=99), trace=tr,
                                                                  started_ns=1, duration_s=0.5))),
        # skin/touch, diag
        Wrong("touch on pad 99", "skin/touch", replace(touch, pad=99)),
        Wrong("touch naming another pad", "skin/touch", replace(touch, name="nowhere")),
        Wrong("touch pose of 2 joints", "skin/touch", replace(touch, q=[0.0, 0.0])),
        Wrong("diagnostic of an unnamed service", "diag/intruder",
              m.Diagnostic(seq=seq, stamp_ns=stamp_ns, service="", level="error", code="x", message="y")),
    ]
    return out
