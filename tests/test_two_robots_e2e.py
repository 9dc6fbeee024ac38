"""A lab with two robots: two pipelines, two robot names, one Zenoh router, no crosstalk.

One ``nwr router`` on loopback; two ``nwr demo`` sessions of the short
script, each its own robot (``arm-a``, ``arm-b``) and its own recordings,
both connecting to it as clients. Each session runs as its script says,
each recording holds its own robot's keys and no other's, and ``nwr status``
of one robot names the other on the same mesh.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from pipeline import SHORT_SCRIPT, Pipeline, free_base_port

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ROBOTS = ("arm-a", "arm-b")


def robot_profile(p: Pipeline, robot: str, router_port: int) -> None:
    p.profile.write_text(f'[robot]\nname = "{robot}"\n[zenoh]\nmode = "client"\n'
                         f'router = ["tcp/127.0.0.1:{router_port}"]\nbase_port = {p.port}\n'
                         f'[recorder]\ndirectory = "{p.tmp}"\n')


def topics(path: Path) -> set[str]:
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return {channel.topic for channel in summary.channels.values()}


def test_two_robots_through_one_router_run_apart(tmp_path: Path) -> None:
    router_port = free_base_port(1)
    for name in ("router", "a", "b"):
        (tmp_path / name).mkdir()
    with Pipeline(tmp_path / "router") as router, Pipeline(tmp_path / "a") as a, Pipeline(tmp_path / "b") as b:
        router.start("router", "router", "--listen", f"tcp/127.0.0.1:{router_port}")
        time.sleep(1.0)
        arms = {"arm-a": a, "arm-b": b}
        for robot, p in arms.items():
            robot_profile(p, robot, router_port)
            p.start("demo", "demo", "--world", "scripted", "--script", str(SHORT_SCRIPT),
                    "-o", str(p.tmp / f"{robot}.mcap"), ends=True)
        # While both run: each robot's status names the other on the mesh.
        status = a.wait_until(
            lambda: (lambda r: r.stdout if "other robots on this mesh: arm-b" in r.stdout else None)(
                a.run("status", "--window", "0.5", timeout_s=60.0)),
            timeout_s=60.0, what="nwr status of arm-a naming arm-b")
        assert "robot arm-a via tcp/127.0.0.1" in status
        for robot, p in arms.items():
            assert p.wait("demo", timeout_s=180.0) == 0, p.logs()
            assert "scripted touches as expected" in p.log("demo"), p.log("demo")
            seen = topics(p.tmp / f"{robot}.mcap")
            other = next(r for r in ROBOTS if r != robot)
            assert seen and all(t.startswith(f"nwr/{robot}/") for t in seen), sorted(seen)
            assert not any(f"nwr/{other}/" in t for t in seen)
