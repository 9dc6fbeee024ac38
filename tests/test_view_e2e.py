"""The view over real processes: a short simulated session, watched through a Foxglove WebSocket client.

A minimal client of the Foxglove WebSocket protocol (``websockets``) connects
to ``nwr demo --view PORT``: checks the advertised channels and schemas, that
each frame's link transforms match the model's FK at the joint state it was
built from, that a touched pad's colour and arrow follow its gain, and that the
scene rate stays at its cap (from message timestamps) while the planner
commands at 500 Hz. Then ``nwr view FILE`` serves the recording with play,
pause and seek.
"""

from __future__ import annotations

import asyncio
import base64
import json
import signal
import socket
import struct
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
import websockets
from pipeline import SHORT_SCRIPT, Pipeline
from test_view import CHANNELS, DESC, MODEL, arrow_length, protobuf_decoder, rgba, transforms_of

from nwr.common import keys
from nwr.common.recordings import read_recording
from nwr.services.view import core as c
from nwr.services.view.export import export_foxglove

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

SUBPROTOCOL = "foxglove.sdk.v1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Capture:
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)  # topic -> advertised channel
    messages: dict[str, list[tuple[int, bytes]]] = field(default_factory=dict)  # topic -> [(log time, payload)]
    states: list[tuple[int, int, float]] = field(default_factory=list)  # playback states: status, time, speed

    def decoded(self, topic: str) -> list[tuple[int, Any]]:
        channel = self.channels[topic]
        if channel["encoding"] == "json":
            return [(t, json.loads(data)) for t, data in self.messages.get(topic, [])]
        decode = protobuf_decoder(channel["schemaName"], channel["schemaEncoding"], base64.b64decode(channel["schema"]))
        return [(t, decode(data)) for t, data in self.messages.get(topic, [])]


class Client:
    """Just enough of the Foxglove WebSocket protocol (v1) to subscribe and drive playback."""

    def __init__(self, ws: Any, capture: Capture) -> None:
        self.ws = ws
        self.capture = capture
        self.by_subscription: dict[int, str] = {}

    @classmethod
    async def connect(cls, port: int, capture: Capture, timeout_s: float = 30.0) -> Client:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL],
                                              max_size=None)
                return cls(ws, capture)
            except OSError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.2)

    async def pump(self, until: Any, timeout_s: float) -> None:
        """Handle messages (subscribing to every advertised channel) until ``until()`` or the timeout."""
        deadline = time.monotonic() + timeout_s
        while not until() and time.monotonic() < deadline:
            try:
                message = await asyncio.wait_for(self.ws.recv(), 0.2)
            except TimeoutError:
                continue
            except websockets.ConnectionClosed:
                return
            if isinstance(message, str):
                op = json.loads(message)
                if op["op"] == "advertise":
                    subscriptions = []
                    for channel in op["channels"]:
                        self.capture.channels[channel["topic"]] = channel
                        sub = len(self.by_subscription) + 1
                        self.by_subscription[sub] = channel["topic"]
                        subscriptions.append({"id": sub, "channelId": channel["id"]})
                    await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
            elif message[0] == 0x01:  # message data: subscription id, log time, payload
                sub, log_time = struct.unpack_from("<IQ", message, 1)
                self.capture.messages.setdefault(self.by_subscription[sub], []).append((log_time, message[13:]))
            elif message[0] == 0x05:  # playback state
                status, current, speed = struct.unpack_from("<BQf", message, 1)
                self.capture.states.append((status, current, speed))

    async def playback(self, play: bool, speed: float = 1.0, seek_ns: int | None = None) -> None:
        request_id = f"r{time.monotonic_ns()}".encode()
        await self.ws.send(struct.pack("<BBfBQI", 0x03, 0 if play else 1, speed, seek_ns is not None,
                                       seek_ns or 0, len(request_id)) + request_id)


def run_client(port: int, until: Any, timeout_s: float, script: Any = None) -> Capture:
    capture = Capture()

    async def main() -> None:
        client = await Client.connect(port, capture)
        try:
            if script is None:
                await client.pump(until, timeout_s)
            else:
                await script(client, capture)
        finally:
            await client.ws.close()

    asyncio.run(main())
    return capture


def test_live_view_and_recording_playback(tmp_path, pipeline: Pipeline):
    recording = tmp_path / "session.mcap"
    port = free_port()
    demo = pipeline.start("demo", "demo", "--world", "scripted", "--script", str(SHORT_SCRIPT), "--output",
                          str(recording), "--view", str(port), ends=True)
    live = run_client(port, until=lambda: demo.poll() is not None, timeout_s=60.0)
    code = pipeline.wait("demo", 30)
    log = pipeline.log("demo")
    assert code == 0, log
    assert "all 4 scripted touches as expected" in log, log

    # -- advertised channels and their schemas -------------------------------------------
    for spec in CHANNELS:
        channel = live.channels[spec.topic]
        assert (channel["encoding"], channel["schemaName"], channel["schemaEncoding"]) == \
            (spec.message_encoding, spec.schema_name, spec.schema_encoding), spec.topic
    assert live.channels["/tf"]["schemaName"] == "foxglove.FrameTransforms"
    assert live.channels["/nwr/pads"]["schemaName"] == "foxglove.SceneUpdate"

    # -- every frame's transforms are the model's FK at a published joint state ---------------
    records, _ = read_recording(recording)
    published = {r.message.seq: r.message.q for r in records if r.key == "robot/state"}
    robot = dict(live.decoded("/nwr/robot"))
    tf = live.decoded("/tf")
    assert len(tf) > 100
    links = {j.child for j in c.urdf_joints(__import__("xml.etree.ElementTree").etree.ElementTree.fromstring(
        json.loads(live.messages["/robot_description"][0][1])["data"]))}
    checked = 0
    for t, message in tf:
        state = robot[t]  # the joint state this frame was built from, same log time
        q = np.array(state["q"])
        if state["seq"] in published:  # the recorder may have started a little later than the view
            assert published[state["seq"]] == state["q"]
        poses = c.compose(transforms_of(message), DESC.base_frame)
        assert set(poses) >= links
        for link in links:
            assert np.abs(poses[link][:3, 3] - MODEL.frame_pose(q, link)[:3, 3]).max() < 1e-6, (t, link)
        checked += 1
    assert checked == len(tf)

    # -- the touched pad's colour and arrow follow its gain -------------------------------------
    skin = live.decoded("/nwr/skin")
    skin_times = [t for t, _ in skin]
    contact = dict(live.decoded("/nwr/contact"))
    touched = 0
    strongest_gain = 0.0
    for t, update in live.decoded("/nwr/pads"):
        k = c.index_at(skin_times, t)
        if k == 0:
            continue
        gains = skin[k - 1][1]["gain"]  # the newest skin sample at this frame
        strongest = skin[k - 1][1]["strongest"]
        for entity in update.entities:
            name = entity.id.removeprefix("pad/")
            meta = {kv.key: kv.value for kv in entity.metadata}
            assert float(meta["gain"]) == pytest.approx(gains[name])
            assert rgba(entity.cubes[0].color) == pytest.approx(c.gain_color(gains[name]))
        arrows = [a for e in contact[t].entities for a in e.arrows]
        if strongest["gain"] > 0:
            touched += 1
            strongest_gain = max(strongest_gain, strongest["gain"])
            assert len(arrows) == 1 and arrow_length(arrows[0]) == pytest.approx(c.ARROW_MAX_M * strongest["gain"])
            assert {kv.key: kv.value for kv in contact[t].entities[0].metadata}["pad"] == strongest["pad"]
        else:
            assert not arrows and contact[t].deletions
    assert touched > 3 and strongest_gain > 0.5  # both reflex touches were seen, wrist_2's near G = 1

    # -- the state machine, the reflex ghost and the onsets -----------------------------------
    modes = {p["mode"] for _, p in live.decoded("/nwr/planner")}
    assert {"TASK", "REFLEX", "RETURNING"} <= modes
    assert any(u.entities for _, u in live.decoded("/nwr/reflex"))
    onsets = [o for _, o in live.decoded("/nwr/onset")]
    assert len(onsets) >= 2 and all(0 < o["latency_ms"] < 1000 for o in onsets)

    # -- the scene's rate stays at its cap while the planner commands the arm at 500 Hz ------------------
    times = np.array([t for t, _ in tf], dtype=float)
    intervals = np.diff(times) / 1e9
    rate = (len(times) - 1) / ((times[-1] - times[0]) / 1e9)
    assert np.median(intervals) == pytest.approx(1 / c.DEFAULT_RATE_HZ, rel=0.1)
    assert 0.8 * c.DEFAULT_RATE_HZ <= rate <= 1.02 * c.DEFAULT_RATE_HZ
    task = [r.message for r in records if keys.is_command(r.key) and r.message.phase == "TASK"]
    commands = np.array([cmd.stamp_ns for cmd in task], dtype=float)
    # One task command per 10 cycles, each with the next 10 setpoints: 500 setpoints a second.
    command_rate = 1e9 / np.median(np.diff(commands)) * np.median([len(cmd.ahead) for cmd in task])
    assert command_rate == pytest.approx(500, rel=0.1)
    stats = [s for _, s in live.decoded("/nwr/view")]
    assert stats
    cpu = [s["cpu_percent"] for s in stats[1:]] or [stats[0]["cpu_percent"]]
    print(f"\nview: scene {rate:.1f} Hz (median interval {1e3 * np.median(intervals):.1f} ms) while the planner "
          f"commanded {command_rate:.0f} setpoints/s; view CPU {np.median(cpu):.1f} % median, {max(cpu):.1f} % worst "
          f"(of one core, whole process); " + "; ".join(
              f"{topic} {len(msgs) / ((times[-1] - times[0]) / 1e9):.1f}/s" for topic, msgs in live.messages.items()))
    for line in log.splitlines():
        if "view:" in line and "CPU" in line:
            print(line)

    # -- the recording, exported, and served with play, pause and seek ------------------------------
    exported = tmp_path / "session-foxglove.mcap"
    report = export_foxglove(recording, exported)
    assert report.added["/tf"] > 100
    port = free_port()
    pipeline.start("view", "view", str(exported), "--port", str(port))
    try:
        async def script(client: Client, capture: Capture) -> None:
            await client.pump(lambda: "/tf" in capture.channels and capture.states == [] and len(
                client.by_subscription) >= len(CHANNELS), 20.0)
            await asyncio.sleep(0.3)
            await client.pump(lambda: False, 0.3)
            assert not capture.messages.get("/tf"), "paused at the start: nothing is sent"
            start = records[0].log_time_ns
            seek = start + 5_000_000_000
            await client.playback(True, speed=2.0, seek_ns=seek)
            await client.pump(lambda: len(capture.messages.get("/tf", [])) >= 30, 10.0)
            await client.playback(False)
            await client.pump(lambda: any(s[0] == 1 for s in capture.states[1:]), 5.0)
            capture.messages["/tf"].clear()
            await client.pump(lambda: False, 0.5)
            assert not capture.messages["/tf"], "paused: no frame is sent"
            await client.playback(False, seek_ns=start + 1_000_000_000)  # seek while paused
            await client.pump(lambda: bool(capture.messages["/tf"]), 5.0)

        playback = run_client(port, until=None, timeout_s=30.0, script=script)
    finally:
        code = pipeline.stop("view", sig=signal.SIGTERM, grace_s=15.0)
    assert code in (0, -15), pipeline.log("view")
    start = records[0].log_time_ns
    status, current, speed = playback.states[0]
    assert status == 0 and speed == pytest.approx(2.0) and current == pytest.approx(start + 5e9, abs=1e8)  # playing
    assert any(s[0] == 1 for s in playback.states)  # paused
    tf_times = [t for t, _ in playback.messages["/tf"]]
    assert tf_times and all(abs(t - (start + 1e9)) < 0.05e9 for t in tf_times)  # the frame at the paused seek
