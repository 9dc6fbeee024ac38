"""An optional baseline for the bench: the bare chain's three hops in ROS 1 (rospy).

The same shape as :mod:`nwr.services.tools.bench.bare`: four processes
(gateway -> gain -> planner -> bridge), each stage taking what it receives
and publishing the next message from its subscriber callback; the gateway
publishes at the skin's rate, the bridge stamps each command's arrival. The
chain's latency is the skin sample's stamp (at the gateway) to that arrival.
:func:`measure` starts a ``rosmaster --core`` of its own on 127.0.0.1
(``ROS_MASTER_URI``, ``ROS_IP`` and ``ROS_HOSTNAME`` on loopback, so no node
addresses another host) and returns a :class:`~nwr.services.tools.bench.bare.BareRun`.

rospy lives in the system's Python (``/usr/bin/python3``, Debian's
``python3-rospy``), not in the project's environment, and the system's
Python has neither msgspec nor this package. So the roles are this file run
as a script by the system's Python: that part imports only the standard
library, rospy and std_msgs. The chain does what the bare chain does:

- The pipeline's numbers, as float arrays. Each message is a
  ``std_msgs/Float64MultiArray`` holding the numbers of the pipeline's
  message (the bare chain's :func:`~nwr.services.tools.bench.bare.sample`,
  ``pain`` and ``command``): a sample its sequence number and stamp and the
  ten pads' absolute pressure, baseline, change, contact and validity (52
  values); a pain message its own and its sample's sequence number and stamp
  and the pads' level and gain (24); a command the same four and the six
  joint targets (10). ROS has no message of the pipeline's types without a
  build of its own; a float array is what a lab's quick rospy node would
  send. Stamps are ``time.monotonic_ns`` as float64: exact below 2^53 ns
  (104 days of uptime). :data:`SAMPLE_LEN`, :data:`PAIN_LEN` and
  :data:`COMMAND_LEN` follow the bare chain's messages (a test checks them).
- The same work per stage. rospy decodes each array on arrival (genpy
  unpacks the floats into a tuple) before the callback; the callback reads
  the stamps, builds the next message's numbers and publishes it (rospy
  encodes it). As the bare chain's stage decodes with msgspec, builds the
  next Struct and encodes it.
- Stamps are ``time.monotonic_ns`` in every process (one clock per machine
  on Linux), as in the bare chain.
- Tuned as a lab tuning rospy for latency would: every subscriber asks for
  ``tcp_nodelay`` (and every publisher sets it). The chain's publishers and
  subscribers have ``queue_size`` 100 or 1 (``--queue``; ``nwr bench`` runs
  both): rospy's documentation asks for an explicit queue size; 100 holds
  100 ms of a 1 kHz stream, so a short stall delays samples rather than
  dropping them (the bare chain blocks instead of dropping), 1 keeps only
  the newest, as a control loop's subscriber is usually set, and drops the
  rest (counted as lost). With a queue size, rospy's publish hands each
  message to a writer thread per connection: that is how rospy is normally
  used.

No sample is lost to start-up: a stage that publishes writes
``<work>/<role>.ready`` once its publisher has a subscriber connected (the
next stage's), and the gateway starts only when the gain's and the
planner's are there, its own publisher has the gain connected and its start
and end topics have all three other roles. Each role writes
``<work>/<role>.json``: its CPU time (every thread's, ``time.process_time``)
from the gateway's start message to its end message; the gateway adds the
rosmaster's CPU time over the same span (from ``/proc``), the bridge the
arrivals ``[seq, stamp_ns, arrival_ns]`` and the gateway's figures (sent,
publishing wall time). The CPU % is the four roles and the rosmaster over
the gateway's publishing time, % of one core, as the bare chain's.

``python -m nwr.services.tools.bench.ros1 --rate 25 --duration 5`` runs it
once and prints the figures. A role is
``/usr/bin/python3 bench_ros1.py ROLE --rate R --duration D --queue Q --work DIR --master-pid PID``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import xmlrpc.client
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from nwr.services.tools.bench.bare import BareRun

SYSTEM_PYTHON = "/usr/bin/python3"  # the interpreter with rospy (Debian's python3-rospy)
ROLES = ("bridge", "planner", "gain", "gateway")  # the start order: the source last
TOPIC = "/nwr_bench/{}"
START = TOPIC.format("start")
END = TOPIC.format("end")
QUEUE_SIZES = (100, 1)  # publishers' and subscribers', the two nwr bench runs (see the module's docstring)
N_PADS = 10
N_JOINTS = 6
# The float arrays: [seq, stamp_ns, absolute, baseline, change, contact, valid (a value per pad each)];
# [seq, stamp_ns, the sample's seq, its stamp_ns, level, gain (per pad)]; [the same four, q (per joint)].
SAMPLE_LEN = 2 + 5 * N_PADS
PAIN_LEN = 4 + 2 * N_PADS
COMMAND_LEN = 4 + N_JOINTS
Q = [0.1, -1.2, 1.3, -1.6, -1.57, 0.0]  # the bare chain's command target
STARTUP_TIMEOUT_S = 30.0
MASTER_TIMEOUT_S = 20.0


# ------------------------------------------------------------------------------ one role (the system's Python)


def run_role(role: str, *, rate_hz: float, duration_s: float, queue: int, work: Path, master_pid: int) -> int:
    """One process of the chain, run by the system's Python; the gateway publishes once every other role is ready.

    Imports only the standard library, rospy and std_msgs. The role's figures go to ``work/<role>.json``.
    """
    here = os.path.realpath(os.path.dirname(os.path.abspath(__file__)))
    # Run as a script, this file's directory comes first on sys.path: its modules must not shadow rospy's imports.
    sys.path[:] = [p for p in sys.path if os.path.realpath(p or ".") != here]
    import rospy
    from std_msgs.msg import Empty, Float64MultiArray, String

    rospy.init_node(f"nwr_bench_{role}", disable_signals=True)  # SIGTERM ends the process
    if role == "gateway":
        return _publish(rospy, Empty, String, Float64MultiArray, rate_hz=rate_hz, duration_s=duration_s,
                        queue=queue, work=work, master_pid=master_pid)

    arrivals: list[tuple[int, int, int]] = []  # (seq, sample stamp, arrival), the bridge's
    out: Any = None
    if role == "gain":
        out = rospy.Publisher(TOPIC.format("pain"), Float64MultiArray, queue_size=queue, tcp_nodelay=True)
        level, gain = [1.0] * N_PADS, [0.0] * N_PADS  # the bare chain's pain: no touch

        def on_pressure(msg: Any) -> None:
            d = msg.data
            seq, stamp = d[0], d[1]
            out.publish(Float64MultiArray(data=[seq, float(time.monotonic_ns()), seq, stamp, *level, *gain]))

        rospy.Subscriber(TOPIC.format("pressure"), Float64MultiArray, on_pressure, queue_size=queue,
                         tcp_nodelay=True)
    elif role == "planner":
        out = rospy.Publisher(TOPIC.format("command"), Float64MultiArray, queue_size=queue, tcp_nodelay=True)

        def on_pain(msg: Any) -> None:
            d = msg.data
            out.publish(Float64MultiArray(data=[d[0], float(time.monotonic_ns()), d[2], d[3], *Q]))

        rospy.Subscriber(TOPIC.format("pain"), Float64MultiArray, on_pain, queue_size=queue, tcp_nodelay=True)
    else:
        def on_command(msg: Any) -> None:
            now = time.monotonic_ns()
            d = msg.data
            if len(d) == COMMAND_LEN:
                arrivals.append((int(d[2]), int(d[3]), now))

        rospy.Subscriber(TOPIC.format("command"), Float64MultiArray, on_command, queue_size=queue,
                         tcp_nodelay=True)

    done = threading.Event()
    end: dict[str, Any] = {}
    cpu0 = [time.process_time()]

    def on_start(_msg: Any) -> None:
        cpu0[0] = time.process_time()

    def on_end(msg: Any) -> None:
        end.update(json.loads(msg.data))  # the gateway's figures
        done.set()

    rospy.Subscriber(START, Empty, on_start, queue_size=10, tcp_nodelay=True)
    rospy.Subscriber(END, String, on_end, queue_size=10, tcp_nodelay=True)
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while out is not None and out.get_num_connections() < 1 and time.monotonic() < deadline:
        time.sleep(0.01)  # the next stage's subscriber connected: nothing published from here on is lost
    if out is None or out.get_num_connections() >= 1:
        (work / f"{role}.ready").touch()
    done.wait(duration_s + STARTUP_TIMEOUT_S + 30.0)
    figures: dict[str, Any] = {"cpu_s": time.process_time() - cpu0[0]}
    if role == "bridge":
        # The end comes straight from the gateway, the last commands three hops behind it: wait for them,
        # a lost one 2 s (as the bare chain's bridge).
        deadline = time.monotonic() + 2.0
        while len(arrivals) < int(end.get("sent", 0)) and time.monotonic() < deadline:
            time.sleep(0.01)
        figures.update(arrivals=list(arrivals), **end)
    _write_json(work / f"{role}.json", figures)
    rospy.signal_shutdown("the bench chain is done")
    return 0 if done.is_set() else 1


def _publish(rospy: Any, empty: Any, string: Any, array: Any, *, rate_hz: float, duration_s: float, queue: int,
             work: Path, master_pid: int) -> int:
    """The gateway: wait for the others, publish ``duration_s`` of samples at ``rate_hz``, then the end."""
    pub = rospy.Publisher(TOPIC.format("pressure"), array, queue_size=queue, tcp_nodelay=True)
    start = rospy.Publisher(START, empty, queue_size=10, tcp_nodelay=True)
    end = rospy.Publisher(END, string, queue_size=10, tcp_nodelay=True)
    others = ("gain", "planner", "bridge")

    def ready() -> bool:
        return (pub.get_num_connections() >= 1 and start.get_num_connections() >= len(others)
                and end.get_num_connections() >= len(others)
                and all((work / f"{r}.ready").exists() for r in ("gain", "planner")))

    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while not ready():
        if time.monotonic() > deadline:
            missing = [r for r in ("gain", "planner") if not (work / f"{r}.ready").exists()]
            print(f"ros1 chain: not ready after {STARTUP_TIMEOUT_S:g} s: {missing} not connected downstream, "
                  f"{pub.get_num_connections()} subscriber(s) of the samples, {start.get_num_connections()} of "
                  f"the start, {end.get_num_connections()} of the end", file=sys.stderr)
            return 1
        time.sleep(0.02)
    time.sleep(0.3)  # as the bare chain: the connections settle
    period_ns = round(1e9 / rate_hz)
    n = int(round(duration_s * rate_hz))
    baseline, change, flags, valid = [1013.0] * N_PADS, [0.01] * N_PADS, [0.0] * N_PADS, [1.0] * N_PADS
    overruns = 0
    next_ns = time.monotonic_ns() + period_ns
    start.publish(empty())
    cpu0 = time.process_time()
    master0 = _proc_cpu_s(master_pid)
    t0 = time.monotonic()
    for seq in range(n):
        delay = next_ns - time.monotonic_ns()  # absolute deadlines, as nwr.common.pacing.Rate
        if delay > 0:
            time.sleep(delay / 1e9)
            next_ns += period_ns
        else:
            next_ns += (-delay // period_ns + 1) * period_ns
            overruns += 1
        # The bare chain's sample: the pads' absolute pressure, baseline, change, contact and validity.
        pressures = [1013.0 + 0.01 * (seq % 7)] * N_PADS
        pub.publish(array(data=[float(seq), float(time.monotonic_ns()), *pressures, *baseline, *change, *flags,
                                *valid]))
    wall = time.monotonic() - t0
    time.sleep(0.2)  # the last sample through the chain before the end stops it
    end.publish(string(data=json.dumps({"sent": n, "publish_wall_s": wall, "overruns": overruns})))
    figures = {"cpu_s": time.process_time() - cpu0, "master_cpu_s": _proc_cpu_s(master_pid) - master0}
    _write_json(work / "gateway.json", figures)
    # rospy writes from a thread per connection: stay until the others have had the end (and written theirs).
    deadline = time.monotonic() + 10.0
    while not all((work / f"{r}.json").exists() for r in others) and time.monotonic() < deadline:
        time.sleep(0.02)
    rospy.signal_shutdown("the bench chain is done")
    return 0


def _proc_cpu_s(pid: int) -> float:
    """CPU time (s, user + system) of a live process, from /proc/PID/stat (fields 14 and 15 of proc(5))."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    tmp.replace(path)  # whole or not at all: the gateway waits for it to exist


# ------------------------------------------------------------------------------ the whole chain (the project's Python)


def available(python: str = SYSTEM_PYTHON, path: str | None = None) -> str | None:
    """None when ``python`` imports rospy and std_msgs and ``rosmaster`` is on ``path`` (default: PATH), else why."""
    missing = []
    if shutil.which("rosmaster", path=path) is None:
        missing.append("rosmaster is not on PATH")
    if not Path(python).exists():
        missing.append(f"{python} does not exist")
    else:
        try:
            proc = subprocess.run([python, "-c", "import rospy, std_msgs.msg"], capture_output=True, text=True,
                                  timeout=60)
        except (OSError, subprocess.TimeoutExpired) as exc:
            missing.append(f"{python} cannot run ({exc})")
        else:
            if proc.returncode != 0:
                last = (proc.stderr.strip().splitlines() or ["?"])[-1]
                missing.append(f"{python} cannot import rospy and std_msgs ({last})")
    if not missing:
        return None
    return "; ".join(missing) + " (Debian: apt install python3-rospy python3-std-msgs python3-rosmaster)"


def measure(rate_hz: float, duration_s: float, work: Path, port: int, queue: int = QUEUE_SIZES[0]) -> BareRun:
    """Start a rosmaster on 127.0.0.1:``port`` and the four roles (queues of ``queue``), run ``duration_s``,
    collect the figures.

    Raises RuntimeError when ROS 1 is missing (:func:`available`), the port is taken, or a role fails.
    Everything it starts is stopped before it returns.
    """
    from nwr.services.tools.bench.bare import BareRun

    why = available()
    if why is not None:
        raise RuntimeError(f"the ROS 1 chain cannot run: {why}")
    rosmaster = shutil.which("rosmaster")
    assert rosmaster is not None
    work.mkdir(parents=True, exist_ok=True)
    for pattern in ("*.json", "*.ready", "*.tmp"):
        for stale in work.glob(pattern):
            stale.unlink()
    with socket.socket() as s:  # a master already there would answer in place of ours
        try:
            s.bind(("127.0.0.1", port))
        except OSError as exc:
            raise RuntimeError(f"the ROS 1 chain's port 127.0.0.1:{port} is taken ({exc})") from exc
    env = dict(os.environ)
    env.update(ROS_MASTER_URI=f"http://127.0.0.1:{port}", ROS_IP="127.0.0.1", ROS_HOSTNAME="127.0.0.1",
               ROS_HOME=str(work / "ros_home"), ROS_LOG_DIR=str(work / "ros_home" / "log"))
    procs: dict[str, subprocess.Popen[bytes]] = {}
    try:
        procs["rosmaster"] = _spawn([rosmaster, "--core", "-p", str(port)], work / "rosmaster.log", env)
        _wait_master(port, procs["rosmaster"], work / "rosmaster.log")
        script = str(Path(__file__).resolve())
        for role in ROLES:
            procs[role] = _spawn([SYSTEM_PYTHON, script, role, "--rate", str(rate_hz), "--duration", str(duration_s),
                                  "--queue", str(queue), "--work", str(work),
                                  "--master-pid", str(procs["rosmaster"].pid)],
                                 work / f"{role}.log", env)
        try:
            code = procs["gateway"].wait(duration_s + STARTUP_TIMEOUT_S + 30.0)
        except subprocess.TimeoutExpired:
            code = None
        if code != 0:
            raise RuntimeError(f"the ROS 1 chain's gateway failed ({code}): {_tail(work / 'gateway.log')}")
        for role in ("bridge", "planner", "gain"):
            try:
                procs[role].wait(10.0)
            except subprocess.TimeoutExpired:
                raise RuntimeError(f"the ROS 1 chain's {role} did not end: {_tail(work / f'{role}.log')}") from None
    finally:
        for proc in reversed(procs.values()):  # the roles, then the master
            _stop(proc)
    missing = [role for role in ROLES if not (work / f"{role}.json").exists()]
    if missing:
        raise RuntimeError(f"the ROS 1 chain's {missing} wrote no figures: "
                           + " | ".join(_tail(work / f"{role}.log") for role in missing))
    figures = {role: json.loads((work / f"{role}.json").read_text()) for role in ROLES}
    data = figures["bridge"]
    latency = [(arrival - stamp) / 1e6 for _seq, stamp, arrival in data["arrivals"]]
    wall = float(data["publish_wall_s"])
    cpu = float(figures["gateway"]["master_cpu_s"]) + sum(float(f["cpu_s"]) for f in figures.values())
    return BareRun(latency, int(data["sent"]), len(latency), 100.0 * cpu / max(wall, 1e-9), wall)


def _spawn(args: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen[bytes]:
    with log.open("wb") as out:  # the child has its own descriptor
        return subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT, env=env)


def _wait_master(port: int, proc: subprocess.Popen[bytes], log: Path) -> None:
    """Until the master on ``port`` answers over XML-RPC as ``proc`` (its pid): not another process's."""
    deadline = time.monotonic() + MASTER_TIMEOUT_S
    with xmlrpc.client.ServerProxy(f"http://127.0.0.1:{port}") as master:  # closes its connection
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                raise RuntimeError(f"the ROS 1 chain's rosmaster exited ({proc.returncode}): {_tail(log)}")
            try:
                reply: Any = master.getPid("/nwr_bench")  # [code, status message, pid]
                if reply[0] == 1 and reply[2] == proc.pid:
                    return
            except (OSError, xmlrpc.client.Error):
                pass
            time.sleep(0.1)
    raise RuntimeError(f"the ROS 1 chain's rosmaster did not answer on port {port}: {_tail(log)}")


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)


def _tail(log: Path, chars: int = 1500) -> str:
    try:
        return log.read_text(errors="replace")[-chars:]
    except OSError as exc:
        return f"(no log: {exc})"


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ROLES:  # a role, run by the system's Python
        role_parser = argparse.ArgumentParser(prog="bench_ros1.py", description="One role of the bench's ROS 1 chain.")
        role_parser.add_argument("role", choices=ROLES)
        role_parser.add_argument("--rate", type=float, required=True)
        role_parser.add_argument("--duration", type=float, required=True)
        role_parser.add_argument("--queue", type=int, required=True)
        role_parser.add_argument("--work", type=Path, required=True, help="the role's figures")
        role_parser.add_argument("--master-pid", type=int, required=True)
        r = role_parser.parse_args(argv)
        return run_role(r.role, rate_hz=r.rate, duration_s=r.duration, queue=r.queue, work=r.work,
                        master_pid=r.master_pid)

    parser = argparse.ArgumentParser(prog="python -m nwr.services.tools.bench.ros1",
                                     description="The bench's ROS 1 chain, once: latency p50/p99, lost, CPU.")
    parser.add_argument("--rate", type=float, default=25.0, help="samples per second (default 25)")
    parser.add_argument("--duration", type=float, default=5.0, help="seconds of publishing (default 5)")
    parser.add_argument("--queue", type=int, default=QUEUE_SIZES[0],
                        help=f"the publishers' and subscribers' queue size (default {QUEUE_SIZES[0]})")
    parser.add_argument("--port", type=int, default=0, help="the rosmaster's port (default: a free one)")
    parser.add_argument("--work", type=Path, help="directory for the logs and figures (default: a temporary one)")
    args = parser.parse_args(argv)
    why = available()
    if why is not None:
        print(f"ros1 chain: {why}", file=sys.stderr)
        return 2
    from nwr.services.tools.bench.bare import percentiles

    port = args.port or free_port()
    with tempfile.TemporaryDirectory(prefix="nwr-bench-ros1-") as tmp:
        run = measure(args.rate, args.duration, args.work or Path(tmp), port, args.queue)
    pct = percentiles(run.latency_ms)
    print(f"ros1 chain, {args.rate:g} Hz for {args.duration:g} s, queues of {args.queue}: p50 {pct['p50']:.3f} ms, "
          f"p99 {pct['p99']:.3f} ms, "
          f"lost {run.sent - run.received} of {run.sent}, CPU {run.cpu_percent_total:.1f}% of one core "
          f"(four roles and the rosmaster, over {run.wall_s:.2f} s of publishing)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
