"""Franka's own contact detection beside the skin, on the FR3 through franky and libfranka's protocol (franky-sim).

    .venv/bin/python scripts/franky_contact.py [--touches N] [--seed S]

One embedded franky-sim (its FR3 in MuJoCo behind libfranka's protocol, on
127.0.0.1: libfranka's fixed ports), the arm driven as the franky backend
drives it (one ``JointImpedanceTrackingMotion``, the default
``bridge.franky.stiffness_nm_rad``, its reference the FR3's figure-eight,
default period, streamed at 500 Hz), and scripted touches that press a pad
*and* push the arm:

- a touch is the gateway's scripted pressure curve on one pad (a ramp to its
  peak over 0.3 s, held 0.6 s, released over 0.2 s), and the same touch a
  force applied in MuJoCo (``xfrc_applied`` on the pad's link, at the pad's
  point) along minus the pad's outward normal, ``PUSH_N_PER_HPA`` newtons
  per hPa of the pressure change: 1.25 N/hPa, the physics world's held
  press (wrist_1, 15 hPa felt, 18.6 N; docs/worlds.md);
- the skin's onset: the first 25 Hz skin sample (AIRSKIN's rate, a random
  phase) whose change reaches 6 hPa, where the gain (continuous model) and
  so a reflex starts;
- the torque detection's onset: the first robot state (``tau_ext_hat_filtered``
  read through franky every 2 ms) that :class:`nwr.services.gain.torque.TorqueDetector`
  flags (per-joint thresholds ``ON_NM``/``OFF_NM`` times ``--scale``; the
  ``--baseline``, default ``dynamics``: franky-sim reports its applied torque
  there), with its pad and force estimate;
- both from the touch's start, ms; the figure-eight runs untouched first
  (``--quiet-s``) and between touches: every detection there is a false
  positive.

Prints one table row per touch, the false positives, the untouched
residual's p99 and maximum per joint, the least push each pad must get to be
felt at home, and the load. franky-sim falls behind real time on a loaded
machine, its arm lags, and its applied torque (what it reports) grows with
the lag: run it where it may take SCHED_FIFO (``--priority``), as the e2e
test does.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from nwr.common.pacing import realtime
from nwr.common.robot import RobotModel, load_description
from nwr.common.task import FigureEight, TaskSection
from nwr.services.gain.torque import BASELINES, TorqueDetector
from nwr.services.tools.hardware.franky_sim import HOST, home

PUSH_N_PER_HPA = 1.25
SIM_PRIORITY = 10
SKIN_HZ = 25.0
REFLEX_HPA = 6.0  # the continuous model's first gain above 0 (t2)
RAMP_S, HOLD_S, RELEASE_S = 0.3, 0.6, 0.2
PERIOD_S = 0.002
STIFFNESS = [600.0, 600.0, 600.0, 600.0, 250.0, 150.0, 50.0]  # bridge.franky.stiffness_nm_rad's default
ON_NM = [6.0, 6.0, 3.0, 6.0, 2.0, 2.0, 1.0]  # gain.torque's defaults (docs/profile.md)
OFF_NM = [4.0, 4.0, 1.5, 4.0, 1.0, 1.0, 0.5]
TASK_RAMP_S = 0.5  # the task eases in (planner.task.ramp_s)


def pressure(t: float, peak: float) -> float:
    """The scripted touch's pressure change at ``t`` s after its start, hPa."""
    if t < 0:
        return 0.0
    if t < RAMP_S:
        return peak * t / RAMP_S
    if t < RAMP_S + HOLD_S:
        return peak
    if t < RAMP_S + HOLD_S + RELEASE_S:
        return peak * (1.0 - (t - RAMP_S - HOLD_S) / RELEASE_S)
    return 0.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--touches", type=int, default=12, help="touches, on pads and peaks drawn at random")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--quiet-s", type=float, default=6.0, help="untouched figure-eight before the first touch")
    parser.add_argument("--priority", type=int, default=SIM_PRIORITY,
                        help=f"SCHED_FIFO priority of this process, the simulator's threads included, where "
                             f"permitted (default {SIM_PRIORITY}, as the e2e test's simulator; 0: off)")
    parser.add_argument("--baseline", default="dynamics", choices=BASELINES,
                        help="the detector's baseline model (services/gain/torque.py)")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="the thresholds (on and off, per joint) times this")
    parser.add_argument("--gap-s", type=float, default=2.5, help="untouched figure-eight between touches")
    args = parser.parse_args()
    import franky
    import mujoco
    from franky_sim import SimulationServer
    from franky_sim.mujoco_simulator import MujocoSimulator

    realtime(args.priority, "franky-sim")  # before the simulator's threads start: they inherit it
    desc = load_description("fr3")
    model = RobotModel(desc)
    task = FigureEight(TaskSection(), desc)
    rng = np.random.default_rng(args.seed)
    pads = [p for p in range(len(desc.pads)) if desc.pads[p].link not in ("link0", "link1")]
    touches = [(float(args.quiet_s + k * (args.gap_s + RAMP_S + HOLD_S + RELEASE_S)), int(rng.choice(pads)),
                float(rng.uniform(8.0, 25.0)), float(rng.uniform(0, 1 / SKIN_HZ))) for k in range(args.touches)]
    end_s = touches[-1][0] + RAMP_S + HOLD_S + RELEASE_S + args.gap_s
    detector = TorqueDetector(model, args.scale * np.array(ON_NM), args.scale * np.array(OFF_NM),
                              baseline=args.baseline)
    rows: list[dict] = []
    flags: list[tuple[float, int, float]] = []  # (t, pad, force) of every detected state
    states = 0
    residuals: list[tuple[float, tuple[float, ...]]] = []  # (t, r) of every state once tared
    with MujocoSimulator(enable_visualization=False) as sim:
        sim.add_robot()
        with SimulationServer(sim, hostname_candidates=[HOST]) as server:
            server.run_async()
            home(HOST, np.asarray(desc.home, dtype=float))
            robot = franky.Robot(HOST, realtime_config=franky.RealtimeConfig.Ignore)
            m, d = sim.model, sim.data
            bodies = {p.link: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"robot0_fr3_{p.link}")
                      for p in desc.pads}
            if min(bodies.values()) < 0:
                raise SystemExit(f"franky-sim's scene lacks a body of {bodies}")
            motion = franky.JointImpedanceTrackingMotion(stiffness=np.array(STIFFNESS))
            motion.set_reference(franky.JointReference(task.position(0.0), np.zeros(7)))
            robot.move(motion, asynchronous=True)
            time.sleep(0.5)
            load = [os.getloadavg()[0]]
            start = time.monotonic()
            s, last = 0.0, 0.0
            while (t := time.monotonic() - start) < end_s:
                rate = min(1.0, t / TASK_RAMP_S)
                s += rate * (t - last)
                last = t
                motion.set_reference(franky.JointReference(task.position(s), rate * task.velocity(s)))
                state = robot.state
                q = np.asarray(state.q, dtype=float)
                # The touches under way push their pad's link at the pad's point, along minus its normal.
                for body in set(bodies.values()):
                    d.xfrc_applied[body] = 0.0
                for t0, pad, peak, _ in touches:
                    p = pressure(t - t0, peak)
                    if p > 0:
                        body = bodies[desc.pads[pad].link]
                        point = d.xpos[body] + d.xmat[body].reshape(3, 3) @ desc.pads[pad].point
                        normal = d.xmat[body].reshape(3, 3) @ desc.pads[pad].normal
                        force = -PUSH_N_PER_HPA * p * normal
                        d.xfrc_applied[body, :3] += force
                        d.xfrc_applied[body, 3:] += np.cross(point - d.xipos[body], force)
                verdict = detector.update(q, np.asarray(state.tau_ext_hat_filtered, dtype=float),
                                          np.asarray(state.dq, dtype=float), round(state.time.to_sec() * 1e9))
                states += 1
                if verdict.tared:
                    residuals.append((t, verdict.residual_nm))
                if verdict.detected:
                    flags.append((t, verdict.pad, verdict.force_n))
                time.sleep(max(0.0, PERIOD_S - (time.monotonic() - start - t)))
            for body in set(bodies.values()):
                d.xfrc_applied[body] = 0.0
            load.append(os.getloadavg()[0])
            robot.stop()
            del robot
    for t0, pad, peak, phase in touches:
        ramp_at = REFLEX_HPA / peak * RAMP_S  # when the change reaches 6 hPa
        first_sample = t0 + phase + np.ceil((ramp_at - phase) * SKIN_HZ) / SKIN_HZ
        skin_ms = (first_sample - t0) * 1000
        window = [f for f in flags if t0 <= f[0] < t0 + RAMP_S + HOLD_S + RELEASE_S + 0.3]
        torque_ms = (window[0][0] - t0) * 1000 if window else None
        named = {desc.pads[f[1]].name for f in window if f[1] >= 0}
        held = [f for f in window if t0 + RAMP_S <= f[0] < t0 + RAMP_S + HOLD_S]
        rows.append(dict(pad=desc.pads[pad].name, peak=peak, force=PUSH_N_PER_HPA * peak, skin=skin_ms,
                         torque=torque_ms, located=desc.pads[held[-1][1]].name if held and held[-1][1] >= 0 else "-",
                         estimate=held[-1][2] if held else 0.0, names=len(named)))
    touched = [(t0, t0 + RAMP_S + HOLD_S + RELEASE_S + 0.3) for t0, *_ in touches]
    false = [f for f in flags if not any(a <= f[0] < b for a, b in touched)]
    episodes = sum(1 for i, f in enumerate(false) if i == 0 or f[0] - false[i - 1][0] > 0.05)
    print("| pad | peak hPa | push N | skin onset ms | torque onset ms | torque - skin ms | located (held) | "
          "force estimate N |")
    print("|---|---:|---:|---:|---:|---:|---|---:|")
    for r in rows:
        diff = f"{r['torque'] - r['skin']:+.0f}" if r["torque"] is not None else "-"
        torque = f"{r['torque']:.0f}" if r["torque"] is not None else "not detected"
        print(f"| {r['pad']} | {r['peak']:.1f} | {r['force']:.1f} | {r['skin']:.0f} | {torque} | {diff} | "
              f"{r['located']} | {r['estimate']:.1f} |")
    detected = [r for r in rows if r["torque"] is not None]
    print(f"\ndetected {len(detected)} of {len(rows)} touches; located on the touched pad while held: "
          f"{sum(r['located'] == r['pad'] for r in rows)}; false positives on the untouched figure-eight: "
          f"{episodes} episodes, {len(false)} of {states - sum(1 for f in flags if f not in false)} states "
          f"({end_s - len(touches) * (RAMP_S + HOLD_S + RELEASE_S + 0.3):.0f} s untouched); "
          f"{states} states in {end_s:.0f} s")
    quiet = np.abs([r for t, r in residuals if not any(a <= t < b for a, b in touched)])
    print(f"untouched residual per joint, N m: p99 {np.percentile(quiet, 99, axis=0).round(2).tolist()}, "
          f"max {quiet.max(axis=0).round(2).tolist()}")
    on = args.scale * np.array(ON_NM)
    off = args.scale * np.array(OFF_NM)
    print(f"{args.baseline} baseline, thresholds x {args.scale:g}: on {on.round(2).tolist()} N m, "
          f"off {off.round(2).tolist()} N m; "
          f"load average {min(load):.1f}-{max(load):.1f} on {os.cpu_count()} cores")
    # What the thresholds can feel at all: the least push along minus each pad's normal that reaches one, at home.
    home_q = np.asarray(desc.home, dtype=float)
    per_newton = -np.einsum("pk,pkj->pj", model.pad_normals(home_q), model.pad_jacobians(home_q))
    least = [float(np.min(on / np.maximum(np.abs(a), 1e-9))) for a in per_newton]
    print("least force felt at home, N: " + ", ".join(f"{p.name} {f:.0f}" if f < 1e6 else f"{p.name} never"
                                                      for p, f in zip(desc.pads, least, strict=True)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
