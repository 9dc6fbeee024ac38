"""The bench's ROS 1 chain (nwr.services.tools.bench.ros1): whether it can run, its messages' sizes, and a real run
on a rosmaster of its own (the system's Python with rospy), every sample through the three hops."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import pytest
from ros_support import free_port, require

from nwr.services.tools.bench import bare as bench_bare
from nwr.services.tools.bench import ros1 as bench_ros1


def test_without_rosmaster_on_the_path_the_chain_says_why_in_one_line(tmp_path: Path) -> None:
    why = bench_ros1.available(path=str(tmp_path))  # an empty directory: no rosmaster
    assert isinstance(why, str) and "rosmaster is not on PATH" in why and "\n" not in why
    python = str(tmp_path / "python3")
    why = bench_ros1.available(python=python, path=str(tmp_path))
    assert isinstance(why, str) and f"{python} does not exist" in why and "\n" not in why


def test_the_templates_are_the_pipeline_messages_and_hold_their_headers() -> None:
    encode = msgspec.msgpack.Encoder().encode
    t = 10**13
    s = bench_bare.sample(299, t)
    p = bench_bare.pain(s, t + 1)
    c = bench_bare.command(p, t + 2)
    templates = bench_ros1.templates(300)
    # The same sizes as the bare chain's messages at that sequence number (stamps of the same width).
    assert {k: len(v) for k, v in templates.items()} == {"sample": len(encode(s)), "pain": len(encode(p)),
                                                        "command": len(encode(c))}
    assert len(templates["sample"]) >= bench_ros1.HEAD_SAMPLE.size
    assert min(len(templates["pain"]), len(templates["command"])) >= bench_ros1.HEAD_TRACE.size


@pytest.mark.slow
def test_the_ros1_chain_delivers_every_sample_through_three_hops(tmp_path: Path) -> None:
    require("rospy", "std_msgs", rosmaster=True)
    run = bench_ros1.measure(100.0, 3.0, tmp_path / "work", free_port())
    assert run.sent == 300 and run.received == run.sent > 200  # lost == 0
    assert all(math.isfinite(x) and x > 0.0 for x in run.latency_ms)
    assert run.cpu_percent_total > 0.0 and run.wall_s > 0.0
