"""``nwr press``: a finger held on each pad, simulated in lockstep, and what the arm did about it.

A study participant does not always tap: a finger may stay on a pad for
seconds. For each strategy and each pad this runs the pipeline's own
wirings in lockstep (:mod:`nwr.services.pipeline.lockstep`, simulated skin
and arm) on a touch script of one held press, in open loop (the pad reads
the scripted pressure wherever it goes) and closed loop (the finger stays
where it met the pad; the pad feels less as it withdraws), and prints the
per-touch figures of :mod:`.analysis` that matter for a held press: the
reflexes, the returns into the touch while it lasted (0 is the goal), the
closest the touched pad came back to the contact point, the fastest point
of the arm on its way back.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import msgspec

from nwr.common import keys
from nwr.common.config import Profile
from nwr.common.launch import Touch, TouchScript
from nwr.common.recordings import Recorded
from nwr.common.robot import RobotModel, load_description
from nwr.services.profile import profile_for
from nwr.services.tools.recordings.analysis import TouchSummary, cell, format_table, summarize

# The press begins once the arm has reached its task (the approach from the start pose is over), s.
START_S = 2.0
# After the press: time for the return and the task's resumption, s.
AFTER_S = 8.0


@dataclass
class Press:
    strategy: str
    pad: str
    closed_loop: bool
    touch: TouchSummary | None  # None: the press was not seen on its pad
    reflexes: int  # reflexes begun on the pressed pad while it was pressed


def held_press(profile: Profile, strategy: str, pad: str, *, closed_loop: bool, press_s: float = 3.0,
               peak_hpa: float = 15.0, model: RobotModel | None = None) -> Press:
    """One press of ``press_s`` at ``peak_hpa`` on ``pad``, in lockstep; its per-touch figures."""
    from nwr.services.gateway.core import with_sim
    from nwr.services.gateway.stepped import SimulatedSkin
    from nwr.services.pipeline.lockstep import Lockstep

    profile = msgspec.structs.replace(profile, gateway=with_sim(profile.gateway, closed_loop=closed_loop))
    script = TouchScript(duration_s=START_S + press_s + AFTER_S,
                         touch=[Touch(pad=pad, start_s=START_S, duration_s=press_s, peak_hpa=peak_hpa)])
    records: list[Recorded] = []

    def emit(key: str, message: Any, t: int) -> None:
        if not key.startswith("journal/"):
            records.append(Recorded(key, t, message))

    Lockstep(profile, strategy=strategy, journal=False).run(SimulatedSkin(profile, script), emit, settle_s=0.0)
    desc = load_description(profile.robot.description or None)
    info = desc.pad(pad)
    # The press as scripted: in closed loop a pad that withdrew stops feeling the finger before it leaves.
    samples = [r.message for r in records if r.key == keys.SKIN_PRESSURE]
    origin = samples[0].stamp_ns - round(1e9 / profile.gateway.rate_hz) if samples else 0
    begin, end = origin + round(START_S * 1e9), origin + round((START_S + press_s) * 1e9)
    pressed = [s for s in samples if begin <= s.stamp_ns <= end and s.contact[info.id]]
    if not pressed:
        return Press(strategy, pad, closed_loop, None, 0)
    held = TouchSummary(info.id, info.name, info.region, pressed[0].stamp_ns, end, pressed[0].seq,
                        max(s.seq for s in samples if s.stamp_ns <= end),
                        max(s.change_hpa[info.id] for s in pressed))
    touch = summarize(records, desc, model, touches=[held])[0]
    reflexes = {r.message.reflex.reflex_seq for r in records
                if r.key.startswith("reflex/") and r.key.endswith("/status") and r.message.reflex is not None
                and r.message.reflex.contact.pad == info.id
                and touch.first_seq <= r.message.reflex.trace.seq <= touch.last_seq}
    return Press(strategy, pad, closed_loop, touch, len(reflexes))


def held_presses(profile: Profile, strategies: Iterable[str], pads: Iterable[str] | None = None, *,
                 loops: Iterable[bool] = (False, True), press_s: float = 3.0,
                 peak_hpa: float = 15.0) -> list[Press]:
    """:func:`held_press` on every pad (or ``pads``), for every strategy and loop."""
    desc = load_description(profile.robot.description or None)
    model = RobotModel(desc)
    names = list(pads) if pads is not None else [p.name for p in desc.pads]
    return [held_press(profile, strategy, pad, closed_loop=closed, press_s=press_s, peak_hpa=peak_hpa, model=model)
            for strategy in strategies for closed in loops for pad in names]


HEADER = ["strategy", "loop", "pad", "reflexes", "back into", "withdrawal (mm)", "back to (mm)", "return (m/s)",
          "resumed (s)"]


def rows(presses: list[Press]) -> list[list[str]]:
    f = cell
    out = []
    for p in presses:
        t = p.touch
        loop = "closed" if p.closed_loop else "open"
        if t is None:
            out.append([p.strategy, loop, p.pad, "not seen", "-", "-", "-", "-", "-"])
            continue
        out.append([p.strategy, loop, p.pad, str(p.reflexes), str(t.returns_into),
                    f(t.withdrawal_mm, ".1f") + ("" if t.withdraws else " cannot"), f(t.back_mm, ".1f"),
                    f(t.return_speed_m_s, ".3f"), f(t.resumed_after_s, ".2f")])
    return out


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "press", help="simulate a finger held on each pad (lockstep) and print what the arm did",
        description="Run the pipeline's own services in lockstep on simulated skin and arm, one held press per "
                    "pad and strategy, in open loop (the pad reads the scripted pressure) and closed loop (the "
                    "finger stays where it met the pad), and print per press: the reflexes begun while it "
                    "lasted, the returns into it (0 is the goal), how far the pad withdrew, the closest it "
                    "came back to the contact point while pressed, the fastest point of the arm on the way "
                    "back, and when the task resumed. Exit status 1 if any press saw a return into it.",
    )
    parser.add_argument("--reflex", action="append", metavar="R",
                        help="reflex strategy (repeatable; default: the profile's planner.strategy)")
    parser.add_argument("--pad", action="append", metavar="NAME", help="pad name (repeatable; default: every pad)")
    parser.add_argument("--loop", choices=("open", "closed", "both"), default="both")
    parser.add_argument("--seconds", type=float, default=3.0, help="how long the finger stays (default: 3)")
    parser.add_argument("--hpa", type=float, default=15.0, help="the press's pressure change (default: 15, PL 4)")
    parser.set_defaults(handler=_press)


def _press(args: argparse.Namespace) -> int:
    from nwr.common.errors import ConfigError

    profile = profile_for(args)
    if not 0 < args.seconds <= 60:
        raise ConfigError(f"--seconds {args.seconds}: give a press of more than 0 and at most 60 s")
    if not 0 < args.hpa <= 200:
        raise ConfigError(f"--hpa {args.hpa}: give a pressure change of more than 0 and at most 200 hPa")
    loops = {"open": (False,), "closed": (True,), "both": (False, True)}[args.loop]
    presses = held_presses(profile, args.reflex or [profile.planner.strategy], args.pad, loops=loops,
                           press_s=args.seconds, peak_hpa=args.hpa)
    print(format_table(HEADER, rows(presses)))
    into = sum(p.touch.returns_into for p in presses if p.touch is not None)
    print(f"\n{len(presses)} presses of {args.seconds:g} s at {args.hpa:g} hPa "
          f"(planner.sustained_contact = {profile.planner.sustained_contact!r}): {into} returns into a finger "
          "still pressing")
    return 1 if into else 0

