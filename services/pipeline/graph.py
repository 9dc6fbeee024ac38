"""The pipeline's graph as data: its services, the keys each reads and writes, start and stop order, process names.

Every launcher builds its processes from here: ``nwr up`` and ``nwr demo``
(:func:`nwr.services.pipeline.supervisor.launch`), ``nwr bench``, the live
``nwr replay`` and ``nwr study``; ``nwr status`` and ``nwr run`` name the
services from :data:`SERVICES`. ``deploy/compose.yaml`` and the router's
access control (``deploy/acl.json5``) are held against it by
``tests/test_graph.py``.

Which keys a service reads and writes is not written here a second time:
what a service with a wiring reads is its wiring's declared inputs
(:class:`nwr.services.wiring.Input`), what the others read the key
registry's consumers; what each writes, the registry's producers
(:data:`nwr.common.keys.TOPICS`).

Start order: the recorder first (the others start once it is alive, so it
records every journal from its first batch), then the bridge, the planners
and the gain estimator; the view (read-only) before the gateway; the gateway
last, once the others are alive (``--wait-for``), since its clock starts the
touch script. Stop order: the bridge first (it brings the arm to rest while
the skin, the gain estimator and the planners still run: an orderly end, not a
stale input), then the gateway (no new samples), the others in reverse start
order, the recorder once they have exited (it keeps their last journal
batches), a router after everything.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from nwr.common import keys
from nwr.common.errors import ConfigError

# Service -> what it does (the help of ``nwr run SERVICE``).
SERVICES = {
    "gateway": "skin gateway: simulated AIRSKIN pads -> skin/pressure",
    "gain": "gain estimator: skin/pressure -> skin/pain (pain level and gain per pad)",
    "planner": "reflex planner: task, state machine and reflex -> robot/command/<name>",
    "bridge": "robot bridge: the active planner's robot/command/<name> -> the (simulated) arm -> robot/state",
    "recorder": "recorder: everything under nwr/<robot>/ -> MCAP",
    "view": "view (read-only): the live 3D scene and signals for Foxglove over WebSocket",
}
# A Zenoh router (``nwr router``) when the layout has one: started before the
# services, stopped after them.
ROUTER = "router"
START_ORDER = (ROUTER, "recorder", "bridge", "planner", "gain", "view", "gateway")
# Services nobody waits for before the touch script starts (read-only).
NOT_WAITED_FOR = ("view",)


# Each service with a wiring (the call order the live process, lockstep and nwr verify run): module, class.
# Imported when asked for, so that a process loads only its own service's code.
WIRINGS = {
    "gateway": ("nwr.services.gateway.wiring", "GatewayWiring"),
    "gain": ("nwr.services.gain.wiring", "GainWiring"),
    "planner": ("nwr.services.planner.wiring", "PlannerWiring"),
    "bridge": ("nwr.services.bridge.wiring", "BridgeWiring"),
}


def wiring_for(service: str) -> Any:
    """The wiring class of a service, or of a process name as journaled (``planner-<name>`` for planners)."""
    if service.startswith(keys.PLANNER_SERVICE_PREFIX):
        service = "planner"
    found = WIRINGS.get(service)
    if found is None:
        raise ConfigError(f"no wiring for a service named {service!r} (services with one: {sorted(WIRINGS)})")
    module, name = found
    return getattr(importlib.import_module(module), name)


def reads(service: str) -> tuple[str, ...]:
    """The key patterns ``service`` subscribes to: its wiring's declared inputs, else the key registry's consumers."""
    if service in WIRINGS:
        inputs = wiring_for(service).inputs.values()
        return tuple(dict.fromkeys(inp.key for inp in inputs if inp.key is not None))
    return tuple(t.pattern for t in keys.TOPICS if service in t.consumers)


def writes(service: str) -> tuple[str, ...]:
    """The key patterns ``service`` puts on (the key registry's producers)."""
    return tuple(t.pattern for t in keys.TOPICS if service in t.producers or keys.ANY_SERVICE in t.producers)


def process_name(service: str, planner: str | None = None) -> str:
    """A process's name, which its liveliness token, diagnostics and journal carry: ``planner-<name>`` per planner."""
    if service == "planner" and planner:
        return keys.planner_service(planner)
    return service


@dataclass(frozen=True)
class Unit:
    """One process of a layout: its label (the process name), its service and its ``nwr run SERVICE`` arguments."""

    label: str
    service: str
    args: tuple[str, ...] = ()

    def restarted(self, n: int) -> Unit:
        """This unit as its ``n``-th restart runs it: a recorder writes a file of its own, never over the first."""
        if self.service != "recorder" or "--output" not in self.args:
            return self
        args = list(self.args)
        i = args.index("--output") + 1
        first = Path(args[i])
        args[i] = str(first.with_name(f"{first.stem}-restart{n}{first.suffix}"))
        return Unit(self.label, self.service, tuple(args))

    def command(self) -> list[str]:
        """The arguments after ``nwr [--profile ...]``."""
        if self.service == ROUTER:
            return [ROUTER, *self.args]
        return ["run", self.service, *self.args]


@dataclass
class Layout:
    """What one launch runs.

    ``planners`` names one planner per reflex strategy (each named after its
    strategy); empty: one planner as the profile says (named ``planner_name``).
    ``active`` is the planner the bridge follows (default: the first).
    """

    planners: list[str] = field(default_factory=list)
    active: str | None = None
    planner_name: str = "planner"  # the profile's planner name, when ``planners`` is empty
    recorder: list[str] | None = None  # the recorder's arguments; None: no recorder
    gateway: list[str] | None = field(default_factory=list)  # the gateway's arguments; None: no gateway
    view_port: int | None = None
    router: list[str] | None = None  # a router's arguments; None: no router
    bridge: list[str] = field(default_factory=list)  # the bridge's arguments (its backend, the robot's address)

    def __post_init__(self) -> None:
        if self.active and self.planners and self.active not in self.planners:
            self.planners.insert(0, self.active)
        if self.active is None and self.planners:
            self.active = self.planners[0]


def units(layout: Layout) -> list[Unit]:
    """The layout's processes in start order; the gateway waits for every other one but the view."""
    out: list[Unit] = []
    for service in START_ORDER:
        if service == ROUTER and layout.router is not None:
            out.append(Unit(ROUTER, ROUTER, tuple(layout.router)))
        elif service == "recorder" and layout.recorder is not None:
            out.append(Unit("recorder", "recorder", tuple(layout.recorder)))
        elif service == "bridge":
            active = ("--active", layout.active) if layout.active else ()
            out.append(Unit("bridge", "bridge", (*active, *layout.bridge)))
        elif service == "planner":
            named: list[str | None] = list(layout.planners) or [layout.active]
            for p in named:
                out.append(Unit(process_name("planner", p), "planner", ("--name", p, "--reflex", p) if p else ()))
        elif service == "gain":
            out.append(Unit("gain", "gain"))
        elif service == "view" and layout.view_port is not None:
            out.append(Unit("view", "view", ("--port", str(layout.view_port))))
        elif service == "gateway" and layout.gateway is not None:
            waits = [process_name("planner", u.args[1] if u.args else layout.planner_name)
                     if u.service == "planner" else u.label
                     for u in out if u.service not in (ROUTER, *NOT_WAITED_FOR)]
            out.append(Unit("gateway", "gateway", ("--wait-for", ",".join(waits), *layout.gateway)))
    return out


def stop_order(labels: list[str]) -> list[list[str]]:
    """Groups of process labels to stop one after the other (see the module's docstring)."""
    last = [label for label in (ROUTER,) if label in labels]
    recorder = [label for label in labels if label == "recorder"]
    bridge = [label for label in labels if label == "bridge"]
    gateway = [label for label in labels if label == "gateway"]
    rest = [label for label in reversed(labels) if label not in (*last, *recorder, *bridge, *gateway)]
    return [group for group in (bridge, gateway, rest, recorder, last) if group]


def recorder_args(output: Path, session: str, strategy: str, labels: dict[str, str] | None = None) -> list[str]:
    """The recorder's arguments for one session file."""
    extra = [f"--label={k}={v}" for k, v in (labels or {}).items()]
    return ["--session", session, "--output", str(output), "--strategy", strategy, *extra]
