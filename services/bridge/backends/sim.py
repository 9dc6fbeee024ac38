"""The simulated arm (``bridge.backend = "sim"``, the default): the envelope's kinematics, integrated at the
bridge's rate (:class:`nwr.services.bridge.backend.SimBackend`)."""

from __future__ import annotations

import argparse

import numpy as np

from nwr.common.config import BridgeSection
from nwr.common.robot import RobotDescription
from nwr.services.bridge.backend import Backend, SimBackend
from nwr.services.bridge.envelope import Envelope

NAME = "sim"
REAL_ARM = False


def make(cfg: BridgeSection, env: Envelope, q0: np.ndarray, args: argparse.Namespace,
         desc: RobotDescription) -> Backend:
    return SimBackend(env, 1.0 / cfg.rate_hz, q0)
