"""A reflex planner written outside the project's services: a starting point for a lab.

It speaks the pipeline's keys and messages and nothing else, so the bridge
follows it like any planner once it is the active one:

- announces itself with the liveliness token ``nwr/<robot>/alive/planner-<name>``, and
  holds the owner token of the pipeline it belongs to,
  ``nwr/<robot>/owner/planner-<name>/<instance>/<host>/<pid>/<since>``: the bridge follows
  only a planner of its own pipeline (``<instance>`` is ``NWR_INSTANCE``, which ``nwr up``
  and ``nwr replay --planner-cmd`` give the processes they start; ``-`` beside services
  started alone);
- reads ``skin/pain`` (per-pad gain, strongest contact) and ``robot/state``;
- writes ``robot/command/<name>`` (joint position targets signed with its name, the
  trace of the skin sample it acted on, a reflex number and the phase) and
  ``reflex/<name>/status``.

Its behaviour is deliberately simple: hold the pose it found; on a contact
with a gain above zero, fold shoulder and elbow away by an amount scaled by
the gain, then come back, each leg a cosine-eased move of ``--leg-s``.

    python examples/minimal_planner.py --name mini --base-port 7450
    nwr replay recordings/session.mcap --planner-cmd "python examples/minimal_planner.py --name mini" --name mini

Only the message module of the project is used (for the wire format); the
session is opened with plain zenoh, multicast scouting off and explicit
loopback endpoints, as every process of the pipeline does.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import signal
import socket
import threading
import time

import msgspec
import numpy as np
import zenoh

from nwr.common import messages as m

# Shoulder lift -, elbow +: the arm draws in (the UR10e's reflex directions).
WITHDRAWAL_RAD = np.array([0.0, -0.35, 0.6, 0.0, 0.0, 0.0])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--name", default="mini", help="planner name (the bridge follows it once it is active)")
    parser.add_argument("--robot", default="ur10e")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--base-port", type=int, default=7450, help="the pipeline's first port (its [zenoh] base_port)")
    parser.add_argument("--rate", type=float, default=250.0, help="command rate, Hz")
    parser.add_argument("--leg-s", type=float, default=0.6, help="duration of the withdrawal and of the return, s")
    args = parser.parse_args()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/{args.host}:0"]))
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/{args.host}:{args.base_port + i}" for i in range(5)]))
    prefix = f"nwr/{args.robot}"
    encode = msgspec.msgpack.Encoder().encode
    pain_decoder = msgspec.msgpack.Decoder(m.SkinPain)
    state_decoder = msgspec.msgpack.Decoder(m.RobotState)

    lock = threading.Lock()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    shared: dict = {"q": None, "trace": m.Trace(-1, 0), "reflex": None, "reflex_seq": 0, "owner": ""}

    def on_pain(sample: zenoh.Sample) -> None:
        try:
            pain = pain_decoder.decode(sample.payload.to_bytes())
        except msgspec.ValidationError:
            return  # a malformed message is dropped, never half-used
        with lock:
            shared["trace"] = pain.trace
            c = pain.strongest
            if c is not None and c.gain > 0 and shared["reflex"] is None and shared["q"] is not None:
                shared["reflex_seq"] += 1
                shared["reflex"] = (time.monotonic(), shared["q"].copy(), c.gain)

    def on_state(sample: zenoh.Sample) -> None:
        try:
            state = state_decoder.decode(sample.payload.to_bytes())
        except msgspec.ValidationError:
            return
        with lock:
            shared["owner"] = state.owner
            if shared["q"] is None or state.owner != args.name:
                shared["q"] = np.asarray(state.q)  # hold where the arm is until we move it

    with zenoh.open(conf) as session:
        token = session.liveliness().declare_token(f"{prefix}/alive/planner-{args.name}")
        # (each part one chunk of a key: letters, digits, '_', '.', '-')
        instance, host = (re.sub(r"[^A-Za-z0-9_.-]", "_", text) or "-"
                          for text in (os.environ.get("NWR_INSTANCE", ""), socket.gethostname()))
        owner = session.liveliness().declare_token(
            f"{prefix}/owner/planner-{args.name}/{instance}/{host}/{os.getpid()}/{int(time.time())}")
        session.declare_subscriber(f"{prefix}/skin/pain", on_pain)
        session.declare_subscriber(f"{prefix}/robot/state", on_state)
        commands = session.declare_publisher(f"{prefix}/robot/command/{args.name}", priority=zenoh.Priority.REAL_TIME,
                                             express=True)
        status = session.declare_publisher(f"{prefix}/reflex/{args.name}/status")
        seq = 0
        period = 1.0 / args.rate
        next_t = time.monotonic()
        while not stop.is_set():
            next_t += period
            stop.wait(max(0.0, next_t - time.monotonic()))
            with lock:
                if shared["q"] is None:
                    continue
                mode, q = "TASK", shared["q"]
                if shared["reflex"] is not None:
                    t0, q0, gain = shared["reflex"]
                    s = (time.monotonic() - t0) / args.leg_s
                    if s >= 2.0:
                        shared["reflex"], q = None, q0
                    else:
                        mode = "REFLEX" if s < 1.0 else "RETURNING"
                        ease = 0.5 - 0.5 * math.cos(math.pi * (s if s < 1.0 else 2.0 - s))
                        q = q0 + gain * ease * WITHDRAWAL_RAD
                    shared["q"] = q
                active = shared["owner"] == args.name
                trace, reflex_seq = shared["trace"], shared["reflex_seq"]
            if not active:
                continue  # only the active planner commands; the others stay quiet
            now = time.monotonic_ns()
            commands.put(encode(m.PositionCommand(seq=seq, stamp_ns=now, owner=args.name, q=q.tolist(), trace=trace,
                                                  reflex_seq=reflex_seq, phase=mode)))
            if seq % 25 == 0 or mode != "TASK":
                status.put(encode(m.PlannerStatus(seq=seq, stamp_ns=now, name=args.name, strategy="minimal",
                                                  mode=mode, task_time_s=0.0)))
            seq += 1
        token.undeclare()
        owner.undeclare()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
