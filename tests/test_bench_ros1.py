"""The bench's ROS 1 chain (nwr.services.tools.bench.ros1): whether it can run, its messages' sizes, and a real run
on a rosmaster of its own (the system's Python with rospy), every sample through the three hops."""

from __future__ import annotations

import math
from pathlib import Path

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


def test_the_float_arrays_hold_the_numbers_of_the_bare_chains_messages() -> None:
    s = bench_bare.sample(299, 10**13)
    p = bench_bare.pain(s, 10**13 + 1)
    c = bench_bare.command(p, 10**13 + 2)
    pads = len(s.absolute_hpa)
    assert bench_ros1.N_PADS == pads == len(p.level) == len(p.gain)
    # seq and stamp; absolute, baseline, change, contact, valid per pad
    assert bench_ros1.SAMPLE_LEN == 2 + len(s.absolute_hpa + s.baseline_hpa + s.change_hpa + s.contact + s.valid)
    assert bench_ros1.PAIN_LEN == 4 + len(p.level + p.gain)  # seq, stamp and the trace's; level, gain per pad
    assert bench_ros1.COMMAND_LEN == 4 + len(c.q) and bench_ros1.Q == c.q


@pytest.mark.slow
@pytest.mark.parametrize("queue", bench_ros1.QUEUE_SIZES)
def test_the_ros1_chain_delivers_every_sample_through_three_hops(tmp_path: Path, queue: int) -> None:
    require("rospy", "std_msgs", rosmaster=True)
    run = bench_ros1.measure(100.0, 3.0, tmp_path / "work", free_port(), queue)
    assert run.sent == 300
    if queue > 1:
        assert run.received == run.sent  # lost == 0
    else:
        assert 0 < run.received <= run.sent  # a queue of 1 keeps the newest: it may drop a sample under load
    assert all(math.isfinite(x) and x > 0.0 for x in run.latency_ms)
    assert run.cpu_percent_total > 0.0 and run.wall_s > 0.0
