"""A UR e-Series controller emulator that the unmodified ``ur_rtde`` library talks to.

Run it with ``python -m nwr.services.tools.hardware.ur_emulator --host 127.0.0.1``; then
``rtde_receive.RTDEReceiveInterface("127.0.0.1")`` and
``rtde_control.RTDEControlInterface("127.0.0.1")`` connect to it as to a real
arm (or URSim).

What it serves
--------------
* RTDE (port 30004, protocol version 2, per Universal Robots' RTDE guide):
  protocol negotiation, controller version (reported as 5.15.0), output and
  input recipes, start / pause, DATA_PACKAGEs out at the requested rate (at
  most 500 Hz), DATA_PACKAGEs in (stored in the input registers), text
  messages (logged).
* The dashboard server (port 29999): the welcome line and the handful of
  commands ur_rtde issues, answered as a robot in remote control with no
  program loaded.
* The script port (30003): the control script ur_rtde uploads is stored, and
  its behaviour is emulated in Python (it is not interpreted): the register
  protocol of ur_rtde's ``rtde_control.script`` (input_int_register_0 = the
  command, input_double_registers = its arguments, output_int_register_0 = 1
  ready / 2 done) for servoJ, speedJ, servoStop, speedStop, stopJ, the RTDE
  watchdog and stopping the script; every other command is acknowledged
  without an effect.

Fault injection
---------------
``--control-port PORT`` opens a line-based control port on 127.0.0.1 (never
elsewhere), one answer line per command line:

* ``protective stop``: safety mode PROTECTIVE_STOP and its status bits, the
  control script stops and the arm decelerates to rest (a stop of category
  2). Cleared by the dashboard's ``unlock protective stop``, refused for
  ``--protective-unlock-delay`` seconds after the stop (5 s, as on e-Series).
* ``emergency stop``: safety mode ROBOT_EMERGENCY_STOP and its bits, the
  script stops, the arm decelerates to rest and is then powered off (category
  1). Cleared by ``release emergency stop`` (the button), then the
  dashboard's ``power on`` and ``brake release``.
* ``stop program``: the control script stopped as from the pendant (the
  dashboard's ``stop`` does the same).
* ``drop [S]``: every RTDE, dashboard and script connection closed; new ones
  refused for S seconds (default 0).
* ``stall S``: RTDE input ignored for S seconds, as if the client had gone
  silent: the RTDE watchdog, once armed, stops the script.
* ``offset J X S [speedj]``: a hostile controller: joint J's (index 0-5)
  reported position (``actual_q``) offset by X rad for S seconds while the
  arm itself moves as commanded; with ``speedj``, from the next speedJ the
  client sends (a velocity reflex's onset) rather than now.
* ``freeze S [speedj|stop]``: no RTDE data sent to any client for S seconds,
  the connections open (a controller whose data stream stalls); with
  ``speedj`` from the next speedJ the client sends, with ``stop`` once the
  client has seen the control script's answer to its next stop
  (``servoStop``, ``speedStop``, ``stopJ``): the script's last report says
  busy, and ur_rtde's next command waits for its readiness until the data
  flows again.
* ``nan J S``: joint J's reported position and speed not a number for S
  seconds.
  Each records a fault (``offset`` / ``freeze``) with the true arm's fastest
  joint speeds (``peak_qd``, from the fault to 1 s after it ended) and its
  joint positions meanwhile (``track``: [t, q0..q5] every other control
  period, 4 ms of the arm's motion: ``t`` is the controller's clock when it was
  integrated), for a test
  to tell what the real arm would have done.
* ``state``: the controller's state as one JSON line (joints, modes, whether
  the script runs, each fault with the controller's monotonic time of the
  fault, of the arm's rest after it and of the script's next start, motion
  commands received meanwhile, and every change of the command register with
  its receipt time).
* anything else: answered as the dashboard server would (``unlock protective
  stop``, ``power on``, ``brake release``, ``power off``, ...).

While the arm is not powered, its brakes are not released or a safety stop is
in force, an uploaded control script is not started, as on a real controller.

The arm is a kinematic 6-joint UR10e integrated at 500 Hz with the joint
position and speed limits of the packaged URDF and the acceleration limits of
``common/robots/ur10e/robot.toml``.

Structure: the protocol (packing and unpacking RTDE packages), the variable
table and :class:`Controller` (registers, the emulated control script and the
arm) are pure and socket-free; :class:`Emulator` adds the three TCP servers,
one thread per connection, plus the 500 Hz controller thread.

ur_rtde fixes its ports (RTDE 30004 and dashboard 29999; the script goes to
30003): they are options here for other clients, but ur_rtde reaches only the
defaults. Nothing here resolves names: bind addresses are used as given.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import socket
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from nwr.common.pacing import realtime
from nwr.services.tools.hardware.rtde import (
    CONTROL_PACKAGE_PAUSE,
    CONTROL_PACKAGE_SETUP_INPUTS,
    CONTROL_PACKAGE_SETUP_OUTPUTS,
    CONTROL_PACKAGE_START,
    CONTROLLER_VERSION,
    DATA_PACKAGE,
    GET_URCONTROL_VERSION,
    IN_USE,
    MAX_FREQUENCY_HZ,
    NOT_FOUND,
    REQUEST_PROTOCOL_VERSION,
    TEXT_MESSAGE,
    RtdeProtocolError,
    _names,
    data_recipe_id,
    pack_bool_reply,
    pack_controller_version,
    pack_data,
    pack_setup_reply,
    parse_protocol_version,
    parse_setup_inputs,
    parse_setup_outputs,
    parse_text_message,
    split_packages,
    unpack_data,
    variable_type,
)
from nwr.services.tools.hardware.ur_arm import (
    DT,
    PROTECTIVE_UNLOCK_DELAY_S,
    ROBOT_MODE_NAMES,
    SAFETY_MODE_NAMES,
    ur10e_arm,
)
from nwr.services.tools.hardware.ur_controller import (
    Controller,
)

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- RTDE sessions


@dataclasses.dataclass
class Recipe:
    recipe_id: int
    names: list[str]
    types: list[str]
    frequency: float = 0.0


class RtdeSession:
    """One RTDE client's protocol state, socket-free: packages in, reply bytes out.

    ``claims`` is shared by every session of a server: which session writes
    which input variable (the controller refuses a second writer with IN_USE).
    """

    def __init__(self, controller: Controller, claims: dict[str, int], claims_lock: threading.Lock) -> None:
        self.controller = controller
        self.claims = claims
        self.claims_lock = claims_lock
        self.protocol = 1
        self.outputs: dict[int, Recipe] = {}
        self.inputs: dict[int, Recipe] = {}
        self.started = False
        # Input and output recipes are numbered apart, each from 1 (ur_rtde relies on it).
        self.next_output = 1
        self.next_input = 1

    def handle(self, command: int, payload: bytes) -> bytes:
        """React to one package; return the reply (possibly empty)."""
        if command == REQUEST_PROTOCOL_VERSION:
            version = parse_protocol_version(payload)
            accepted = version in (1, 2)
            if accepted:
                self.protocol = version
            return pack_bool_reply(command, accepted)
        if command == GET_URCONTROL_VERSION:
            return pack_controller_version()
        if command == CONTROL_PACKAGE_SETUP_OUTPUTS:
            if self.protocol >= 2:
                frequency, names = parse_setup_outputs(payload)
            else:
                frequency, names = 125.0, _names(payload, "SETUP_OUTPUTS")
            types = [variable_type(name, "output") or NOT_FOUND for name in names]
            if NOT_FOUND in types or not 0.0 < frequency <= MAX_FREQUENCY_HZ or self.started:
                log.warning("output recipe refused (frequency %g Hz, started %s): %s", frequency, self.started,
                            [n for n, t in zip(names, types, strict=True) if t == NOT_FOUND])
                return pack_setup_reply(command, 0, types)
            recipe = Recipe(self.next_output, names, types, frequency)
            self.next_output += 1
            self.outputs = {recipe.recipe_id: recipe}  # one output recipe per connection: the newest
            return pack_setup_reply(command, recipe.recipe_id, types)
        if command == CONTROL_PACKAGE_SETUP_INPUTS:
            names = parse_setup_inputs(payload)
            types = [variable_type(name, "input") or NOT_FOUND for name in names]
            with self.claims_lock:
                for i, name in enumerate(names):
                    if types[i] != NOT_FOUND and self.claims.get(name, id(self)) != id(self):
                        types[i] = IN_USE
                ok = NOT_FOUND not in types and IN_USE not in types and not self.started
                if ok:
                    for name in names:
                        self.claims[name] = id(self)
            if not ok:
                log.warning("input recipe refused: %s", dict(zip(names, types, strict=True)))
                return pack_setup_reply(command, 0, types)
            recipe = Recipe(self.next_input, names, types)
            self.next_input += 1
            self.inputs[recipe.recipe_id] = recipe
            return pack_setup_reply(command, recipe.recipe_id, types)
        if command == CONTROL_PACKAGE_START:
            self.started = bool(self.outputs) or bool(self.inputs)
            return pack_bool_reply(command, self.started)
        if command == CONTROL_PACKAGE_PAUSE:
            self.started = False
            return pack_bool_reply(command, True)
        if command == DATA_PACKAGE:
            given = self.inputs.get(data_recipe_id(payload))
            if given is None:
                raise RtdeProtocolError(f"DATA_PACKAGE for unknown input recipe {data_recipe_id(payload)}")
            if self.started:
                self.controller.write_inputs(given.names, unpack_data(payload, given.types))
            return b""
        if command == TEXT_MESSAGE:
            message, source, level = parse_text_message(payload)
            log.info("text message from %s (level %d): %s", source, level, message)
            self.controller.messages.append(message)
            return b""
        raise RtdeProtocolError(f"unexpected command {command}")

    def data_packages(self) -> bytes:
        """The output DATA_PACKAGEs of the current state."""
        out = b""
        for recipe in self.outputs.values():
            out += pack_data(recipe.recipe_id, recipe.types, self.controller.read_outputs(recipe.names))
        return out

    def release(self) -> None:
        with self.claims_lock:
            for name in [n for n, owner in self.claims.items() if owner == id(self)]:
                del self.claims[name]


# --------------------------------------------------------------------------- dashboard

POLYSCOPE_VERSION = "URSoftware 5.15.0.0 (emulated)"


class Dashboard:
    """The dashboard server's answers, socket-free."""

    welcome = "Connected: Universal Robots Dashboard Server"

    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        self.loaded = "<unnamed>"

    def answer(self, line: str) -> str:
        c = self.controller
        command = line.strip()
        lower = command.lower()
        if lower == "polyscopeversion":
            return POLYSCOPE_VERSION
        if lower == "version":
            return ".".join(map(str, CONTROLLER_VERSION))
        if lower == "robotmode":
            return f"Robotmode: {ROBOT_MODE_NAMES.get(c.robot_mode, c.robot_mode)}"
        if lower == "safetymode":
            return f"Safetymode: {SAFETY_MODE_NAMES.get(c.safety_mode, c.safety_mode)}"
        if lower == "safetystatus":
            return f"Safetystatus: {SAFETY_MODE_NAMES.get(c.safety_mode, c.safety_mode)}"
        if lower == "is in remote control":
            return "true"
        if lower == "programstate":
            return f"{'PLAYING' if c.script_running else 'STOPPED'} {self.loaded}"
        if lower == "running":
            return f"Program running: {'true' if c.script_running else 'false'}"
        if lower == "get loaded program":
            return f"Loaded program: {self.loaded}"
        if lower == "stop":
            c.stop_script("dashboard stop")
            return "Stopped"
        if lower == "pause":
            return "Pausing program"
        if lower == "play":
            return "Failed to execute: play"
        if lower.startswith("load "):
            return f"File not found: {command[5:]}"
        if lower == "power on":
            return c.power_on()
        if lower == "power off":
            return c.power_off()
        if lower == "brake release":
            return c.brake_release()
        if lower == "unlock protective stop":
            return c.unlock_protective_stop()
        if lower in ("close popup", "close safety popup", "clear operational mode"):
            return {"close popup": "closing popup", "close safety popup": "closing safety popup",
                    "clear operational mode": "No longer controlling the operational mode. "}[lower]
        if lower == "isprogramsaved":
            return f"true {self.loaded}"
        if lower == "get operational mode":
            return "NONE"
        if lower == "get serial number":
            return "20200000000"
        if lower == "get robot model":
            return "UR10"
        if lower == "quit":
            return "Disconnected"
        return f"could not understand: '{command}'"


# --------------------------------------------------------------------------- sockets


class Emulator:
    """The controller thread and the three TCP servers."""

    def __init__(self, host: str = "127.0.0.1", rtde_port: int = 30004, dashboard_port: int = 29999,
                 script_ports: Sequence[int] = (30003,), controller: Controller | None = None,
                 control_port: int | None = None) -> None:
        self.host = host
        self.controller = controller or Controller(ur10e_arm())
        self.stopping = threading.Event()
        self.connections: set[socket.socket] = set()
        self.connections_lock = threading.Lock()
        self.refuse_until = 0.0
        self.claims: dict[str, int] = {}
        self.claims_lock = threading.Lock()
        self.threads: list[threading.Thread] = []
        self.listeners: list[socket.socket] = []
        self.ports = {"rtde": rtde_port, "dashboard": dashboard_port}
        servers: list[tuple[str, str, int, Callable[[socket.socket], None]]] = [
            (host, "rtde", rtde_port, self._serve_rtde), (host, "dashboard", dashboard_port, self._serve_dashboard),
            *[(host, f"script{p}", p, self._serve_script) for p in script_ports]]
        if control_port is not None:  # fault injection: on the loopback only, whatever --host says
            servers.append(("127.0.0.1", "control", control_port, self._serve_control))
        for address, name, port, serve in servers:
            listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind((address, port))
            listener.listen(8)
            listener.settimeout(0.2)
            self.listeners.append(listener)
            self.ports[name] = listener.getsockname()[1]
            self._spawn(self._accept, listener, serve, name=f"accept-{name}")

    def _spawn(self, target: Callable[..., None], *args: Any, name: str) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        thread.start()
        self.threads.append(thread)

    def start(self) -> None:
        self._spawn(self._control_loop, name="controller")
        log.info("UR emulator on %s: %s", self.host, ", ".join(f"{k} {v}" for k, v in self.ports.items()))

    def close(self) -> None:
        self.stopping.set()
        for listener in self.listeners:
            listener.close()
        for thread in self.threads:
            thread.join(timeout=2.0)

    def _control_loop(self) -> None:
        next_tick = time.monotonic()
        while not self.stopping.is_set():
            self.controller.tick(DT)
            next_tick += DT
            delay = next_tick - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.1:
                next_tick = time.monotonic()  # overrun: do not try to catch up

    def _accept(self, listener: socket.socket, serve: Callable[[socket.socket], None]) -> None:
        while not self.stopping.is_set():
            try:
                conn, peer = listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if time.monotonic() < self.refuse_until and serve != self._serve_control:
                conn.close()  # the controller is "unreachable"
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(0.2)
            log.info("%s: connection from %s:%d", threading.current_thread().name, *peer[:2])
            self._spawn(self._guarded, serve, conn, name=f"{threading.current_thread().name}-{peer[1]}")

    def _guarded(self, serve: Callable[[socket.socket], None], conn: socket.socket) -> None:
        if serve != self._serve_control:
            with self.connections_lock:
                self.connections.add(conn)
        try:
            with conn:
                serve(conn)
        except (OSError, RtdeProtocolError) as exc:
            log.info("%s: connection closed (%s)", threading.current_thread().name, exc)
        finally:
            with self.connections_lock:
                self.connections.discard(conn)

    def drop(self, refuse_s: float = 0.0) -> int:
        """Close every RTDE, dashboard and script connection; refuse new ones for ``refuse_s``."""
        self.refuse_until = time.monotonic() + refuse_s
        self.controller.fault("drop")
        with self.connections_lock:
            dropped = list(self.connections)
        for conn in dropped:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        log.warning("dropped %d connection(s); refusing new ones for %.1f s", len(dropped), refuse_s)
        return len(dropped)

    def control(self, line: str) -> str:
        """One fault-injection command (see the module's docstring); anything else goes to the dashboard."""
        c = self.controller
        words = line.strip().lower().split()
        command = " ".join(words)
        try:
            if command == "state":
                return json.dumps(c.state())
            if command == "protective stop":
                c.protective_stop()
                return "protective stop"
            if command == "emergency stop":
                c.emergency_stop()
                return "emergency stop"
            if command == "release emergency stop":
                return c.release_emergency_stop()
            if command == "stop program":
                with c.lock:
                    c.fault("script_stopped")
                    c.stop_script("stopped at the pendant")
                return "Stopped"
            if words[:1] == ["drop"]:
                return f"dropped {self.drop(float(words[1]) if len(words) > 1 else 0.0)}"
            if words[:1] == ["offset"] and len(words) in (4, 5) and words[4:] in ([], ["speedj"]):
                c.offset(int(words[1]), float(words[2]), float(words[3]), at="".join(words[4:]))
                return f"offset joint {words[1]} by {float(words[2]):g} rad for {float(words[3]):g} s" + (
                    " from the next speedJ" if len(words) == 5 else "")
            if words[:1] == ["freeze"] and len(words) in (2, 3) and words[2:] in ([], ["speedj"], ["stop"]):
                c.freeze(float(words[1]), at="".join(words[2:]))
                return f"freezing RTDE output for {float(words[1]):g} s" + (
                    f" from the next {'speedJ' if words[2] == 'speedj' else 'stop'}" if len(words) == 3 else "")
            if words[:1] == ["nan"] and len(words) == 3:
                c.nan(int(words[1]), float(words[2]))
                return f"joint {words[1]} reported NaN for {float(words[2]):g} s"
            if words[:1] == ["stall"] and len(words) == 2:
                c.stall(float(words[1]))
                return f"stalling RTDE input for {float(words[1]):g} s"
        except ValueError as exc:
            return f"error: {exc}"
        return Dashboard(c).answer(line)

    def _serve_control(self, conn: socket.socket) -> None:
        self._serve_lines(conn, self.control, "control")

    def _serve_lines(self, conn: socket.socket, answer: Callable[[str], str], what: str) -> None:
        """A line-based server (the dashboard, the control port): one answer a line, logged (not ``state``)."""
        buffer = b""
        while not self.stopping.is_set():
            data = self._recv(conn)
            if data is None:
                return
            buffer += data
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                text = line.decode("utf-8", "replace")
                reply = answer(text)
                if text.strip().lower() != "state":
                    log.info("%s: %r -> %r", what, text, reply)
                conn.sendall((reply + "\n").encode())

    def _recv(self, conn: socket.socket) -> bytes | None:
        """Bytes received, b'' on a timeout, None once the peer closed."""
        try:
            data = conn.recv(65536)
        except TimeoutError:
            return b""
        return data or None

    def _serve_rtde(self, conn: socket.socket) -> None:
        session = RtdeSession(self.controller, self.claims, self.claims_lock)
        send_lock = threading.Lock()
        closed = threading.Event()

        def sender() -> None:
            next_send = time.monotonic()
            while not (closed.is_set() or self.stopping.is_set()):
                period = 1.0 / MAX_FREQUENCY_HZ
                if session.started and session.outputs and not self.controller.frozen():
                    period = 1.0 / next(iter(session.outputs.values())).frequency
                    data = session.data_packages()
                    try:
                        with send_lock:
                            conn.sendall(data)
                    except OSError:
                        closed.set()
                        return
                next_send += period
                delay = next_send - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                else:
                    next_send = time.monotonic()

        self._spawn(sender, name=f"{threading.current_thread().name}-out")
        buffer = b""
        try:
            while not (closed.is_set() or self.stopping.is_set()):
                data = self._recv(conn)
                if data is None:
                    break
                packages, buffer = split_packages(buffer + data)
                for command, payload in packages:
                    reply = session.handle(command, payload)
                    if reply:
                        with send_lock:
                            conn.sendall(reply)
        finally:
            closed.set()
            session.release()

    def _serve_dashboard(self, conn: socket.socket) -> None:
        dashboard = Dashboard(self.controller)
        conn.sendall((dashboard.welcome + "\n").encode())
        self._serve_lines(conn, dashboard.answer, "dashboard")

    def _serve_script(self, conn: socket.socket) -> None:
        """Collects programs: a program is complete at a top-level ``end`` or after 100 ms of silence."""
        buffer = ""
        last = time.monotonic()
        while not self.stopping.is_set():
            data = self._recv(conn)
            if data is None:
                break
            if data:
                buffer += data.decode("utf-8", "replace")
                last = time.monotonic()
                program, buffer = take_program(buffer)
                if program is not None:
                    self._run_program(program)
            elif buffer.strip() and time.monotonic() - last > 0.1:
                self._run_program(buffer)
                buffer = ""
        if buffer.strip():
            self._run_program(buffer)

    def _run_program(self, text: str) -> None:
        if text.lstrip().startswith(("def ", "sec ")):
            self.controller.load_script(text)
        else:
            log.info("script port: one-off script statements ignored: %r", text.strip()[:200])


def take_program(buffer: str) -> tuple[str | None, str]:
    """Split off a complete top-level program (``def``/``sec`` ... ``end`` at column 0)."""
    lines = buffer.splitlines(keepends=True)
    started = False
    for i, line in enumerate(lines):
        if line.startswith(("def ", "sec ")):
            started = True
        elif started and line.rstrip() == "end" and line.endswith("\n"):
            return "".join(lines[:i + 1]), "".join(lines[i + 1:])
    return None, buffer


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m nwr.services.tools.hardware.ur_emulator",
                                     description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--rtde-port", type=int, default=30004, help="ur_rtde always uses 30004")
    parser.add_argument("--dashboard-port", type=int, default=29999, help="ur_rtde's control interface uses 29999")
    parser.add_argument("--script-port", type=int, action="append",
                        help="where programs are accepted (repeatable; default 30003, ur_rtde's choice)")
    parser.add_argument("--q0", type=float, nargs=6, metavar="RAD", help="initial joint positions (default: home)")
    parser.add_argument("--control-port", type=int, metavar="PORT",
                        help="fault injection: a line-based control port on 127.0.0.1 (see the docstring)")
    parser.add_argument("--protective-unlock-delay", type=float, default=PROTECTIVE_UNLOCK_DELAY_S, metavar="S",
                        help="'unlock protective stop' is refused this long after the stop (e-Series: 5 s)")
    parser.add_argument("--realtime-priority", type=int, default=0, metavar="P",
                        help="run under SCHED_FIFO at priority P (1-99; 0: off): a real controller is a machine of "
                             "its own, and an emulator starved beside a loaded pipeline trips its own watchdog")
    parser.add_argument("--verbose", "-v", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(threadName)s: %(message)s")
    if not 0 <= args.realtime_priority <= 99:
        parser.error(f"--realtime-priority {args.realtime_priority}: give 1-99, or 0 for the normal scheduler")
    realtime(args.realtime_priority, "ur emulator")  # before its threads start: they inherit it
    emulator = Emulator(args.host, args.rtde_port, args.dashboard_port, args.script_port or [30003],
                        Controller(ur10e_arm(args.q0), protective_unlock_delay_s=args.protective_unlock_delay),
                        control_port=args.control_port)
    emulator.start()
    print(f"ready {emulator.ports}", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        emulator.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
