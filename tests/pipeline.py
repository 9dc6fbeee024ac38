"""The pipeline of an end-to-end test: its mesh, its profile, its processes, their logs, one way to stop them.

An end-to-end test runs the real processes (``nwr up``, ``nwr demo``,
``nwr run SERVICE``, a router) on loopback. :class:`Pipeline` is what every
such test sets up the same way:

- a Zenoh mesh of its own: a base port whose every slot is free
  (:func:`free_base_port`), so that no two tests, and no two test runs on
  one machine, ever meet on a mesh;
- the profile (``profile.toml`` in the test's folder): that port, the
  recordings in the test's folder, and the test's own sections;
- its processes, each ``python -m nwr.services.cli --profile PROFILE ARGS``
  in a process group of its own, its output in ``<label>.log``
  (:meth:`Pipeline.log`);
- waiting (:meth:`Pipeline.wait_until`, :meth:`Pipeline.wait_alive`): a
  guard, not a measurement, that fails at once, with the logs, when a
  process that should run has exited;
- stopping (:meth:`Pipeline.stop`): a signal (SIGINT, as a person's Ctrl-C,
  or SIGTERM), a grace period, then SIGKILL to the whole group; whatever is
  left of a group (a launcher's services) is killed with it, so nothing
  outlives its test.

The ``pipeline`` fixture (tests/conftest.py) gives a test one, stopped at
its end. Tests that share one running pipeline make it in a module-scoped
fixture of their own: ``with Pipeline(tmp_path_factory.mktemp(NAME)) as p``.
"""

from __future__ import annotations

import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from types import TracebackType
from typing import TypeVar

import zenoh

from nwr.common import keys
from nwr.common.config import ZenohSection
from nwr.common.node import SLOTS, Node, zenoh_config

T = TypeVar("T")

ROBOT = "ur10e"
DATA = Path(__file__).resolve().parent / "data"
SHORT_SCRIPT = DATA / "short.toml"  # four touches in 16 s: the session most end-to-end tests run
# Where free_base_port looks: below Linux's ephemeral ports (32768-60999) and the UR controller's fixed ports
# (29999-30004), away from the fixed meshes of the tests that keep their own (17450-18999).
PORT_RANGE = (20000, 29000)
# Guards, not measurements: how long to wait for something that must happen before calling the test failed.
WAIT_S = 60.0
# A failure quotes this much of the end of each process's log, characters.
LOG_TAIL = 4000

_given: set[int] = set()  # base ports handed out in this test run


def _free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_base_port(width: int = max(SLOTS.values()) + 1) -> int:
    """A base port on 127.0.0.1 with ``width`` free ports from it (every slot of a mesh), never one handed out
    before in this run (a port a test's processes have just left may still be in TIME_WAIT)."""
    for _ in range(1000):
        base = random.randrange(PORT_RANGE[0], PORT_RANGE[1], 10)
        if base not in _given and all(_free(base + i) for i in range(width)):
            _given.add(base)
            return base
    raise RuntimeError(f"no {width} free ports in a row between {PORT_RANGE[0]} and {PORT_RANGE[1]} on 127.0.0.1")


def alive(session: zenoh.Session, robot: str = ROBOT) -> set[str]:
    """The services whose liveliness token ``session`` sees (``alive/<service>``)."""
    names = set()
    for reply in session.liveliness().get(keys.key(robot, "alive/*"), timeout=1.0):
        if reply.ok is not None:
            names.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
    return names


class Pipeline:
    """The processes of one end-to-end test on a mesh of their own (module docstring)."""

    def __init__(self, tmp: Path, *, port: int | None = None) -> None:
        """``port``: the mesh's base port (default: a free one)."""
        self.tmp = tmp
        self.port = free_base_port() if port is None else port
        self.profile = tmp / "profile.toml"
        self.configure("")
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self._ends: set[str] = set()  # labels of processes that end by themselves (a session's end)
        self._stopped: set[str] = set()

    def configure(self, sections: str) -> None:
        """Write the profile: the mesh, the recordings in the test's folder, and the test's own ``sections`` (TOML,
        not ``[zenoh]`` or ``[recorder]``), before anything starts."""
        self.profile.write_text(f'[zenoh]\nbase_port = {self.port}\n[recorder]\ndirectory = "{self.tmp}"\n'
                                f"{sections}")

    @property
    def zenoh(self) -> ZenohSection:
        """The mesh, for the test's own sessions."""
        return ZenohSection(base_port=self.port)

    @contextmanager
    def session(self) -> Iterator[zenoh.Session]:
        """A plain Zenoh session on the mesh (a peer listening on a free port)."""
        with zenoh.open(zenoh_config(self.zenoh)) as session:
            yield session

    def node(self, robot: str = ROBOT) -> Node:
        """A node on the mesh without a liveliness token (the test is no service)."""
        return Node("test", robot, self.zenoh, token=False)

    # -- processes ---------------------------------------------------------------------------------------------
    def argv(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "nwr.services.cli", "--profile", str(self.profile), *args]

    def run(self, *args: str, timeout_s: float = 120.0, env: Mapping[str, str] | None = None
            ) -> subprocess.CompletedProcess[str]:
        """``nwr ARGS`` to its end: its exit code, stdout and stderr. If it has not ended within ``timeout_s``, its
        group is killed and the test fails."""
        proc = subprocess.Popen(self.argv(*args), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                                start_new_session=True)
        try:
            out, err = proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            _kill_group(proc.pid)
            out, err = proc.communicate()
            raise AssertionError(f"nwr {' '.join(args)} did not end within {timeout_s:.0f} s:\n"
                                 f"{out[-LOG_TAIL:]}\n{err[-LOG_TAIL:]}") from None
        finally:
            _kill_group(proc.pid)  # what is left of its group
        return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)

    def start(self, label: str, *args: str, env: Mapping[str, str] | None = None, ends: bool = False
              ) -> subprocess.Popen[bytes]:
        """``nwr ARGS`` in the background (``env``: its whole environment, default this one's), its output
        appended to ``<label>.log``; ``ends``: it ends by itself (a session's end), not a failure while waiting.
        A label started again (a restart) replaces the process it named."""
        running = self.procs.get(label)
        if running is not None and running.poll() is None:
            raise ValueError(f"{label} is running already (pid {running.pid})")
        with (self.tmp / f"{label}.log").open("ab") as log:  # the child keeps its own descriptor
            proc = subprocess.Popen(self.argv(*args), stdout=log, stderr=subprocess.STDOUT, env=env,
                                    start_new_session=True)
        self.procs.pop(label, None)  # a restart goes to the end of the stop order
        self.procs[label] = proc
        self._stopped.discard(label)
        (self._ends.add if ends else self._ends.discard)(label)
        return proc

    def log(self, label: str) -> str:
        path = self.tmp / f"{label}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def logs(self) -> str:
        """The end of every process's log, for a failure's message."""
        return "".join(f"\n--- {label}.log\n{self.log(label)[-LOG_TAIL:]}" for label in self.procs)

    def wait(self, label: str, timeout_s: float) -> int:
        """The exit code of a process that ends by itself; if it has not within ``timeout_s``, it is stopped
        (SIGINT) and the test fails."""
        try:
            return self.procs[label].wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.stop(label, grace_s=30.0)
            raise AssertionError(f"{label} did not end within {timeout_s:.0f} s{self.logs()}") from None

    def stop(self, label: str, *, sig: signal.Signals = signal.SIGINT, grace_s: float = 60.0) -> int:
        """Stop one process: ``sig``, then SIGKILL to its group after ``grace_s``; its exit code. What is left
        of its group (services a launcher did not stop) is killed too."""
        proc = self.procs[label]
        self._stopped.add(label)
        if proc.poll() is None:
            proc.send_signal(sig)
            try:
                proc.wait(grace_s)
            except subprocess.TimeoutExpired:
                _kill_group(proc.pid)
                proc.wait()
        _kill_group(proc.pid)
        return proc.returncode

    def stop_all(self, *, sig: signal.Signals = signal.SIGINT, grace_s: float = 60.0) -> dict[str, int]:
        """Stop every process still running, the last started first; every exit code. A process that cannot be
        stopped does not keep the others running: they are stopped first, then its error is raised."""
        codes: dict[str, int] = {}
        failed: BaseException | None = None
        for label in reversed(list(self.procs)):
            try:
                codes[label] = self.stop(label, sig=sig, grace_s=grace_s)
            except BaseException as exc:  # re-raised once the others are stopped
                _kill_group(self.procs[label].pid)
                failed = failed or exc
        if failed is not None:
            raise failed
        return codes

    def __enter__(self) -> Pipeline:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.stop_all(grace_s=30.0)

    # -- waiting -----------------------------------------------------------------------------------------------
    def exited(self) -> dict[str, int]:
        """The processes that should run but have exited, and their codes."""
        return {label: code for label, proc in self.procs.items()
                if label not in self._ends and label not in self._stopped and (code := proc.poll()) is not None}

    def wait_until(self, condition: Callable[[], T], timeout_s: float, what: str, every_s: float = 0.1) -> T:
        """Poll ``condition`` until it returns something true, and return that; fail naming ``what``, with the
        logs, if it has not within ``timeout_s`` or a process that should run has exited."""
        deadline = time.monotonic() + timeout_s
        while True:
            value = condition()
            if value:
                return value
            dead = self.exited()
            if dead:
                raise AssertionError(f"waiting for {what}: exited {dead}{self.logs()}")
            if time.monotonic() > deadline:
                raise AssertionError(f"waiting for {what}: not within {timeout_s:.0f} s{self.logs()}")
            time.sleep(every_s)

    def wait_alive(self, session: zenoh.Session, services: set[str], timeout_s: float = WAIT_S, what: str = "",
                   robot: str = ROBOT) -> set[str]:
        """Until every one of ``services`` has its liveliness token; the services alive then."""
        return self.wait_until(lambda: (seen := alive(session, robot)) >= services and seen, timeout_s,
                               what or f"{', '.join(sorted(services))} alive")


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        pass  # the group is gone: every process of it has exited
