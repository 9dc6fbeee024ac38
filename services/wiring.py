"""What every service's wiring shares: how it hands out what it publishes, and its inputs, declared once.

A wiring (``services/<service>/wiring.py``) is the call order of one service
per input and per tick: no Zenoh, no threads, no clock (its time comes from
its journal, :mod:`nwr.common.journal`). It publishes through ``out(key,
message)`` and reports through ``diag(level, code, text)`` (repeats of a code
within ``every_s`` are counted, not sent: ``every_s=0`` for a change of state
that must always be heard); the live process
maps those onto Zenoh, lockstep onto the other wirings, ``nwr verify`` onto
a comparison with the recording.

Each input is declared once, on the method that takes it (:func:`receives`
for a message on a registry key, :func:`event` for a tick or a token of the
service's own): its journal name, its key and how it is re-run. Adding an
input to a service is that one line.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, ParamSpec, Protocol, TypeVar

from nwr.common import messages as m
from nwr.common.journal import Journal

P = ParamSpec("P")
R = TypeVar("R")

Out = Callable[[str, Any], None]  # (relative key, message)


class Diag(Protocol):
    def __call__(self, level: str, code: str, message: str, *, every_s: float = 1.0) -> None:
        """Report (level, code, readable message); repeats of the code within ``every_s`` are rate limited."""


def no_diag(level: str, code: str, message: str, *, every_s: float = 1.0) -> None:
    """A ``diag`` that drops every report (lockstep, where nobody listens)."""


# ------------------------------------------------------------------------------ inputs, declared once

Fields = tuple[int, str, Sequence[float]]  # what an event puts in its journal entry: (arg, text, data)
_INPUT = "__nwr_input__"


@dataclass(frozen=True)
class Input:
    """One input of a wiring: its journal name, the method that takes it and, for a message, where it comes from.

    Declared once, on the method (:func:`receives`, :func:`event`); the
    live subscriptions (:func:`subscribe`), lockstep's routing
    (:mod:`nwr.services.pipeline.lockstep`), the journal's entries, ``nwr
    verify``'s re-run (:meth:`Wiring.replay`) and the pipeline's graph
    (:func:`nwr.services.pipeline.graph.reads`) all read it.
    """

    name: str  # the journal's name for it (recordings keep it: never rename one)
    method: str  # the wiring's method that takes it
    key: str | None = None  # a message's registry key (a pattern, too); None: an event of the service's own
    keyed: bool = False  # the method takes the key the message came on first (a pattern's)
    stamped: bool = False  # the method takes the receipt time last (journaled as the entry's arg)
    direct: bool = True  # live: on Zenoh's network thread (see nwr.common.node.Node.subscribe)
    record: Callable[..., Fields] | None = None  # an event: the call's arguments -> its journal fields
    recall: Callable[[Any, m.JournalEntry], tuple[Any, ...]] | None = None  # an event: the entry -> the arguments


def receives(name: str, key: str, *, keyed: bool = False, stamped: bool = False,
             direct: bool = True) -> Callable[[Callable[P, R]], Callable[P, R]]:
    """Declare a wiring's method the handler of messages on ``key``; calling it journals the message first."""
    def declare(method: Callable[P, R]) -> Callable[P, R]:
        @functools.wraps(method)
        def handle(*args: P.args, **kwargs: P.kwargs) -> R:
            self = args[0]
            message = args[2] if keyed else args[1]
            self.journal.begin(name, args[1] if keyed else key, message,  # type: ignore[attr-defined]
                               arg=args[-1] if stamped else 0)
            return method(*args, **kwargs)

        setattr(handle, _INPUT, Input(name, method.__name__, key, keyed, stamped, direct))
        return handle
    return declare


def event(name: str, *, record: Callable[..., Fields] | None = None,
          recall: Callable[[Any, m.JournalEntry], tuple[Any, ...]] | None = None,
          ) -> Callable[[Callable[P, R]], Callable[P, R]]:
    """Declare a wiring's method an event of its own (a tick, a token): calling it journals it first.

    ``record(*args)`` gives the journal's (arg, text, data) for a call's arguments; ``recall(wiring, entry)`` the
    arguments again, for the re-run. Without them the event has none.
    """
    def declare(method: Callable[P, R]) -> Callable[P, R]:
        @functools.wraps(method)
        def handle(*args: P.args, **kwargs: P.kwargs) -> R:
            arg, text, data = record(*args[1:], **kwargs) if record is not None else (0, "", ())
            args[0].journal.begin(name, arg=arg, text=text, data=data)  # type: ignore[attr-defined]
            return method(*args, **kwargs)

        setattr(handle, _INPUT, Input(name, method.__name__, record=record, recall=recall))
        return handle
    return declare


class Wiring:
    """What every service's wiring has: its inputs' table (from the declared methods) and its re-run from a journal.

    A subclass sets ``service``, ``outputs`` and ``journal``; ``inputs`` maps
    each input's journal name to its declaration.
    """

    service: str
    outputs: tuple[str, ...]
    journal: Journal
    inputs: ClassVar[dict[str, Input]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        found = (getattr(value, _INPUT, None) for klass in reversed(cls.__mro__) for value in vars(klass).values())
        cls.inputs = {inp.name: inp for inp in found if isinstance(inp, Input)}

    def listens(self, inp: Input) -> bool:
        """Whether this instance takes the messages of a declared input (all of them, unless a wiring says not)."""
        return True

    def subscriptions(self) -> list[Input]:
        """The message inputs this instance takes, in the order they are declared."""
        return [inp for inp in self.inputs.values() if inp.key is not None and self.listens(inp)]

    def deliver(self, inp: Input, key: str, message: Any, received_ns: int = 0) -> Any:
        """A message of input ``inp`` that came on ``key`` (received at ``received_ns``): its handler's result."""
        method = getattr(self, inp.method)
        if inp.keyed:
            return method(key, message, received_ns) if inp.stamped else method(key, message)
        return method(message, received_ns) if inp.stamped else method(message)

    def replay(self, entry: m.JournalEntry, message: Any) -> None:
        """Re-run one journal entry (``message``: the recorded message it names, if any)."""
        inp = self.inputs.get(entry.input)
        if inp is None:
            raise ValueError(f"the {self.service} has no input {entry.input!r} (it has {sorted(self.inputs)})")
        if inp.key is not None:
            self.deliver(inp, entry.key, message, entry.arg)
        else:
            getattr(self, inp.method)(*(inp.recall(self, entry) if inp.recall is not None else ()))


def subscribe(node: Any, wiring: Wiring, lock: threading.Lock,
              then: Mapping[str, Callable[[Any], None]] | None = None) -> None:
    """The live subscriptions of a wiring's message inputs on ``node`` (a :class:`nwr.common.node.Node`).

    Each handler runs under ``lock``; a stamped input's receipt time is read
    before it. ``then[name](result)`` runs after the handler, under the lock
    (the adapter's own follow-up: waking a loop, starting a check).
    """
    after = then or {}
    clock = node.clock
    for inp in wiring.subscriptions():
        assert inp.key is not None
        fixed = inp.key
        follow = after.get(inp.name)

        def handle(*args: Any, inp: Input = inp, fixed: str = fixed, follow: Any = follow) -> None:
            key, message = args if len(args) == 2 else (fixed, args[0])
            received = clock.now_ns() if inp.stamped else 0  # before the lock: when it arrived
            with lock:
                result = wiring.deliver(inp, key, message, received)
                if follow is not None:
                    follow(result)

        node.subscribe(inp.key, handle, keyed="*" in inp.key, direct=inp.direct)
