"""``nwr demo`` in the physics world (its default, and ``--world physics``) through real processes: the world's
finger, a reflex, the pressure the arm's motion changes, and ``nwr verify`` bit for bit; with the paper's gain model
and with the effective-mass one (which reads the robot state the world's arm sends back)."""

from __future__ import annotations

import pytest
from pipeline import DATA, Pipeline

from nwr.common import keys
from nwr.common.launch import load_script
from nwr.common.recordings import read_recording
from nwr.common.robot import load_description
from nwr.services.gain.impact import REASONS
from nwr.services.tools.recordings.verify import verify

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

SCRIPT = DATA / "physics.toml"  # one finger on forearm_top, 9 hPa held 1 s


@pytest.mark.parametrize("model", ["continuous", "effective-mass"])
def test_a_physics_demo_feels_the_finger_withdraws_from_it_and_verifies(tmp_path, pipeline: Pipeline,
                                                                        model: str) -> None:
    pipeline.configure(f'[gain]\nmodel = "{model}"\n')
    output = tmp_path / "physics.mcap"
    # `nwr demo`'s default world is the physics world: one run names it, the other leaves it to the default.
    world = ("--world", "physics") if model == "effective-mass" else ()
    proc = pipeline.run("demo", *world, "--script", str(SCRIPT), "--output", str(output), timeout_s=120)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log
    assert ("`nwr demo`'s default" in log) == (not world), log
    assert "the physics world's fingers:" in proc.stdout, log

    records, _ = read_recording(output)
    desc = load_description()
    pad = desc.pad("forearm_top").id
    touch = next(r.message for r in records if r.key == keys.SKIN_TOUCH)
    states = [r.message for r in records if r.key == keys.ROBOT_STATE]
    assert all(s.backend == "physics" for s in states)
    onset = next(s for s in states if s.reflex_seq > 0 and s.accepted is not None)  # a reflex happened

    # The pressure is the world's: it rose with the finger's force to the script's level (the force for 9 hPa on a
    # still pad, within the skin's noise and the cushion's yield), and fell while the pad withdrew from the finger,
    # whose owner still pushed (the script holds 9 hPa until 2.5 s).
    world = [r.message for r in records if r.key == keys.WORLD_SKIN]
    pressure = [r.message for r in records if r.key == keys.SKIN_PRESSURE]
    # Every world sample from the gateway's first on became a skin sample (the gateway may subscribe a few samples
    # after the bridge's world began: 8 samples, 0.32 s, on the loaded CI machine).
    since = [w for w in world if w.stamp_ns >= pressure[0].stamp_ns - 40_000_000]
    assert len(pressure) >= len(since) - 2 and all(p.source == "physics" for p in pressure)
    held = [w for w in world if touch.origin_ns + 1.5e9 < w.stamp_ns < touch.origin_ns + 2.5e9]
    peak = max(w.change_hpa[pad] for w in held)
    assert 7.0 < peak < 11.0, [round(w.change_hpa[pad], 2) for w in held]
    assert max(w.force_n[pad] for w in held) > 8.0  # 9 hPa: 11.3 N on a still pad
    after_onset = [w.change_hpa[pad] for w in held if w.stamp_ns > onset.accepted_ns + 50_000_000]
    assert after_onset and min(after_onset) < peak - 0.5, after_onset  # the withdrawing pad loses the finger
    felt = [p.change_hpa[pad] for p in pressure if touch.origin_ns + 1.5e9 < p.stamp_ns < touch.origin_ns + 2.5e9]
    assert max(felt) > 6.0  # the gateway's change from baseline: PL 3

    contacts = [r.message for r in records if r.key == keys.WORLD_CONTACTS]
    person = max((p for c in contacts for p in c.people), key=lambda p: p.peak_force_n)
    assert person.touch == touch.seq and pad in {q for c in contacts for p in c.people for q in p.pads}
    assert load_script(str(SCRIPT)).touch[0].pad == "forearm_top"

    pains = [r.message for r in records if r.key == keys.SKIN_PAIN]
    assert pains and all(p.model == model for p in pains)
    if model == "effective-mass":  # every pain message carries a prediction, made from the world's arm
        assert all(len(p.impact_n) == len(desc.pads) for p in pains)
        # Live, a starved machine may deliver a robot state late: the model then says why and falls back to its
        # floor (stale_state), which is no failure; most predictions are the state's all the same.
        bases = [p.impact_basis for p in pains]
        assert set(bases) <= {"state", *REASONS} and bases.count("state") > len(bases) / 2, set(bases)
        assert all(0.0 <= f <= 280.0 for p in pains for f in p.impact_n)

    results = verify(output)
    lines = [r.format() for r in results]
    assert {r.service for r in results} == {"gateway", "gain", "bridge", "planner-cartesian"}, lines
    assert all(r.verdict == "identical" for r in results), lines
    bridge = next(r for r in results if r.service == "bridge")
    assert bridge.outputs[keys.WORLD_SKIN] > 50 and bridge.outputs[keys.WORLD_CONTACTS] > 5, bridge.format()
