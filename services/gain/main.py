"""Gain estimator process: skin/pressure -> skin/pain, one message per skin sample."""

from __future__ import annotations

import argparse
import logging
import threading

from nwr.common.config import Profile, check_profile
from nwr.common.door import Door
from nwr.common.node import Node
from nwr.services.gain.wiring import SERVICE, GainWiring
from nwr.services.wiring import subscribe

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", choices=["continuous", "discrete", "effective-mass"],
                        help="gain model (overrides gain.model; effective-mass: docs/reflexes.md)")


def run(profile: Profile, args: argparse.Namespace) -> int:
    if args.model:
        profile.gain.model = args.model
        check_profile(profile)  # the effective-mass model's floor against the contact level, its regions
    lock = threading.Lock()  # the journal's batches are taken under it
    with Node(SERVICE, profile.robot.name, profile.zenoh, listen_slot="gain", token=False,
              door=Door.of(profile), exclusive=True) as node:
        node.install_signal_handlers()
        wiring = node.wire(GainWiring, profile, lock)
        # On Zenoh's network thread (direct): the handler never waits, and this
        # process subscribes to nothing it publishes.
        subscribe(node, wiring, lock)
        node.declare_token()  # alive once subscribed: the gateway starts on it, and loses no sample
        log.info("%s gain model, thresholds %s hPa, k = %s", profile.gain.model, profile.gain.thresholds_hpa,
                 profile.gain.k)
        node.stop.wait()
        estimator = wiring.estimator
        log.info("processed %d skin samples, %d non-finite pad values", estimator.seq, estimator.non_finite)
    return 0
