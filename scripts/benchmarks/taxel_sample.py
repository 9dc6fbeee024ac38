"""Our own Python per skin sample: ten AIRSKIN pads against the 300-taxel skin, in one process.

    .venv/bin/python scripts/benchmarks/taxel_sample.py [--samples N] [--rounds R]

Times, per sample, what a service's Python does with one skin sample on each skin, the two alternated R
times in one process (the medians of the rounds printed, and their ratio):

- **pads** (the baseline): a ten-pad ``SkinPressure`` encoded and decoded (msgpack, the key's codec) and the
  gain estimator's ``process`` on it (the paper's continuous model, the default profile), one pad pressed.
- **taxels**: a ``SkinPressure`` of 300 readings encoded and decoded (the same message, 300 entries per list:
  what a 300-element sample costs on the wire and in the codec), the simulated finger's pressure
  (:func:`nwr.common.taxels.finger_pressure`), the sample's contacts (:func:`nwr.common.taxels.contacts`:
  clusters, centroids, normals) and each contact's level and gain from its force.
- **taxels, untouched**: the same on a sample no taxel of which presses (the common case).
- **scripted source**: the scripted taxel skin's sample (:class:`nwr.services.gateway.taxels.ScriptedTaxels`)
  with the ``two-fingers`` script's two touches under way: what the gateway's Python adds to make one.

The figures are CPU time of this one thread (``time.thread_time_ns``), not wall time, and leave out Zenoh's
threads (put, receive), which :mod:`docs/performance.md`'s pipeline runs measure. The machine's load is
printed beside them.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable

import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import load_profile
from nwr.common.launch import load_script
from nwr.common.robot import ROBOTS_DIR, load_description
from nwr.common.taxels import contacts, finger_pressure, load_taxel_skin
from nwr.services.gain.core import GainEstimator, continuous_gain, pain_level
from nwr.services.gateway.taxels import ScriptedTaxels

# A taxel presses from this reading, kPa (a tenth of the lightest contact's force spread over a fingertip).
PRESS_KPA = 0.05


def _message(n: int, pressed: np.ndarray) -> m.SkinPressure:
    baseline = [1000.0] * n
    change = pressed.tolist()
    return m.SkinPressure(seq=1, stamp_ns=time.monotonic_ns(), absolute_hpa=[b + c for b, c in zip(baseline, change)],
                          baseline_hpa=baseline, change_hpa=change, contact=[c > 0 for c in change],
                          valid=[True] * n, touch_hpa=change)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=2000, help="samples per round and skin (default 2000)")
    parser.add_argument("--rounds", type=int, default=7, help="alternated rounds (default 7)")
    args = parser.parse_args()

    desc = load_description(None)
    skin = load_taxel_skin(ROBOTS_DIR / "ur10e" / "skin-taxels.toml", desc)
    codec = keys.Codec(keys.topic_for(keys.SKIN_PRESSURE))
    estimator = GainEstimator(load_profile(None).gain, desc.pads)
    thresholds = skin.force_thresholds_n

    pad_change = np.zeros(len(desc.pads))
    pad_change[2] = 15.0
    pad_payload = codec.encode(_message(len(desc.pads), pad_change))

    link, centre = "upper_arm_link", skin.points[52]
    touched = finger_pressure(skin, link, centre, 0.03, 4.0)
    taxel_payload = codec.encode(_message(len(skin), touched))
    untouched_payload = codec.encode(_message(len(skin), np.zeros(len(skin))))

    def pads() -> None:
        sample = codec.decode(pad_payload)
        estimator.process(sample, 0)
        codec.encode(sample)

    def taxels(payload: bytes, force: float) -> Callable[[], None]:
        def run() -> None:
            sample = codec.decode(payload)
            pressure = finger_pressure(skin, link, centre, 0.03, force)
            for contact in contacts(skin, pressure, PRESS_KPA):
                pain_level(contact.force_n, thresholds)
                continuous_gain(contact.force_n, thresholds)
            codec.encode(sample)
        return run

    profile = load_profile(None)
    source = ScriptedTaxels(skin, desc.pads, load_script("two-fingers"), profile.gain.thresholds_hpa)
    clock = [3.0]

    def scripted() -> None:
        clock[0] = 3.0 + (clock[0] - 3.0 + 1e-3) % 1.5  # within the two touches
        source.sample(clock[0])

    cases = {"pads": pads, "taxels": taxels(taxel_payload, 4.0), "taxels, untouched": taxels(untouched_payload, 0.0),
             "scripted source": scripted}
    assert len(contacts(skin, touched, PRESS_KPA)) == 1
    rounds: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(args.rounds):
        for name, case in cases.items():
            for _ in range(50):
                case()  # warm
            start = time.thread_time_ns()
            for _ in range(args.samples):
                case()
            rounds[name].append((time.thread_time_ns() - start) / args.samples / 1e3)

    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores); "
          f"{args.rounds} alternated rounds of {args.samples} samples; {len(skin)} taxels, {len(desc.pads)} pads")
    base = statistics.median(rounds["pads"])
    print(f"{'case':<20}{'CPU us/sample p50':>18}{'min':>8}{'max':>8}{'x pads':>8}{'% core @1 kHz':>15}")
    for name, values in rounds.items():
        p50 = statistics.median(values)
        print(f"{name:<20}{p50:>18.1f}{min(values):>8.1f}{max(values):>8.1f}{p50 / base:>8.2f}{p50 / 10:>15.1f}")


if __name__ == "__main__":
    main()
