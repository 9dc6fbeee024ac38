"""What the live ROS 2 tests share: a stand-in for rmw_zenohd, a ROS 2 publisher nobody here wrote the bytes of,
and Foxglove's decoders of raw CDR."""

from __future__ import annotations

import base64
import json
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import zenoh
import zenoh.ext as zx
from pipeline import free_base_port

from nwr.common import rmw_zenoh as rz

NODE_DIR = Path(__file__).resolve().parent / "node"


def _config(mode: str, listen: list[str], connect: list[str]) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    return conf


def router_config(endpoint: str) -> zenoh.Config:
    """A Zenoh router listening on ``endpoint``, multicast scouting off: what rmw_zenohd is."""
    return _config("router", [endpoint], [])


@contextmanager
def rmw_router() -> Iterator[tuple[str, zenoh.Session]]:
    """A Zenoh router on a free loopback port, as ``rmw_zenohd`` is one: its endpoint and its session."""
    endpoint = f"tcp/127.0.0.1:{free_base_port(1)}"
    with zenoh.open(router_config(endpoint)) as session:
        yield endpoint, session


@contextmanager
def ros_client(endpoint: str) -> Iterator[zenoh.Session]:
    """A session of the ROS 2 graph's side: a client of the router, as a ROS 2 tool would be."""
    with zenoh.open(_config("client", [], [endpoint])) as session:
        yield session


def attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment made by Zenoh's own serializer (not by nwr.common.rmw_zenoh)."""
    return bytes(zx.z_serialize((zx.Int64(seq), zx.Int64(stamp_ns), gid)).to_bytes())


def foxglove_decode(node: str, types: Any, samples: list[tuple[str, bytes]]) -> list[Any]:
    """Raw CDR samples ``(msgtype, bytes)`` decoded by Foxglove's decoders under node; each type's definition is
    the one ``rosbags`` writes into bags (its .msg text with its dependencies)."""
    payload = [{"definition": types.generate_msgdef(msgtype, ros_version=2)[0],
                "data": base64.b64encode(data).decode()} for msgtype, data in samples]
    proc = subprocess.run([node, str(NODE_DIR / "decode_ros2_cdr.mjs")], cwd=NODE_DIR, input=json.dumps(payload),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return list(json.loads(proc.stdout))


def parse_token(token: str) -> list[str]:
    """rmw_zenoh_cpp's checks of a token it receives (Entity::make, liveliness_utils.cpp): the admin space, the
    entity kind, the number of parts, none empty, and a valid Zenoh key expression; its parts."""
    parts = token.split("/")
    assert parts[0] == rz.ADMIN_SPACE and all(parts), token
    assert parts[5] in ("NN", "MP", "MS") and len(parts) == (9 if parts[5] == "NN" else 13), token
    assert str(zenoh.KeyExpr(token)) == token
    return parts
