"""The bench's baseline: the pipeline's three hops as a bare chain of zenoh-python processes.

What ``nwr bench`` holds the pipeline against, measured in the same run:
four processes of the pipeline's shape (gateway -> gain -> planner ->
bridge), opened with the pipeline's own Zenoh configuration
(:func:`nwr.common.node.zenoh_config`: peers on loopback at the services'
ports, or clients of a local router), sending the pipeline's own messages
(the same sizes, encoded with msgspec, with the QoS the key registry gives
them: real-time priority, express, blocking on congestion) and doing
nothing else: each stage
decodes what it receives and publishes the next message from its Zenoh
callback; the gateway publishes ten pads at the skin's rate. The bridge
stamps each command's arrival: the chain's latency is the skin sample's
stamp to that arrival, the three hops a reflex takes. :func:`in_process`
is the same chain as function calls (the lower bound of any chain), paced
at the chain's rate like the chains it bounds.

Every process reads the same clock (``time.monotonic_ns``, one per machine
on Linux), so stamps from different processes compare directly. A role is
``python -m nwr.services.tools.bench.bare ROLE --profile P ...``; the
bridge writes its figures as JSON when the gateway's end message arrives.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import zenoh

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import ZenohSection
from nwr.common.node import qos, zenoh_config
from nwr.services.pipeline.supervisor import wait_listening

ROLES = ("bridge", "planner", "gain", "gateway")  # the start order: the source last
N_PADS = 10
KEY = "nwr-bare/{}"  # its own keys: a running pipeline's subscribers never see the chain
ALIVE = "nwr-bare/alive/{}"
START = "nwr-bare/start"
END = "nwr-bare/end"
STARTUP_TIMEOUT_S = 30.0


def sample(seq: int, stamp_ns: int) -> m.SkinPressure:
    pressures = [1013.0 + 0.01 * (seq % 7)] * N_PADS
    return m.SkinPressure(seq=seq, stamp_ns=stamp_ns, absolute_hpa=pressures, baseline_hpa=[1013.0] * N_PADS,
                          change_hpa=[0.01] * N_PADS, contact=[False] * N_PADS, valid=[True] * N_PADS)


def pain(s: m.SkinPressure, now_ns: int) -> m.SkinPain:
    return m.SkinPain(seq=s.seq, stamp_ns=now_ns, trace=m.Trace(s.seq, s.stamp_ns), model="continuous",
                      level=[1] * N_PADS, gain=[0.0] * N_PADS)


def command(p: m.SkinPain, now_ns: int) -> m.PositionCommand:
    return m.PositionCommand(seq=p.seq, stamp_ns=now_ns, owner="bare", q=[0.1, -1.2, 1.3, -1.6, -1.57, 0.0],
                             trace=p.trace)


def declare(session: zenoh.Session, role_key: str, relative: str) -> zenoh.Publisher:
    """A publisher on the chain's own key with the QoS the pipeline gives ``relative`` (priority, express, block)."""
    return session.declare_publisher(KEY.format(role_key), **qos(keys.topic_for(relative)))


def proc_cost(pid: int) -> tuple[float, float]:
    """CPU time (s, user + system) and peak RSS (MB, VmHWM) of a live process."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime (fields 14, 15 of stat(5))
    hwm = 0.0
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                hwm = int(line.split()[1]) / 1024
    return cpu, hwm



# ------------------------------------------------------------------------------ one role


def run_role(role: str, cfg: ZenohSection, *, rate_hz: float, duration_s: float, out: Path | None) -> int:
    """One process of the chain; the gateway publishes for ``duration_s`` once every other role is alive.

    Each role writes ``out/<role>.json``: its CPU time (every thread's, ``time.process_time``) from the
    gateway's start message to its end message, so that start-up (imports, opening the session) is not
    counted; the bridge adds the arrivals.
    """
    encode = msgspec.msgpack.Encoder().encode
    conf = zenoh_config(cfg, listen_slot=role)
    with zenoh.open(conf) as session:
        done = threading.Event()
        arrivals: list[tuple[int, int, int]] = []  # (seq, sample stamp, arrival), the bridge's
        subscribers: list[Any] = []
        if role == "gain":
            decode_s = msgspec.msgpack.Decoder(m.SkinPressure).decode
            out_pub = declare(session, "pain", keys.SKIN_PAIN)
            subscribers.append(session.declare_subscriber(
                KEY.format("pressure"), lambda z: out_pub.put(encode(pain(decode_s(z.payload.to_bytes()),
                                                                          time.monotonic_ns())))))
        elif role == "planner":
            decode_p = msgspec.msgpack.Decoder(m.SkinPain).decode
            out_pub = declare(session, "command", keys.robot_command("bare"))
            subscribers.append(session.declare_subscriber(
                KEY.format("pain"), lambda z: out_pub.put(encode(command(decode_p(z.payload.to_bytes()),
                                                                         time.monotonic_ns())))))
        elif role == "bridge":
            decode_c = msgspec.msgpack.Decoder(m.PositionCommand).decode

            def on_command(z: zenoh.Sample) -> None:
                now = time.monotonic_ns()
                c = decode_c(z.payload.to_bytes())
                arrivals.append((c.trace.seq, c.trace.stamp_ns, now))

            subscribers.append(session.declare_subscriber(KEY.format("command"), on_command))
        if role != "gateway":
            end: dict[str, Any] = {}
            cpu0 = [time.process_time()]

            def on_start(_z: zenoh.Sample) -> None:
                cpu0[0] = time.process_time()

            subscribers.append(session.declare_subscriber(START, on_start))

            def on_end(z: zenoh.Sample) -> None:
                end.update(json.loads(z.payload.to_bytes()))  # the gateway's figures
                done.set()

            subscribers.append(session.declare_subscriber(END, on_end))
            token = session.liveliness().declare_token(ALIVE.format(role))
            done.wait(duration_s + STARTUP_TIMEOUT_S + 30.0)
            cpu_s = time.process_time() - cpu0[0]
            figures: dict[str, Any] = {"cpu_s": cpu_s}
            if role == "bridge":
                # The end comes straight from the gateway, the last commands three hops behind it: wait for
                # them (on a loaded machine they can trail by more than the gateway's pause), a lost one 2 s.
                deadline = time.monotonic() + 2.0
                while len(arrivals) < int(end.get("sent", 0)) and time.monotonic() < deadline:
                    time.sleep(0.01)
                figures.update(arrivals=arrivals, **end)
            if out is not None:
                (out / f"{role}.json").write_text(json.dumps(figures))
            token.undeclare()
            return 0
        return _publish(session, rate_hz, duration_s, out)


def _publish(session: zenoh.Session, rate_hz: float, duration_s: float, out: Path | None) -> int:
    """The gateway: wait for the others, publish ``duration_s`` of samples at ``rate_hz``, then the end."""
    from nwr.common.pacing import Rate

    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while True:
        alive = {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in session.liveliness().get(ALIVE.format("*"))
                 if r.ok is not None}
        if alive >= {"gain", "planner", "bridge"}:
            break
        if time.monotonic() > deadline:
            print(f"bare chain: {sorted({'gain', 'planner', 'bridge'} - alive)} did not start", file=sys.stderr)
            return 1
        time.sleep(0.05)
    time.sleep(0.3)  # routes settle
    encode = msgspec.msgpack.Encoder().encode
    pub = declare(session, "pressure", keys.SKIN_PRESSURE)
    rate = Rate(rate_hz, "bare gateway")
    n = int(round(duration_s * rate_hz))
    session.put(START, b"")
    cpu0 = time.process_time()
    t0 = time.monotonic()
    for seq in range(n):
        rate.sleep()
        pub.put(encode(sample(seq, time.monotonic_ns())))
    wall = time.monotonic() - t0
    time.sleep(0.2)  # the last sample through the chain before the end stops it
    session.put(END, json.dumps({"sent": n, "publish_wall_s": wall, "overruns": rate.overruns}))
    if out is not None:
        (out / "gateway.json").write_text(json.dumps({"cpu_s": time.process_time() - cpu0}))
    return 0


# ------------------------------------------------------------------------------ the whole chain


@dataclass
class BareRun:
    latency_ms: list[float]  # per sample that arrived: stamp to the bridge
    sent: int
    received: int
    cpu_percent_total: float  # the four processes (and the router), % of one core, while the gateway published
    wall_s: float  # the gateway's publishing time


def measure(cfg: ZenohSection, rate_hz: float, duration_s: float, work: Path,
            router_listen: str | None = None) -> BareRun:
    """Start the four roles (and a router for ``router_listen``), run ``duration_s``, collect the bridge's figures."""

    work.mkdir(parents=True, exist_ok=True)
    for stale in work.glob("*.json"):
        stale.unlink()
    procs: dict[str, subprocess.Popen[bytes]] = {}
    base = [sys.executable, "-m", "nwr.services.tools.bench.bare"]
    if cfg.secure:
        raise ValueError("the bare chain runs without TLS: measure with an insecure profile")
    zargs = ["--base-port", str(cfg.base_port), "--host", cfg.host, "--mode", cfg.mode]
    if cfg.router:
        zargs += ["--router", ",".join(cfg.router)]
    router_cpu = 0.0
    try:
        if router_listen is not None:
            procs["router"] = _spawn([sys.executable, "-m", "nwr.services.cli", "router", "--listen", router_listen],
                                     work / "router.log")
            wait_listening(router_listen, procs["router"])
            router_cpu = -proc_cost(procs["router"].pid)[0]  # from here: its start-up is over
        for role in ROLES:
            procs[role] = _spawn([*base, role, *zargs, "--rate", str(rate_hz), "--duration", str(duration_s),
                                  "--out", str(work)], work / f"{role}.log")
        if procs["gateway"].wait(duration_s + STARTUP_TIMEOUT_S + 30.0) != 0:
            raise RuntimeError(f"the bare chain's gateway failed: {(work / 'gateway.log').read_text()[-500:]}")
        if "router" in procs:
            router_cpu += proc_cost(procs["router"].pid)[0]
        for role in ("bridge", "planner", "gain"):
            procs[role].wait(10.0)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.terminate()
                p.wait(5.0)
    figures = {role: json.loads((work / f"{role}.json").read_text()) for role in ROLES}
    data = figures["bridge"]
    latency = [(arrival - stamp) / 1e6 for _seq, stamp, arrival in data["arrivals"]]
    wall = float(data["publish_wall_s"])
    cpu = router_cpu + sum(f["cpu_s"] for f in figures.values())
    return BareRun(latency, int(data["sent"]), len(latency), 100.0 * cpu / max(wall, 1e-9), wall)


def _spawn(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as out:  # the child has its own descriptor
        return subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT)


def in_process(n: int, rate_hz: float | None = None) -> list[float]:
    """The same chain as function calls (encode, decode, the next message) in this process, ms per sample.

    ``rate_hz``: one sample per period, on absolute deadlines (the chains' own pacing), so that each sample
    meets the caches and the CPU's frequency and sleep states a paced chain meets; None: back to back.
    """
    from nwr.common.pacing import Rate

    encode = msgspec.msgpack.Encoder().encode
    dec_s = msgspec.msgpack.Decoder(m.SkinPressure).decode
    dec_p = msgspec.msgpack.Decoder(m.SkinPain).decode
    dec_c = msgspec.msgpack.Decoder(m.PositionCommand).decode
    rate = Rate(rate_hz, "in-process chain") if rate_hz else None
    out = []
    for seq in range(n):
        if rate is not None:
            rate.sleep()
        t = time.monotonic_ns()
        c = dec_c(encode(command(dec_p(encode(pain(dec_s(encode(sample(seq, t))), time.monotonic_ns()))),
                                 time.monotonic_ns())))
        out.append((time.monotonic_ns() - c.trace.stamp_ns) / 1e6)
    return out


def percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {"p50": float("nan"), "p99": float("nan")}
    a = np.asarray(values)
    return {"p50": float(np.median(a)), "p99": float(np.percentile(a, 99))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m nwr.services.tools.bench.bare",
                                     description="One role of the bench's bare chain (started by nwr bench).")
    parser.add_argument("role", choices=ROLES)
    parser.add_argument("--base-port", type=int, required=True)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--mode", choices=("peer", "client"), default="peer")
    parser.add_argument("--router", default="", help="comma-separated router endpoints (clients of a router)")
    parser.add_argument("--rate", type=float, default=25.0)
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--out", type=Path, help="directory for the role's figures (<role>.json)")
    args = parser.parse_args(argv)
    cfg = ZenohSection(base_port=args.base_port, host=args.host, mode=args.mode,
                       router=[e for e in args.router.split(",") if e])
    return run_role(args.role, cfg, rate_hz=args.rate, duration_s=args.duration, out=args.out)


if __name__ == "__main__":
    sys.exit(main())
