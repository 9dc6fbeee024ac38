"""The reflex planner's wiring: skin/pain + robot/state + peer statuses + ticks -> commands, statuses, decisions.

The call order of the service per input, with no Zenoh, no thread and no
clock of its own (time comes from the journal, the control cycles from a
:class:`~nwr.common.pacing.Rate`'s deadlines computed on that time): the
live process (:mod:`.main`), lockstep runs and ``nwr verify`` run this code.

- a pain message steps the control cycles that are due first (``catch up``),
  then the planner's event path; a reflex's first command is published
  before the decision that notes it;
- a robot state does the same catch-up before the planner sees it;
- a tick steps the cycles due (at most one beyond those the task's plan
  covers: the live loop sleeps through those) and publishes the status on a
  change or every ``status_rate_hz``;
- the retreat check of a reflex is taken (:meth:`PlannerWiring.retreat_take`)
  and applied (:meth:`PlannerWiring.retreat_apply`) as two inputs: the live
  process computes it between the two in a thread of its own.
"""

from __future__ import annotations

from typing import Any

import msgspec

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.journal import Journal
from nwr.common.pacing import Rate
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner import retreat
from nwr.services.planner.core import Planner
from nwr.services.planner.reflex import RetreatCheck
from nwr.services.wiring import Diag, Out, Wiring, event, receives


class PlannerWiring(Wiring):
    def __init__(self, profile: Profile, *, journal: Journal, out: Out, diag: Diag) -> None:
        cfg = profile.planner
        desc = load_description(profile.robot.description or None)
        self.planner = Planner(cfg, desc, RobotModel(desc), limits=profile.bridge.limits)
        self.name = cfg.name
        self.service = keys.planner_service(cfg.name)
        self.command_key = keys.robot_command(cfg.name)
        self.status_key = keys.planner_status(cfg.name)
        self.decision_key = keys.planner_decision(cfg.name)
        self.outputs = (self.command_key, self.status_key, self.decision_key)
        self.journal = journal
        self.out = out
        self.diag = diag
        self.rate = Rate(cfg.rate_hz, "planner", starting=True)  # until the first pain message
        self.status_every = max(1, round(cfg.rate_hz / cfg.status_rate_hz))
        self.status_tick = 0
        self.failure: Exception | None = None
        self.check_model = RobotModel(desc)  # the retreat check's own, when it runs in the caller's thread
        self.check: RetreatCheck | None = None
        journal.begin("start")
        self.rate.restart(journal.now_ns())

    @classmethod
    def rebuild(cls, profile: Profile, params: dict[str, Any], *, journal: Journal, out: Out,
                diag: Diag) -> PlannerWiring:
        return cls(profile, journal=journal, out=out, diag=diag)

    def params(self) -> dict[str, Any]:
        return {}

    # -- inputs ------------------------------------------------------------------------
    def _catch_up(self, now: int) -> None:
        for _ in range(self.rate.take(now, limit=self.planner.quiet_cycles)):
            self.planner.step(now)  # a planned cycle: no command

    def _status(self, now: int) -> None:
        self.out(self.status_key, self.planner.status(now))

    @receives("state", keys.ROBOT_STATE)
    def on_state(self, state: m.RobotState) -> None:
        planner = self.planner
        q = m.as_array(state.q)
        if q.shape != planner.q.shape:
            self.diag("warning", "bad_state", f"robot state has {q.size} joints, the robot has {planner.q.size}")
            return
        now = self.journal.now_ns()
        self._catch_up(now)
        planner.on_state(q, following=state.owner == self.name and state.status == "ok",
                         dq=m.as_array(state.dq), owner=state.owner, now_ns=now, phase=state.phase,
                         ok=state.status == "ok", streaming=state.command_mode == "position")
        self._notes()
        if planner.changed:
            self._status(self.journal.now_ns())

    @receives("pain", keys.SKIN_PAIN, stamped=True)
    def on_pain(self, pain: m.SkinPain, received_ns: int) -> m.Command | None:
        """The event path: a reflex starts the moment its pain message arrives (at ``received_ns``)."""
        planner = self.planner
        self._catch_up(received_ns)
        self.rate.starting = False  # the skin flows: the pipeline has started
        try:
            command = planner.on_pain(pain, self.journal.now_ns())
        except ValueError as exc:
            self.diag("warning", "bad_pain", str(exc))
            return None
        decided = self.journal.now_ns()
        if command is not None:
            self.out(self.command_key, command)
        # After the command: noting the decision costs the reflex nothing.
        self.out(self.decision_key, planner.decision(pain, received_ns, decided, command))
        if planner.changed:
            self._status(self.journal.now_ns())
        self._notes()  # what the contact caused (a flickering pad, a restart held back) is reported at once
        return command

    # Not on Zenoh's network thread: this planner's own status, put under the lock, comes back through it.
    @receives("status", keys.planner_status("*"), keyed=True, direct=False)
    def on_peer_status(self, key: str, status: m.PlannerStatus) -> None:
        if key != keys.planner_status(status.name):
            self.diag("warning", "status_spoofed",
                      f"a status on {key} claims to be planner {status.name!r}'s: ignored (a planner's status names "
                      "the planner whose key it comes on)")
            return
        self.planner.on_peer_status(status, self.journal.now_ns())
        self._notes()

    def _notes(self) -> None:
        for level, code, message in self.planner.drain_notes():
            self.diag(level, code, message)

    @event("tick")
    def tick(self) -> None:
        """The control loop woke: step the cycles due, publish the status when it is due."""
        self.failure = None  # a failed cycle, for the adapter to report
        now = self.journal.now_ns()
        planner = self.planner
        due = self.rate.take(now, limit=planner.quiet_cycles + 1)
        if due == 0:
            self.journal.discard()  # woken early, or an event stepped the cycles due
            return
        self.rate.skip(now)  # cycles beyond those are lost to a late loop (motion slows, never jumps)
        for _ in range(due):
            try:
                command = planner.step(now)
            except Exception as exc:  # noqa: BLE001  one cycle's failure, never the service's end
                self.failure = exc
                planner.restart()  # no command: the bridge holds the arm; start again from its measured state
                break
            if command is not None:
                self.out(self.command_key, command)
        if planner.changed or self.rate.ticks - self.status_tick >= self.status_every:
            self.status_tick = self.rate.ticks
            self._status(now)

    @event("retreat_take")
    def retreat_take(self) -> RetreatCheck | None:
        """What the retreat check of the current reflex needs (None outside a reflex)."""
        self.check = self.planner.retreat_check()
        return self.check

    @event("retreat_apply", record=lambda check, assessment: (0, "", ()),
           recall=lambda w, e: w.rerun_check())
    def retreat_apply(self, check: RetreatCheck, assessment: retreat.Assessment) -> None:
        """A check's figures, published with the reflex on the next status."""
        self.planner.apply_retreat(check, assessment)

    def assess(self) -> None:
        """The retreat check taken, run and applied at once (lockstep: in the caller's thread)."""
        check = self.retreat_take()
        if check is not None:
            self.retreat_apply(check, check.run(self.check_model))

    def rerun_check(self) -> tuple[RetreatCheck, retreat.Assessment]:
        """The check taken last, run again here (a re-run: the live process ran it in its own thread)."""
        if self.check is None:
            raise ValueError("a retreat check applied that was never taken")
        return self.check, self.check.run(self.check_model)


def planner_profile(profile: Profile, *, name: str | None = None, strategy: str | None = None) -> Profile:
    """``profile`` with its planner's name and strategy overridden (a copy)."""
    cfg = msgspec.structs.replace(profile.planner, strategy=strategy or profile.planner.strategy,
                                  name=name or strategy or profile.planner.name)
    return msgspec.structs.replace(profile, planner=cfg)
