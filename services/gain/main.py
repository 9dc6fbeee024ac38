"""Gain estimator process: skin/pressure -> skin/pain, one message per skin sample."""

from __future__ import annotations

import argparse
import logging

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.node import Node
from nwr.common.robot import load_description
from nwr.services.gain.core import GainEstimator

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", choices=["continuous", "discrete"], help="gain model (overrides gain.model)")


def run(profile: Profile, args: argparse.Namespace) -> int:
    if args.model:
        profile.gain.model = args.model
    desc = load_description(profile.robot.description or None)
    estimator = GainEstimator(profile.gain, desc.pads)
    with Node("gain", profile.robot.name, profile.zenoh, listen_slot="gain") as node:
        node.install_signal_handlers()
        publish = node.publisher(keys.SKIN_PAIN)

        def on_pressure(sample: m.SkinPressure) -> None:
            try:
                pain = estimator.process(sample, node.clock.now_ns())
            except ValueError as exc:
                node.diag("warning", "bad_skin_sample", str(exc))
                return
            publish(pain)

        # On Zenoh's network thread (direct): the handler never waits, and this
        # process subscribes to nothing it publishes.
        node.subscribe(keys.SKIN_PRESSURE, on_pressure, direct=True)
        log.info("%s gain model, thresholds %s hPa, k = %s", profile.gain.model, profile.gain.thresholds_hpa,
                 profile.gain.k)
        node.stop.wait()
        log.info("processed %d skin samples, %d non-finite pad values", estimator.seq, estimator.non_finite)
    return 0
