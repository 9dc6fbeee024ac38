"""``nwr export``: a recording for other tools: ``--foxglove IN OUT``, the recording plus the view's 3D scene
(:mod:`nwr.services.view.export`); ``--ros2 IN OUT``, a ROS 2 bag of standard messages
(:mod:`.rosbag_export`)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from nwr.services.profile import profile_for
from nwr.services.view.core import DEFAULT_RATE_HZ
from nwr.services.view.export import ExportError, export_foxglove


def register(subparsers: Any) -> None:
    export = subparsers.add_parser(
        "export", help="a recording for Foxglove (the view's 3D scene added) or as a ROS 2 bag",
        description="--foxglove IN OUT: write OUT, every record of the recording IN plus the robot description, "
                    "link transforms, pad/contact/reflex scene updates and plottable signals, so that Foxglove "
                    "shows the 3D scene of a recording without the view running. --ros2 IN OUT: write the "
                    "recording as the ROS 2 bag directory OUT (rosbag2, MCAP storage) of standard messages: "
                    "/joint_states, the skin per pad (std_msgs/Float64MultiArray), /tf, /tf_static, "
                    "/robot_description, contact and reflex markers. See docs/view.md and docs/lab.md.",
    )
    which = export.add_mutually_exclusive_group(required=True)
    which.add_argument("--foxglove", nargs=2, metavar=("IN", "OUT"), help="recording to read and file to write")
    which.add_argument("--ros2", nargs=2, metavar=("IN", "OUT"),
                       help="recording to read and ROS 2 bag directory to write (must not exist)")
    export.add_argument("--rate", type=float, default=DEFAULT_RATE_HZ,
                        help=f"scene rate (--ros2: /tf rate), Hz of log time (default: {DEFAULT_RATE_HZ:g})")
    export.set_defaults(handler=_export)


def _export(args: argparse.Namespace) -> int:
    if not args.rate > 0:
        raise ExportError(f"--rate {args.rate}: expected a positive scene rate, e.g. 30")
    profile = profile_for(args)
    description = profile.robot.description or None
    if args.ros2:
        from nwr.services.tools.recordings.rosbag_export import export_ros2

        src, dst = (Path(p) for p in args.ros2)
        print(export_ros2(src, dst, description=description, rate_hz=args.rate).format(dst))
        return 0
    src, dst = (Path(p) for p in args.foxglove)
    report = export_foxglove(src, dst, rate_hz=args.rate, description=description)
    print(f"{dst}: {report.format()}")
    return 0
