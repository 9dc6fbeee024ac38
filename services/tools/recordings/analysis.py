"""Per-touch summary of a recording, computed from the recording alone.

A *touch* is a run of skin samples in which one pad's contact flag is set.
For each touch: the peak pressure change, pain level and gain; the reflex it
caused (a planner reflex whose contact is that pad and whose triggering skin
sample lies within the touch); the reflex onset latency (skin sample stamped
in the gateway -> first command of the reflex accepted by the bridge); how
far the touched pad withdrew along its outward normal (computed with the
robot model from the recorded joint states); and the time from the onset
until the planner was back in TASK, with how close the arm came back to the
saved pose. While the touch lasts: how many times the arm came back into it
(a reflex of the same pad begun from a return or the task, after the first),
the closest the touched pad came back to the contact point after its
withdrawal, and the fastest point of the arm on the way back (phase
RETURNING).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.recordings import Recorded
from nwr.common.robot import RobotDescription, RobotModel
from nwr.services.planner.contacts import CONTACT_RADIUS_M

RETURN_WINDOW_NS = 300_000_000
# A touch stays recent this long after it ends (planner.recent_contact_s's default), s; the place a person was:
# within CONTACT_RADIUS_M of the contact point across the pad's normal (the planner's own measure).
CONTACT_RECENT_S = PlannerSection().recent_contact_s
# A pad this near a recent touch's place approaches it (planner.approach_distance_m's default), m.
RETURN_NEAR_M = PlannerSection().approach_distance_m
# Nearer than this to the place, the direction toward it is the states' lag behind the commands (a state every 20 ms
# at up to 0.1 m/s), not an approach, m.
RETURN_AT_M = 0.002


@dataclass
class TouchSummary:
    pad: int
    name: str
    region: str
    start_ns: int
    end_ns: int
    first_seq: int
    last_seq: int
    peak_hpa: float
    level: int = 1
    gain: float = 0.0
    reflex_seq: int = 0
    onset_latency_ms: float | None = None
    withdrawal_mm: float | None = None
    toward_mm: float | None = None  # touched pad's furthest move toward the contact (reflex and hold)
    other_approach_mm: float | None = None  # any other pad's largest approach to the contact point
    other_pad: str = ""
    planned_toward_mm: float | None = None  # the planner's own retreat check
    # Its retreat check of the other touched pads at the onset (Retreat.contacts_toward_m): the furthest one of
    # them was planned to move toward its own contact, mm, and which (None, "": no other touched pad).
    planned_others_toward_mm: float | None = None
    planned_others_pad: str = ""
    corrected: bool = False
    strategy: str = ""
    resumed_after_s: float | None = None
    return_error_rad: float | None = None  # closest the arm came to the saved pose within 0.3 s of resuming
    # The withdrawal's fastest point of the arm (pads, elbow, flange), and its fastest speed toward the contact
    # (along the touched pad's outward normal at the onset), m/s: what the Cartesian limits let through.
    peak_speed_m_s: float | None = None
    peak_toward_m_s: float | None = None
    # False: the planner found that no motion could move the touched pad away from the contact (it held still).
    withdraws: bool = True
    # Why its reflex's motion is not the strategy's plain withdrawal (ReflexInfo.reason: "sideways", "short",
    # "blocked", "failed"; "" when it is).
    reason: str = ""
    # How far its reflex would have withdrawn the pad at full gain, mm (ReflexInfo.reach_m: what the joints
    # allowed it; None: the strategy does not say): the gain's share of it is the withdrawal in proportion.
    reach_mm: float | None = None
    # Reflexes of this pad begun while the touch lasted, after the first, from a return or the task or after the
    # pad had stopped feeling the touch's pain: each one a return into the finger still pressing (0 is the goal).
    returns_into: int = 0
    # The closest the touched pad came back to the contact point, along its normal at the onset, after its
    # withdrawal and while the touch lasted, mm (negative: pressed past it).
    back_mm: float | None = None
    # Every touch, whichever reflex ran (a second hand's as well as the strongest's): its pad's furthest move
    # toward where the touch met it (along its normal there) while the touch lasted, mm; and, after the touch
    # ended, while it was recent (CONTACT_RECENT_S), the furthest the arm took the pad back past that place
    # (within CONTACT_RADIUS_M of it across the normal: where the person was), mm (0: never past it), beyond the
    # furthest out it had been since the touch ended (a pad the touch's own motion left past the place, and that
    # stays there, counts in pressed_toward_mm only).
    pressed_toward_mm: float | None = None
    past_after_mm: float | None = None
    # From its first pain sample at PL 2, with a gain or a light touch (what the planner knows) until
    # CONTACT_RECENT_S after it, during returns (phase RETURNING): the fastest any pad within RETURN_NEAR_M of
    # where the touched pad was then moved toward that place, m/s (None: no such state; the planner's rule:
    # planner.approach_speed_m_s at most).
    return_toward_m_s: float | None = None
    # The fastest point of the arm while it returned (phase RETURNING) until the touch's reflex ended, m/s.
    return_speed_m_s: float | None = None
    # The touched pad's peak jerk during the withdrawal, m/s^3 (from the robot states: at their rate).
    peak_jerk_m_s3: float | None = None
    # True: the recording has no pain data (skin/pain) and level and gain were computed from peak_hpa through the
    # profile's gain model (a real skin's imported recording).
    pain_computed: bool = False
    # False: the recording has no planner (no reflex statuses): whether the touch caused a reflex is unknown.
    reflex_known: bool = True
    # The effective-mass model's prediction for the touched pad at the onset (the skin sample that started the
    # touch's reflex, else the touch's first): the arm's effective mass along the pad's motion, kg, and the
    # impact force a collision at its speed would cause, N (None: the recording's gain model predicts none).
    effective_mass_kg: float | None = None
    impact_n: float | None = None
    # A physics world's touch (world/contacts, :func:`world_figures`): the measured peak contact force on the
    # person's body part, N, and how far the arm pushed it back from where it met the pad (along the pad's
    # normal) while it pressed, mm.
    peak_force_n: float | None = None
    into_finger_mm: float | None = None
    # The peak pressure over the contact area, N/cm^2, and the energy the arm put into the body part, J
    # (docs/worlds.md "Force figures"); the ISO/TS 15066 body area the part is judged by (people.ISO_TS_15066),
    # its quasi-static and transient force (N) and pressure (N/cm^2) limits, and the peaks' largest fraction of
    # the quasi-static limits (over 1: beyond them).
    peak_pressure_n_cm2: float | None = None
    energy_j: float | None = None
    body_area: str = ""
    force_limit_n: float | None = None
    pressure_limit_n_cm2: float | None = None
    transient_force_limit_n: float | None = None
    transient_pressure_limit_n_cm2: float | None = None
    of_limit: float | None = None


def summarized(key: str) -> bool:
    """Whether :func:`summarize` reads messages of ``key`` (``read_recording(..., only=summarized)`` decodes no
    others: no commands, 70 % of a session's messages)."""
    return key in ("skin/pressure", "skin/pain", "robot/state", "skin/touch", "world/contacts") or (
        key.startswith("reflex/") and key.endswith("/status"))


def summarize(records: list[Recorded], desc: RobotDescription, model: RobotModel | None = None, *,
              touches: list[TouchSummary] | None = None, entry_pads: np.ndarray | None = None) -> list[TouchSummary]:
    """The per-touch figures; ``touches``: the touches to describe, when known otherwise than from the skin's
    contact flags (a scripted press, which a withdrawing pad stops feeling before the finger leaves);
    ``entry_pads``: on a taxel skin, each taxel's pad (:func:`nwr.common.skin.entry_pads`), a pad in contact
    while a taxel of its patch is."""
    model = model or RobotModel(desc)
    pressure = [r.message for r in records if r.key == "skin/pressure"]
    pain = [r.message for r in records if r.key == "skin/pain"]
    states = [r.message for r in records if r.key == "robot/state"]
    # The active planner's statuses only: a standby planner mirrors the active one a status period late (its
    # mode, its task time) and plans shadow reflexes that never moved the arm.
    statuses = [r.message for r in records if r.key.startswith("reflex/") and r.key.endswith("/status")
                and r.message.active and (r.message.reflex is None or not r.message.reflex.shadow)]

    touches = _segment(pressure, desc, entry_pads) if touches is None else touches
    by_seq = {p.trace.seq: p for p in pain}
    for touch in touches:
        for seq in range(touch.first_seq, touch.last_seq + 1):
            p = by_seq.get(seq)
            if p is not None and len(p.gain) > touch.pad:
                if p.gain[touch.pad] > touch.gain or p.level[touch.pad] > touch.level:
                    touch.gain = max(touch.gain, p.gain[touch.pad])
                    touch.level = max(touch.level, p.level[touch.pad])

    reflexes: dict[int, m.ReflexInfo] = {}
    for st in statuses:  # the newest status of each reflex: its retreat check comes after its onset
        if st.reflex is not None:
            reflexes[st.reflex.reflex_seq] = st.reflex
    onsets: dict[int, m.RobotState] = {}
    for s in states:
        if s.accepted is not None and s.reflex_seq not in onsets:
            onsets[s.reflex_seq] = s
    state_t = np.array([s.stamp_ns for s in states], dtype=np.int64)
    state_q = np.array([s.q for s in states]) if states else np.zeros((0, len(desc.joints)))
    state_dq = np.array([s.dq for s in states]) if states else np.zeros((0, len(desc.joints)))
    withdrawing = np.array([s.phase == "REFLEX" for s in states], dtype=bool)
    returning = np.array([s.phase == "RETURNING" for s in states], dtype=bool)
    came_back = np.array([s.phase in ("RETURNING", "TASK") for s in states], dtype=bool)

    def pad_gain(pad: int) -> list[tuple[int, float]]:
        return [(p.stamp_ns, p.gain[pad]) for p in pain if len(p.gain) > pad]

    for touch in touches:
        _contact_figures(touch, model, state_t, state_q)
        felt = next((p.stamp_ns for p in pain if touch.start_ns <= p.stamp_ns <= touch.end_ns
                     and len(p.level) > touch.pad and (p.level[touch.pad] >= 2 or p.gain[touch.pad] > 0.0
                                                       or touch.pad in p.light_touch)),
                    touch.start_ns)
        _return_toward(touch, model, state_t, state_q, state_dq, returning, felt)
    world_figures(touches, records)

    for touch in touches:
        reflex = next(
            (r for seq, r in sorted(reflexes.items())
             if r.contact.pad == touch.pad and touch.first_seq <= r.trace.seq <= touch.last_seq),
            None,
        )
        _predicted(touch, by_seq.get(reflex.trace.seq if reflex is not None else touch.first_seq))
        if reflex is None:
            continue
        touch.reflex_seq = reflex.reflex_seq
        touch.withdraws = reflex.withdraws
        touch.reason = reflex.reason
        touch.reach_mm = 1e3 * reflex.reach_m if reflex.reach_m > 0.0 else None
        onset = onsets.get(reflex.reflex_seq)
        if onset is None or onset.accepted is None:
            continue
        t0 = onset.accepted_ns
        touch_end = touch.end_ns
        # Later reflexes of the same pad while the touch lasted, each begun from a return or the task, or after
        # the pad's gain fell to 0 (it had withdrawn from the pain): the arm came back into the finger.
        previous = t0
        for seq, r in sorted(reflexes.items()):
            again = onsets.get(seq)
            if seq == reflex.reflex_seq or r.contact.pad != touch.pad or again is None or \
                    not t0 < again.accepted_ns <= touch_end:
                continue
            before = int(np.searchsorted(state_t, again.stamp_ns)) - 1
            relieved = any(previous < t < again.accepted_ns and g <= 0.0 for t, g in pad_gain(touch.pad))
            if (before >= 0 and came_back[before]) or relieved:
                touch.returns_into += 1
            previous = again.accepted_ns
        touch.onset_latency_ms = (t0 - onset.accepted.stamp_ns) / 1e6
        resumed = next((st for st in statuses if st.stamp_ns > t0 and st.mode == "TASK"), None)
        end = resumed.stamp_ns if resumed is not None else int(state_t[-1]) if len(state_t) else t0
        # The touch's motion ends where another touch's reflex begins (this touch's own updates and restarts
        # go on with it: a press whose pain builds over several skin samples restarts its reflex every sample,
        # and its withdrawal's speed is that of the whole motion, not of its first 40 ms): without a resumption,
        # the end of the recording would take in later touches' motions.
        others = [o.accepted_ns for seq, o in onsets.items() if o.accepted_ns > t0 and seq in reflexes
                  and not (reflexes[seq].contact.pad == touch.pad
                           and touch.first_seq <= reflexes[seq].trace.seq <= touch.last_seq)]
        end = min([end, *others])
        until = end
        if resumed is not None:
            touch.resumed_after_s = (resumed.stamp_ns - t0) / 1e9
        window = (state_t >= t0) & (state_t <= end)
        touch.strategy = reflex.strategy
        if window.any():
            q0 = state_q[np.argmax(state_t >= t0)]
            points0 = model.pad_points(q0)
            p0 = points0[touch.pad]
            n0 = model.pad_normal(q0, touch.pad)
            d0 = np.linalg.norm(points0 - p0, axis=1)
            # Toward the contact and other pads closer: over the reflex and its hold, not the return after it
            # (whose way back past a touch still recent is `past_after_mm`; a return that waited until the
            # touch was no longer recent goes back through the place legitimately).
            reflexive = ~came_back[window]
            if not reflexive.any():
                reflexive[:] = True
            along, closest = [], d0.copy()
            for q, own_motion in zip(state_q[window], reflexive):
                points = model.pad_points(q)
                along.append(float((points[touch.pad] - p0) @ n0))
                if own_motion:
                    closest = np.minimum(closest, np.linalg.norm(points - p0, axis=1))
            touch.withdrawal_mm = -1e3 * min(along)
            touch.toward_mm = 1e3 * max(0.0, max(np.asarray(along)[reflexive]))
            approach = np.maximum(0.0, d0 - closest)
            approach[touch.pad] = 0.0
            worst = int(np.argmax(approach))
            touch.other_approach_mm = 1e3 * float(approach[worst])
            touch.other_pad = desc.pads[worst].name
            # The withdrawal's states (the bridge says which; older recordings do not: the whole window).
            own = window & (state_t < until)
            moving = own & withdrawing if (own & withdrawing).any() else own
            # (None when the recording ends at the reflex's first state: a session stopped as it began.)
            velocities = [model.speed_jacobians(q) @ dq for q, dq in zip(state_q[moving], state_dq[moving])]
            if velocities:
                touch.peak_speed_m_s = max(float(np.linalg.norm(v, axis=1).max()) for v in velocities)
                touch.peak_toward_m_s = max(0.0, max(float((v @ n0).max()) for v in velocities))
                touch.peak_jerk_m_s3 = peak_jerk(state_t[moving], np.array([v[touch.pad] for v in velocities]))
            # Back toward the contact after the furthest withdrawal, while the touch lasted.
            pressed = np.flatnonzero(window & (state_t <= touch_end))
            if len(pressed):
                furthest = int(np.argmin(along[:len(pressed)]))
                touch.back_mm = -1e3 * max(along[furthest:len(pressed)])
            back = window & returning
            if back.any():
                touch.return_speed_m_s = max(float(np.linalg.norm(model.speed_jacobians(q) @ dq, axis=1).max())
                                             for q, dq in zip(state_q[back], state_dq[back]))
        planned = next((st.reflex.retreat for st in statuses
                        if st.reflex is not None and st.reflex.reflex_seq == reflex.reflex_seq
                        and st.reflex.retreat is not None), None)
        if planned is not None:
            touch.planned_toward_mm = 1e3 * planned.toward_m
            if planned.contacts:
                worst = int(np.argmax(planned.contacts_toward_m))
                touch.planned_others_toward_mm = 1e3 * planned.contacts_toward_m[worst]
                touch.planned_others_pad = desc.pads[planned.contacts[worst]].name
            touch.corrected = planned.corrected
        saved = next((st.saved_pose for st in statuses if st.stamp_ns >= t0 and st.saved_pose is not None), None)
        if resumed is not None and saved is not None and len(state_t):
            # The arm follows its commands a cycle or more behind (more on a
            # loaded machine or a real controller), and the task eases back in
            # from rest: the closest the arm came to the saved pose around the
            # resumption is how well it returned.
            around = (state_t >= resumed.stamp_ns - RETURN_WINDOW_NS) & (state_t <= resumed.stamp_ns + RETURN_WINDOW_NS)
            if around.any():
                errors = np.max(np.abs(state_q[around] - np.asarray(saved)), axis=1)
                touch.return_error_rad = float(errors.min())
    return touches


def _predicted(touch: TouchSummary, pain: m.SkinPain | None) -> None:
    """A touch's predicted impact force and effective mass from the pain message of its onset, if it has them."""
    if pain is not None and len(pain.impact_n) > touch.pad and len(pain.effective_mass_kg) > touch.pad:
        touch.impact_n = pain.impact_n[touch.pad]
        touch.effective_mass_kg = pain.effective_mass_kg[touch.pad]


def _segment(pressure: list[m.SkinPressure], desc: RobotDescription,
             entry_pads: np.ndarray | None = None) -> list[TouchSummary]:
    open_: dict[int, TouchSummary] = {}
    done: list[TouchSummary] = []
    n = len(desc.pads)
    for sample in pressure:
        contact, change = sample.contact, sample.change_hpa
        if entry_pads is not None and len(contact) == len(entry_pads):
            contact, change = _per_pad(contact, change, entry_pads, n)
        elif len(contact) != n:
            continue  # a taxel skin's sample, its taxels' pads unknown here
        for pad, on in enumerate(contact):
            if on:
                t = open_.get(pad)
                if t is None:
                    info = desc.pads[pad]
                    t = open_[pad] = TouchSummary(pad, info.name, info.region, sample.stamp_ns, sample.stamp_ns,
                                                  sample.seq, sample.seq, 0.0)
                t.end_ns, t.last_seq = sample.stamp_ns, sample.seq
                t.peak_hpa = max(t.peak_hpa, change[pad])
            elif pad in open_:
                done.append(open_.pop(pad))
    done.extend(open_.values())
    done.sort(key=lambda t: t.start_ns)
    return done


def _per_pad(contact: list[bool], change: list[float], entry_pads: np.ndarray,
             n: int) -> tuple[list[bool], list[float]]:
    """A taxel sample per pad: in contact where a taxel of its patch is, its change the largest of theirs."""
    on = np.asarray(contact, dtype=bool)
    pads = entry_pads >= 0
    flags = np.zeros(n, dtype=bool)
    flags[entry_pads[pads & on]] = True
    peak = np.zeros(n)
    np.maximum.at(peak, entry_pads[pads], np.asarray(change, dtype=float)[pads])
    return flags.tolist(), peak.tolist()


def peak_jerk(t_ns: np.ndarray, v: np.ndarray) -> float | None:
    """The largest jerk of a point whose velocity is ``v`` (rows, m/s) at the times ``t_ns``, m/s^3.

    Finite differences of the velocity: at the robot state's rate (50 Hz by
    default) a jerk-limited ramp reads near its true jerk, a velocity step as
    its size over two sample intervals squared (large either way)."""
    if len(t_ns) < 3:
        return None
    t = (np.asarray(t_ns, dtype=np.int64) - int(t_ns[0])) / 1e9
    dt = np.diff(t)
    ok = dt > 0
    if ok.sum() < 2:
        return None
    a = np.diff(v, axis=0)[ok] / dt[ok, None]
    ta = (t[1:][ok] + t[:-1][ok]) / 2
    dta = np.diff(ta)
    if not (dta > 0).any():
        return None
    jerk = np.diff(a, axis=0)[dta > 0] / dta[dta > 0, None]
    return float(np.linalg.norm(jerk, axis=1).max()) if len(jerk) else None


def world_figures(touches: list[TouchSummary], records: list[Recorded]) -> None:
    """A physics world's measured figures per touch, from its body parts' contact figures (``world/contacts``):
    the peak contact force on the person (``peak_force_n``), the peak pressure, the energy put into them, how
    far the arm pushed them back, and ISO/TS 15066's limits for the body area they are judged by (the one the
    scripted touch names, ``body_area``, else the kind of body part's, :data:`nwr.services.worlds.people.KINDS`:
    a touch script's finger is the dominant hand's forefinger pad). The body part is the one that stood for the
    scripted touch (``skin/touch``) met on the touch's pad at its start (within 0.5 s, and its ramp). Touches of
    a recording without a physics world keep None."""
    from nwr.services.worlds.people import ISO_TS_15066, KINDS

    people: dict[int, list[m.WorldPerson]] = {}  # skin/touch seq -> its body part's figures, in time order
    for r in records:
        if r.key == "world/contacts":
            for p in r.message.people:
                people.setdefault(p.touch, []).append(p)
    if not people:
        return
    scripted = [r.message for r in records if r.key == "skin/touch"]
    for touch in touches:
        match = min((s for s in scripted if s.pad == touch.pad and s.seq in people
                     and abs(s.origin_ns + s.start_s * 1e9 - touch.start_ns) <= 0.5e9 + s.ramp_s * 1e9),
                    key=lambda s: abs(s.origin_ns + s.start_s * 1e9 - touch.start_ns), default=None)
        if match is None:
            continue
        seen = people[match.seq]
        touch.peak_force_n = max(p.peak_force_n for p in seen)
        touch.into_finger_mm = 1e3 * max(0.0, *(p.peak_pushed_m for p in seen))
        touch.peak_pressure_n_cm2 = max(p.peak_pressure_n_cm2 for p in seen)
        touch.energy_j = max(p.energy_j for p in seen)
        kind = seen[-1].kind
        area = match.body_area if match.body_area in ISO_TS_15066 else KINDS[kind].area if kind in KINDS else ""
        if area:
            region = ISO_TS_15066[area]
            touch.body_area = region.area
            touch.force_limit_n, touch.pressure_limit_n_cm2 = region.force_n, region.pressure_n_cm2
            touch.transient_force_limit_n = region.transient_force_n
            touch.transient_pressure_limit_n_cm2 = region.transient_pressure_n_cm2
            touch.of_limit = max(touch.peak_force_n / region.force_n,
                                 touch.peak_pressure_n_cm2 / region.pressure_n_cm2)


def serves_normal(touch: TouchSummary) -> bool:
    """Whether the touch's reflex withdrew its pad along the pad's normal, as far as the joints let it: not one
    whose joints could not (sideways, blocked: the withdrawal along the normal is then not the gain's to
    judge), nor one the planner found cannot withdraw it."""
    return touch.withdraws and touch.reason in ("", "short")


def withdrawal_share(touch: TouchSummary) -> float | None:
    """The touch's withdrawal as the proportion to its gain is judged by: its share of what the joints allowed
    its reflex at full gain (``reach_mm``), where the strategy says, else the withdrawal itself, mm. A pad whose
    reach changes with the task's phase (12 mm at one, 125 mm at another) withdraws in proportion to the gain
    within each reach, not across them."""
    if touch.withdrawal_mm is None:
        return None
    return touch.withdrawal_mm / touch.reach_mm if touch.reach_mm else touch.withdrawal_mm


def _contact_figures(touch: TouchSummary, model: RobotModel, state_t: np.ndarray, state_q: np.ndarray) -> None:
    """A touch's ``pressed_toward_mm`` and ``past_after_mm`` from the robot states (TouchSummary)."""
    first = int(np.searchsorted(state_t, touch.start_ns))
    if first >= len(state_t):
        return
    q0 = state_q[first]
    p0, n0 = model.pad_point(q0, touch.pad), model.pad_normal(q0, touch.pad)
    pressed = (state_t >= touch.start_ns) & (state_t <= touch.end_ns)
    along = [float((model.pad_point(q, touch.pad) - p0) @ n0) for q in state_q[pressed]]
    touch.pressed_toward_mm = 1e3 * max([0.0, *along])
    after = (state_t > touch.end_ns) & (state_t <= touch.end_ns + round(CONTACT_RECENT_S * 1e9))
    # Back past: beyond the furthest out the pad has been since the touch ended (the contact point at most), so
    # that a pad still where the touch's own motion left it (pressed_toward_mm) is not counted again.
    past, out = 0.0, np.inf
    for q in state_q[after]:
        offset = model.pad_point(q, touch.pad) - p0
        depth = float(offset @ n0)
        if np.linalg.norm(offset - depth * n0) <= CONTACT_RADIUS_M:
            out = min(out, max(depth, 0.0))
            past = max(past, depth - out)
        else:  # away from where the person was: coming back counts from the contact point
            out = 0.0
    touch.past_after_mm = 1e3 * past


def _return_toward(touch: TouchSummary, model: RobotModel, state_t: np.ndarray, state_q: np.ndarray,
                   state_dq: np.ndarray, returning: np.ndarray, felt_ns: int) -> None:
    """A touch's ``return_toward_m_s`` from the robot states (TouchSummary), from ``felt_ns``: the touch's first
    pain sample at PL 2 or with a gain, from which the planner knows it (where the pad was then)."""
    first = int(np.searchsorted(state_t, felt_ns))
    if first >= len(state_t):
        return
    p0 = model.pad_point(state_q[first], touch.pad)
    recent = (state_t >= felt_ns) & (state_t <= touch.end_ns + round(CONTACT_RECENT_S * 1e9)) & returning
    npads = len(model.pad_points(state_q[first]))
    worst = None
    for q, dq in zip(state_q[recent], state_dq[recent]):
        to = p0 - model.pad_points(q)
        dist = np.linalg.norm(to, axis=1)
        near = (dist <= RETURN_NEAR_M) & (dist > RETURN_AT_M)
        if near.any():
            v = model.speed_jacobians(q)[:npads] @ dq  # the pads' rows come first
            toward = np.einsum("pk,pk->p", v, to)[near] / dist[near]
            worst = max(0.0 if worst is None else worst, float(toward.max()))
    touch.return_toward_m_s = worst


# The bridge's statuses that stop the arm's motion (RobotStatus): a block during which the bridge went from
# following commands ("ok") to one of these was degraded, whatever its reflexes looked like.
ARM_STOPS = frozenset({"stale_command", "stale_skin", "planner_lost", "protective_stop", "emergency_stop",
                       "script_not_running", "disconnected", "state_implausible", "robot_reflex",
                       "motion_refused"})


@dataclass(frozen=True)
class BridgeHealth:
    """What the bridge refused or stopped for during a recording, from its robot states: the commands it
    rejected (its own count, the last state's less the first's) and each time it went from following
    commands to a status that stops the arm (:data:`ARM_STOPS`), by status."""

    rejected: int
    stops: dict[str, int]

    @property
    def degraded(self) -> bool:
        return self.rejected > 0 or bool(self.stops)

    def describe(self) -> str:
        parts = [f"{self.rejected} commands rejected"] if self.rejected else []
        parts += [f"{n} x {status}" for status, n in sorted(self.stops.items())]
        return ", ".join(parts) or "none"


# A recording ends as its pipeline stops: the skin, the planner or its commands go first, and the bridge holds
# the arm for that. A stop of these kinds that lasts to the end of the recording is that ending, not a fault.
SESSION_END = frozenset({"stale_skin", "stale_command", "planner_lost"})


def bridge_health(states: list[m.RobotState]) -> BridgeHealth:
    """The recording's :class:`BridgeHealth` from its robot states (in time order)."""
    if not states:
        return BridgeHealth(0, {})
    last_ok = max((i for i, s in enumerate(states) if s.status == "ok"), default=-1)
    stops: dict[str, int] = {}
    for i, (before, after) in enumerate(zip(states, states[1:])):
        if before.status == "ok" and after.status in ARM_STOPS and not (i >= last_ok and after.status in SESSION_END):
            stops[after.status] = stops.get(after.status, 0) + 1
    return BridgeHealth(max(0, states[-1].rejected - states[0].rejected), stops)


@dataclass
class Quality:
    """How one strategy's reflexes did over a session's touches (those that started a reflex)."""

    strategy: str
    reflexes: int = 0
    approached: int = 0  # touches whose pad moved more than APPROACH_MM toward the contact
    worst_toward_mm: float | None = None  # the touched pad's largest move toward the contact
    worst_other_mm: float | None = None  # any other pad's largest approach to the contact point
    withdrawal_median_mm: float | None = None
    withdrawal_min_mm: float | None = None  # of the pads that can withdraw
    repeat_pairs: int = 0  # pairs of touches of one pad at the same pressure (within REPEAT_HPA)
    repeat_diff_mm: float | None = None  # median |withdrawal difference| over those pairs
    gain_rank_corr: float | None = None  # Spearman's rho of withdrawal with gain, per pad, median over pads
    peak_jerk_m_s3: float | None = None  # the touched pads' largest jerk (median over touches)
    # Every touch with a gain, whichever reflex ran: those whose pad moved more than APPROACH_MM toward where the
    # touch met it while it lasted; every touch the skin felt, with a gain or not: those the arm took back more
    # than PAST_MM past that place while recent.
    any_toward: int = 0
    back_past: int = 0
    # Over those touches: the fastest any pad near one's place moved toward it during a return, m/s.
    return_toward_m_s: float | None = None
    # A physics world's (None without one), over every touch it measured: the largest peak force on the person,
    # N, and pressure, N/cm^2, the largest fraction of its body area's quasi-static ISO/TS 15066 limits, and the
    # touches beyond them.
    worst_force_n: float | None = None
    worst_pressure_n_cm2: float | None = None
    worst_of_limit: float | None = None
    over_limit: int | None = None


APPROACH_MM = 5.0  # a touched pad moving more than this toward the contact approached it
PAST_MM = 10.0  # the arm taking a pad more than this back past a recent touch's place went through it
REPEAT_HPA = 1.0  # touches of one pad this close in peak pressure count as the same touch repeated


def quality(touches: list[TouchSummary], strategy: str = "") -> Quality:
    """The reflex quality table's row for ``touches`` (one strategy's session)."""
    from scipy.stats import spearmanr

    done = [t for t in touches if t.reflex_seq and t.withdrawal_mm is not None]
    q = Quality(strategy or next((t.strategy for t in done if t.strategy), ""), len(done))
    felt = [t for t in touches if t.gain > 0.0]
    q.any_toward = sum((t.pressed_toward_mm or 0.0) > APPROACH_MM for t in felt)
    # Every touch the skin felt, with a gain or not (a light touch is where a person is, to the planner too).
    q.back_past = sum((t.past_after_mm or 0.0) > PAST_MM for t in touches)
    near = [t.return_toward_m_s for t in felt if t.return_toward_m_s is not None]
    q.return_toward_m_s = max(near) if near else None
    measured = [t for t in touches if t.peak_force_n is not None]
    if measured:
        q.worst_force_n = max(t.peak_force_n or 0.0 for t in measured)
        q.worst_pressure_n_cm2 = max(t.peak_pressure_n_cm2 or 0.0 for t in measured)
        judged = [t.of_limit for t in measured if t.of_limit is not None]
        q.worst_of_limit = max(judged) if judged else None
        q.over_limit = sum(x > 1.0 for x in judged)
    if not done:
        return q
    toward = [t.toward_mm or 0.0 for t in done]
    q.approached = sum(x > APPROACH_MM for x in toward)
    q.worst_toward_mm = max(toward)
    q.worst_other_mm = max(t.other_approach_mm or 0.0 for t in done)
    withdrawals = [t.withdrawal_mm for t in done if t.withdrawal_mm is not None]
    q.withdrawal_median_mm = float(np.median(withdrawals))
    able = [t.withdrawal_mm for t in done if t.withdraws and t.withdrawal_mm is not None]
    q.withdrawal_min_mm = min(able) if able else None
    diffs = [abs(a.withdrawal_mm - b.withdrawal_mm) for i, a in enumerate(done) for b in done[i + 1:]
             if a.pad == b.pad and abs(a.peak_hpa - b.peak_hpa) <= REPEAT_HPA
             and a.withdrawal_mm is not None and b.withdrawal_mm is not None]
    q.repeat_pairs = len(diffs)
    q.repeat_diff_mm = float(np.median(diffs)) if diffs else None
    # In proportion to the gain, pad by pad (across pads the joints behind each one dominate): Spearman's rho
    # of each pad touched at three or more gains, the median over those pads; of the touches its joints could
    # serve (serves_normal), each withdrawal as a share of what the joints allowed it (withdrawal_share).
    rhos = []
    for pad in {t.pad for t in done}:
        mine = [(t.gain, withdrawal_share(t)) for t in done if t.pad == pad and serves_normal(t)]
        if len({g for g, _ in mine}) >= 3 and len({w for _, w in mine}) > 1:
            rhos.append(float(spearmanr(*zip(*mine)).statistic))
    q.gain_rank_corr = float(np.median(rhos)) if rhos else None
    jerks = [t.peak_jerk_m_s3 for t in done if t.peak_jerk_m_s3 is not None]
    q.peak_jerk_m_s3 = float(np.median(jerks)) if jerks else None
    return q


QUALITY_HEADER = ["strategy", "reflexes", f"pad toward >{APPROACH_MM:g} mm", "worst toward (mm)",
                  "worst other pad (mm)", "withdrawal p50 (mm)", "withdrawal min (mm)", "repeats",
                  "repeat diff (mm)", "rho(gain, withdrawal)", "peak jerk (m/s^3)",
                  f"any touched pad toward >{APPROACH_MM:g} mm", f"back past a recent touch >{PAST_MM:g} mm",
                  "way back toward a recent touch (mm/s)"]
# Where the columns of every contact begin (nwr summary prints them as a table of their own, within its width).
CONTACT_QUALITY_FROM = QUALITY_HEADER.index(f"any touched pad toward >{APPROACH_MM:g} mm")
# pad toward: touches whose touched pad moved more than 5 mm toward the contact; worst other pad: any other
# pad's largest approach to the contact point; withdrawal min: of the pads that can withdraw; repeats: pairs of
# touches of one pad within 1 hPa of each other, repeat diff: their median withdrawal difference; rho: Spearman's
# rank correlation of withdrawal (as a share of what the joints allowed the reflex, where the strategy says: the
# whole-arm withdrawal) with gain per pad (pads touched at three or more gains), the median over pads;
# peak jerk: the touched pad's, median over the touches (at the state rate); any touched pad toward: every touch
# with a gain (a second hand's too, not only the reflex's), its pad moving toward where it was touched while the
# touch lasted; back past a recent touch: the arm taking a touched pad back through where the touch had been, within
# 3 s of its end, beyond the furthest out it had been since that end; way back toward a recent touch: the fastest
# any pad within 50 mm of where a touch met its pad moved toward that place while the arm returned (phase
# RETURNING), while the touch was active or within 3 s of its end ("-": no return came that near).


def quality_rows(rows: list[Quality]) -> list[list[str]]:
    f = cell
    return [[q.strategy, str(q.reflexes), str(q.approached), f(q.worst_toward_mm, ".1f"), f(q.worst_other_mm, ".1f"),
             f(q.withdrawal_median_mm, ".1f"), f(q.withdrawal_min_mm, ".1f"), str(q.repeat_pairs),
             f(q.repeat_diff_mm, ".1f"), f(q.gain_rank_corr, ".2f"), f(q.peak_jerk_m_s3, ".1f"), str(q.any_toward),
             str(q.back_past), f(None if q.return_toward_m_s is None else 1e3 * q.return_toward_m_s, ".0f")]
            for q in rows]


WORLD_QUALITY_HEADER = ["strategy", "worst force on the person (N)", "worst pressure (N/cm^2)",
                        "worst of ISO limit (%)", "over ISO limit"]
# A physics world's measured peaks on the person over every touch, their largest share of the body area's
# quasi-static ISO/TS 15066 limits (force or pressure, whichever is nearer) and the touches beyond them ("-"
# without a physics world).


def world_quality_rows(rows: list[Quality]) -> list[list[str]]:
    f = cell
    return [[q.strategy, f(q.worst_force_n, ".1f"), f(q.worst_pressure_n_cm2, ".1f"),
             f(None if q.worst_of_limit is None else 100 * q.worst_of_limit, ".0f"),
             "-" if q.over_limit is None else str(q.over_limit)] for q in rows]


def cell(x: float | None, fmt: str) -> str:
    """A table cell: ``x`` formatted, "-" when there is none."""
    return "-" if x is None else format(x, fmt)


def table_rows(touches: list[TouchSummary], t0_ns: int) -> list[list[str]]:
    f = cell
    return [
        [
            f"{(t.start_ns - t0_ns) / 1e9:6.2f}", t.name, t.region, f"{t.peak_hpa:5.1f}", str(t.level), f"{t.gain:.3f}",
            "yes" if t.reflex_seq else "no", f(t.onset_latency_ms, ".2f"),
            f(t.withdrawal_mm, ".1f") + ("" if t.withdraws else " cannot"),
            f(t.toward_mm, ".1f") + ("*" if t.corrected else ""),
            "-" if t.other_approach_mm is None else f"{t.other_approach_mm:.1f} {t.other_pad}",
            f(t.peak_speed_m_s, ".3f"), f(t.peak_toward_m_s, ".3f"), str(t.returns_into) if t.reflex_seq else "-",
            f(t.back_mm, ".1f"), f(t.return_speed_m_s, ".3f"), f(t.resumed_after_s, ".2f"),
        ]
        for t in touches
    ]


HEADER = ["t (s)", "pad", "region", "peak (hPa)", "PL", "gain", "reflex", "onset (ms)", "withdrawal (mm)",
          "toward (mm)", "other pad closer (mm)", "peak (m/s)", "toward (m/s)", "back into", "back to (mm)",
          "return (m/s)", "resumed (s)"]
# withdrawal: furthest the touched pad moved away from the contact along its normal ("cannot": no motion of the
# joints could move it away in that pose, and the arm held still);
# toward: furthest it moved toward the contact (* = guarded mode corrected the reflex);
# other pad closer: the largest approach of any other pad to the contact point;
# peak: the withdrawal's fastest point of the arm; toward (m/s): its fastest speed toward the contact;
# back into: returns into the touch while it lasted (a reflex of the same pad begun from a return or the task);
# back to: the closest the touched pad came back to the contact point while the touch lasted (mm from it);
# return: the fastest point of the arm on its way back (phase RETURNING).


def format_table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(header)]
    line = "  ".join(h.rjust(w) for h, w in zip(header, widths))
    out = [line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in rows]
    return "\n".join(out)


def contact_motion(model: RobotModel, q: np.ndarray, pad: int, q0: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                          np.ndarray]:
    """How the arm moved relative to a touch on ``pad`` felt in pose ``q0``, one value per row of ``q`` (m).

    The contact is where :func:`summarize` and the planner's retreat check
    (:func:`nwr.services.planner.retreat.assess`) put it: the touched pad's
    point in ``q0`` (the pose at the reflex onset), with the pad's outward
    normal n0 there. Returns

    - the touched pad's motion along n0 from that point, signed for a reader:
      positive away from the contact (withdrawal), negative toward it,
      ``-(p(t) - p0) . n0`` (its largest value is the table's withdrawal, its
      smallest minus its "toward");
    - the largest approach of any other pad to the contact point,
      ``max_k (|p_k(0) - p0| - |p_k(t) - p0|)`` (negative: all moved away), and
    - which pad it is (id), per row.
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    p0 = model.pad_point(q0, pad)
    n0 = model.pad_normal(q0, pad)
    d0 = np.linalg.norm(model.pad_points(q0) - p0, axis=1)
    away = np.empty(len(q))
    approach = np.empty(len(q))
    worst = np.empty(len(q), dtype=int)
    for i, row in enumerate(q):
        points = model.pad_points(row)
        away[i] = -float((points[pad] - p0) @ n0)
        closer = d0 - np.linalg.norm(points - p0, axis=1)
        closer[pad] = -np.inf
        worst[i] = int(np.argmax(closer))
        approach[i] = float(closer[worst[i]])
    return away, approach, worst
