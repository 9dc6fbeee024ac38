"""The pipeline's services in one process, on simulated time, in lockstep: their own wirings, re-wired nowhere.

Each service's wiring (``services/<service>/wiring.py``, the code the live
process runs) is built here on a simulated clock, and the messages one
publishes are delivered to those that subscribe, through one queue, after
the publishing handler returns; every control cycle of 2 ms is one step of
simulated time:

- each message goes to the wirings that declare it an input
  (:class:`nwr.services.wiring.Input`), in the order bridge, planner, gain,
  gateway: a skin sample at its own stamp to the bridge (fresh skin) and the
  gain estimator, whose pain message goes to the bridge and the planner's
  event path (a reflex's first command reaches the bridge at once, its
  retreat check runs once that has been delivered);
- every control cycle the planner's loop ticks, then the bridge's: the
  robot state goes back to the planner (and the simulated skin) at
  ``state_rate_hz``, the planner's status at ``status_rate_hz`` and on every
  transition.

Where the skin samples come from: a skin source of the gateway
(:mod:`nwr.services.gateway.stepped`): recorded, re-simulated, or the
gateway's own wiring on a touch script.

Nothing here reads a clock, so a run is deterministic: the same skin samples
give the same messages, bit for bit. Each wiring keeps its journal as the
live services do, so ``nwr verify`` re-runs a lockstep recording as it does
a live one. It is what ``nwr replay --fast`` runs (as fast as the cores go)
and the lower bound of ``nwr bench``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import msgspec

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.clock import ManualClock
from nwr.common.config import Profile
from nwr.common.journal import JOURNAL_PERIOD_S, Batcher, Journal, Recording, Untracked, service_config
from nwr.services.bridge.wiring import BridgeWiring
from nwr.services.gain.wiring import GainWiring
from nwr.services.gateway.stepped import Emit, Pose, RecordedSkin, SkinSource
from nwr.services.gateway.wiring import GatewayWiring
from nwr.services.planner.wiring import PlannerWiring, planner_profile
from nwr.services.wiring import Diag, Input, Wiring, no_diag


@dataclass
class LockstepReport:
    skin_samples: int
    cycles: int
    messages: int
    simulated_s: float


class Lockstep:
    """(gateway ->) gain -> planner -> bridge (simulated arm): the services' own wirings on simulated time.

    Messages travel through one queue, in the order they were published, each
    delivered after the handler that published it has returned (as the
    services receive them over the network, less the network's delay). With
    ``journal``, every wiring keeps its journal and the run emits it on
    ``journal/<service>`` like the live services, so ``nwr verify`` can
    re-run a lockstep recording too.
    """

    def __init__(self, profile: Profile, *, strategy: str | None = None, name: str | None = None,
                 journal: bool = True, diag: Diag = no_diag) -> None:
        profile = planner_profile(profile, name=name, strategy=strategy)
        self.profile = msgspec.structs.replace(
            profile, bridge=msgspec.structs.replace(profile.bridge, active_planner=profile.planner.name))
        self.name = self.profile.planner.name
        self.period_ns = round(1e9 / profile.bridge.rate_hz)
        self.clock = ManualClock()
        self.keep_journal = journal
        self.diag = diag  # what the services report (the live ones on diag/<service>): dropped by default
        self.journals: list[tuple[Any, Journal, Batcher]] = []  # (wiring, journal, batcher)
        self.queue: deque[tuple[str, Any]] = deque()
        self.emit: Emit = _no_emit
        self.cycles = 0
        self.messages = 0
        self.gateway: GatewayWiring | None = None
        self.wirings: list[Wiring] = []  # in the order a message reaches them
        self._routes: dict[str, list[tuple[Wiring, Input]]] = {}
        self.state: m.RobotState | None = None  # the newest robot state

    def _journal(self) -> Journal:
        return Recording(self.clock) if self.keep_journal else Untracked(self.clock)

    def _out(self, key: str, message: Any) -> None:
        self.emit(key, message, self.clock.t_ns)
        self.messages += 1
        self.queue.append((key, message))

    def _wire(self, factory: Any, **kwargs: Any) -> Any:
        journal = self._journal()
        wiring = factory(self.profile, journal=journal, out=self._out, diag=self.diag, **kwargs)
        self.wirings.append(wiring)
        self.journals.append((wiring, journal, Batcher(wiring.service, self.clock.t_ns,
                                                       service_config(self.profile, **wiring.params()))))
        return wiring

    def _start(self, t0: int, source: SkinSource) -> None:
        self.clock.t_ns = t0
        self.bridge: BridgeWiring = self._wire(BridgeWiring)
        self.planner: PlannerWiring = self._wire(PlannerWiring)
        self.gain: GainWiring = self._wire(GainWiring)
        journal = self._journal()
        self.gateway = source.wiring(self.clock, journal, self._out)
        if self.gateway is not None:
            gw = self.gateway
            self.wirings.append(gw)
            origin = t0 if source.origin_ns is None else source.origin_ns
            batcher = Batcher(gw.service, origin, service_config(self.profile, **gw.params()))
            self.journals.append((gw, journal, batcher))
        self.bridge.on_token(self.name, True)

    def _flush_journals(self, final: bool = False) -> None:
        if not self.keep_journal:
            return
        for wiring, journal, batcher in self.journals:
            assert isinstance(journal, Recording)
            message = batcher.batch(journal.take(), self.clock.t_ns, final=final)
            if message is not None:
                self.emit(keys.journal(wiring.service), message, self.clock.t_ns)

    def pose(self) -> Pose:
        """Where the newest robot state puts the arm (as the live gateway sees it), else where the arm starts."""
        if self.state is None:
            return self.bridge.backend.get_observation().q, 0
        return m.as_array(self.state.q), self.state.stamp_ns

    def routes(self, key: str) -> list[tuple[Wiring, Input]]:
        """Which wirings take a message on ``key``, by which input: what each declares (in the wirings' order)."""
        found = self._routes.get(key)
        if found is None:
            found = self._routes[key] = [(w, inp) for w in self.wirings for inp in w.subscriptions()
                                         if inp.key is not None and keys.matches(key, inp.key)]
        return found

    def drain(self) -> None:
        """Deliver the queued messages, and those they cause, in order (the pipeline's graph)."""
        queue = self.queue
        planner = self.planner
        assess = False
        while queue:
            key, message = queue.popleft()
            if key == keys.ROBOT_STATE:
                self.state = message
            for wiring, inp in self.routes(key):
                # A reflex's command (the planner's pain input returns it): its retreat check comes after.
                if wiring.deliver(inp, key, message, self.clock.t_ns) is not None and wiring is planner:
                    assess = True
        if assess:  # the retreat check, once what the reflex caused has been delivered (live: its own thread)
            planner.assess()

    def run(self, samples: Iterable[m.SkinPressure] | SkinSource, emit: Emit, *,
            settle_s: float = 2.0, start_ns: int | None = None) -> LockstepReport:
        """Feed skin samples (in stamp order) through the chain; ``emit`` gets every message
        the chain makes (and those a source makes, but not recorded samples given as they are).
        The chain runs on ``settle_s`` after the last sample (a simulated skin's samples go on).

        The chain's first control cycle (the planner's first command, the
        start of its task) is at ``start_ns``, by default at the first
        sample's stamp; a replay gives the original pipeline's, so that the
        task is at the same phase when each touch comes.
        """
        source = samples if isinstance(samples, SkinSource) else RecordedSkin(samples)
        n = len(source)
        if not n:
            return LockstepReport(0, 0, 0, 0.0)
        self.emit = emit
        t0 = (source.stamp(0) if start_ns is None else min(start_ns, source.stamp(0))) - self.period_ns
        end = source.stamp(n - 1) + round(settle_s * 1e9)
        source.extend_to(end)  # a simulated skin goes on at rest while the chain settles, as the live gateway does
        n = len(source)
        self._start(t0, source)
        self.drain()
        flush_every = max(1, round(JOURNAL_PERIOD_S * 1e9 / self.period_ns))
        clock = self.clock
        i = 0
        t = t0
        while t < end:
            t += self.period_ns
            while i < n and source.stamp(i) <= t:
                clock.t_ns = source.stamp(i)  # a source that makes samples stamps them as its own
                sample = source.take(i, self.pose(), emit)
                clock.t_ns = t
                if sample is not None:
                    self.queue.append((keys.SKIN_PRESSURE, sample))
                self.drain()
                i += 1
            clock.t_ns = t
            self.planner.tick()
            self.drain()
            self.bridge.tick()
            self.drain()
            self.cycles += 1
            if self.cycles % flush_every == 0:
                self._flush_journals()
        self._flush_journals(final=True)
        return LockstepReport(i, self.cycles, self.messages, (t - t0) / 1e9)


def _no_emit(key: str, message: Any, t: int) -> None:
    pass
