"""What forged messages on the open (non-TLS) embedded network cost a running pipeline: stops, rejections, takeovers.

    .venv/bin/python scripts/open_network_attacks.py [--runs 3] [--as stale|bare|informed]

Starts ``nwr up --planners cartesian,uniform`` on loopback (a free base port, a recording in a temporary
folder), lets the arm do its task, then a peer on the same mesh attacks, one attack at a time, 4 s apart:

- ``none``: nothing for 3 s (the control: what the machine's load alone costs);
- ``state``: forged robot states at 50 Hz for 3 s, the bridge's stream continued (seq and stamp just ahead, its
  pose) but naming the standby planner the active one;
- ``seq``: one copy of the active planner's last command with its seq 450 ahead;
- ``token``: a stranger's planner token (``alive/planner-stranger``), a switch to it, and its position commands
  towards a pose 0.5 rad from the arm's, for 3 s;
- ``channels``: 10,000 diagnostics, each on a key of its own (``diag/x<n>``).

The attacker is, with ``--as``: ``stale`` a peer of another pipeline instance (its messages carry that instance,
as a stale process of an earlier run or a second, misconfigured pipeline); ``bare`` a bare Zenoh session (no
instance at all); ``informed`` one that read this pipeline's instance from its tokens and carries it.

Printed per run, from the recording: the bridge's controlled stops (its own states' ``stopping`` rising), the
commands it rejected, the owners its states named, the largest distance of the arm from the planners' own
commanded poses (rad, where a takeover shows), and the channels the recording holds. Figures depend on the load
of the machine: print ``uptime`` beside them.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import zenoh
from mcap.reader import make_reader

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import ZenohSection
from nwr.common.node import INSTANCE_ENV, SLOTS, zenoh_config
from nwr.common.recordings import RecordingError, read_recording
from nwr.services.recorder.salvage import recover_file

ROBOT = keys.DEFAULT_ROBOT
ACTIVE = "cartesian"
FORGED_SEQ_AHEAD = 450
CHANNELS = 10_000
FORGED = "forged by open_network_attacks.py"  # the forged states' detail: how the figures tell them apart
ATTACKS = ("none", "state", "seq", "token", "channels")


def free_base_port() -> int:
    for _ in range(1000):
        base = random.randrange(20000, 29000, 10)
        ok = True
        for i in range(max(SLOTS.values()) + 1):
            with socket.socket() as s:
                try:
                    s.bind(("127.0.0.1", base + i))
                except OSError:
                    ok = False
                    break
        if ok:
            return base
    raise RuntimeError("no free base port")


class Attacker:
    """A peer on the mesh that puts forged messages, carrying ``instance`` (None: nothing) as a pipeline would."""

    def __init__(self, session: zenoh.Session, instance: str | None) -> None:
        self.session = session
        self.attachment = None if instance is None else instance.encode()
        self.latest: dict[str, Any] = {}
        self.lock = threading.Lock()
        for relative in (keys.ROBOT_STATE, keys.robot_command(ACTIVE)):
            session.declare_subscriber(keys.key(ROBOT, relative), self._keep(relative))

    def _keep(self, relative: str) -> Any:
        codec = keys.codec(relative)

        def on_sample(sample: zenoh.Sample) -> None:
            with self.lock:
                self.latest[relative] = codec.decode(sample.payload.to_bytes())
        return on_sample

    def put(self, relative: str, message: Any) -> None:
        self.session.put(keys.key(ROBOT, relative), keys.codec(relative).encode(message), attachment=self.attachment)

    def none(self) -> None:
        """No attack: the control, for the stops the machine's load alone causes."""
        time.sleep(3.0)

    def state(self) -> None:
        with self.lock:
            real = self.latest[keys.ROBOT_STATE]
        seq, stamp = real.seq + 5, real.stamp_ns
        for i in range(150):  # the bridge's stream continued, but naming the standby planner the active one
            self.put(keys.ROBOT_STATE, msgspec.structs.replace(real, seq=seq + i, stamp_ns=stamp + (i + 1) * 20_000_000,
                                                               owner="uniform", detail=FORGED))
            time.sleep(0.02)

    def seq(self) -> None:
        with self.lock:
            real = self.latest[keys.robot_command(ACTIVE)]
        self.put(keys.robot_command(ACTIVE), msgspec.structs.replace(real, seq=real.seq + FORGED_SEQ_AHEAD))

    def token(self) -> None:
        token = self.session.liveliness().declare_token(keys.key(ROBOT, keys.alive("planner-stranger")))
        time.sleep(0.5)
        with self.lock:
            real = self.latest[keys.ROBOT_STATE]
        self.put(keys.CONTROL_ACTIVE, m.SwitchRequest(seq=1, stamp_ns=time.monotonic_ns(), name="stranger",
                                                      requested_by="stranger"))
        start, target = np.asarray(real.q), np.asarray(real.q) + 0.5
        for i in range(1500):  # 3 s at 500 Hz, a smooth ramp towards the target
            s = min(1.0, i / 1000)
            q = start + (target - start) * (3 * s**2 - 2 * s**3)
            self.put(keys.robot_command("stranger"), m.PositionCommand(
                seq=i, stamp_ns=time.monotonic_ns(), owner="stranger", q=q.tolist(), trace=m.Trace(0, 0)))
            time.sleep(0.002)
        token.undeclare()

    def channels(self) -> None:
        for i in range(CHANNELS):
            self.put(keys.diag(f"x{i}"), m.Diagnostic(seq=i, stamp_ns=time.monotonic_ns(), service=f"x{i}",
                                                      level="info", code="x", message="x"))


def run_once(tmp: Path, mode: str) -> dict[str, Any]:
    port = free_base_port()
    profile = tmp / "profile.toml"
    output = tmp / "session.mcap"
    profile.write_text(f'[zenoh]\nbase_port = {port}\n[recorder]\ndirectory = "{tmp}"\n')
    env = {k: v for k, v in os.environ.items() if not k.startswith("NWR_")}
    log = (tmp / "up.log").open("wb")
    up = subprocess.Popen([sys.executable, "-m", "nwr.services.cli", "--profile", str(profile), "up", "--planners",
                           f"{ACTIVE},uniform", "--output", str(output)], stdout=log, stderr=subprocess.STDOUT,
                          env=env, start_new_session=True)
    times: dict[str, int] = {}
    try:
        with zenoh.open(zenoh_config(ZenohSection(base_port=port))) as session:
            deadline = time.monotonic() + 60
            instance = ""
            while time.monotonic() < deadline:
                found = [keys.parse_owner(keys.relative_key(ROBOT, str(r.ok.key_expr)))
                         for r in session.liveliness().get(keys.key(ROBOT, "owner/**"), timeout=1.0) if r.ok]
                services = {o.service for o in found if o}
                if {"bridge", "gain", "gateway", f"planner-{ACTIVE}", "planner-uniform"} <= services:
                    instance = next(o.instance for o in found if o)
                    break
                time.sleep(0.2)
            else:
                raise RuntimeError(f"the pipeline did not start:\n{(tmp / 'up.log').read_text()[-3000:]}")
            carried = {"stale": "another.1.1", "bare": None, "informed": instance}[mode]
            attacker = Attacker(session, carried)
            time.sleep(3.0)
            for name in ATTACKS:
                times[name] = time.monotonic_ns()
                getattr(attacker, name)()
                time.sleep(4.0)
    finally:
        up.send_signal(signal.SIGINT)
        try:
            up.wait(180)
        except subprocess.TimeoutExpired:
            os.killpg(up.pid, signal.SIGKILL)
        log.close()
    unfinished = False
    try:
        records, _ = read_recording(output)
    except RecordingError:  # the recorder did not finish in time (10,000 channels take it long): what it saved
        unfinished = True
        recover_file(output, tmp / "recovered.mcap")
        output = tmp / "recovered.mcap"
        records, _ = read_recording(output)
    with output.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    own = [r.message for r in records if r.key == keys.ROBOT_STATE and r.message.detail != FORGED]
    commands = [r.message.q for r in records if r.key in (keys.robot_command(ACTIVE), keys.robot_command("uniform"))
                and isinstance(r.message, m.PositionCommand) and r.message.owner != "stranger"]
    planned = np.asarray(commands)

    def away(state: m.RobotState) -> float:
        return float(np.min(np.max(np.abs(planned - np.asarray(state.q)), axis=1)))

    per: dict[str, dict[str, Any]] = {}
    bounds = [*times.values(), own[-1].stamp_ns + 1]
    for (name, start), end in zip(times.items(), bounds[1:], strict=True):
        window = [s for s in own if start <= s.stamp_ns < end]
        before = [s for s in own if s.stamp_ns < start]
        per[name] = {
            "stops": sum(1 for a, b in zip(window, window[1:], strict=False) if b.stopping and not a.stopping),
            "rejected": (window[-1].rejected - before[-1].rejected) if window and before else None,
            "owners": sorted({s.owner for s in window}),
            "away_rad": round(max((away(s) for s in window), default=0.0), 3),
        }
    return {"per_attack": per, "channels": len(summary.channels), "unfinished": unfinished, "instance": instance,
            "foreign_diags": sum(1 for r in records if r.key.startswith("diag/")
                                 and getattr(r.message, "code", "") == "foreign_instance")}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--as", dest="mode", choices=("stale", "bare", "informed"), default="stale")
    args = parser.parse_args()
    if os.environ.get(INSTANCE_ENV):
        parser.error(f"unset {INSTANCE_ENV}: the pipeline this script starts must have an instance of its own")
    results = []
    for i in range(args.runs):
        with tempfile.TemporaryDirectory() as tmp:
            result = run_once(Path(tmp), args.mode)
        results.append(result)
        print(f"run {i + 1} (attacker: {args.mode}): {result}", flush=True)
    for attack in ATTACKS:
        line = []
        for name in ("stops", "rejected", "away_rad"):
            values = [r["per_attack"][attack][name] or 0 for r in results]
            line.append(f"{name} median {np.median(values):g} (max {max(values):g})")
        owners = sorted({o for r in results for o in r["per_attack"][attack]["owners"]})
        print(f"{attack:>8s}: {', '.join(line)}, owners {owners}")
    channels = [r["channels"] for r in results]
    print(f"channels in the recording: median {np.median(channels):g} (max {max(channels)}); recordings the recorder "
          f"did not finish within 180 s of the stop: {sum(r['unfinished'] for r in results)} of {len(results)}")
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
