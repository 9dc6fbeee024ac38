"""``nwr compare A.mcap B.mcap ...``: the same touches, reflex against reflex.

Touches are lined up across recordings by pad and by start time from each
recording's first skin sample (within ``--window`` seconds), which is how a
replay of one session against several reflex services lines up. Per touch
and file: pad, gain, the predicted impact force at the onset (the
effective-mass gain model's; "-" for the paper's), onset latency, the touched pad's withdrawal along its
normal, how far it came toward the contact, the largest approach of any
other pad to the contact point, the peak joint speed during the reflex and
its return, the time until the task resumed, and how far the reflex motion
strayed from the first file's (the largest difference of the joints'
displacements from their onset poses, from the reflex onset until the earlier
of the two resumptions, the two aligned at their onsets). Files with a
physics world add a table of their fingers' measured figures (how far the
pad moved toward and into the finger, the peak force and pressure on the
person, the energy put into them, the share of ISO/TS 15066's quasi-static
limits); the quality table their worst. Below, each file's command stream against the
first's: identical decoded messages (a deterministic replay of the first
file), or where they part. A PNG (``--figure``) draws, per touch that
caused a reflex, one colour per file and time from the touch's first skin
sample: the touched pad's motion along its outward normal at the reflex
onset (withdrawal up, toward the contact down: the table's withdrawal and
toward), the other pads' closest approach to the contact point, and each
joint's displacement from the onset pose in a panel of its own.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nwr.common import keys
from nwr.common.config import Profile
from nwr.common.recordings import Recorded, read_recording
from nwr.common.robot import RobotDescription, RobotModel, load_description
from nwr.services.profile import load_profile, profile_for
from nwr.services.tools.recordings import analysis, summary


@dataclass
class Session:
    path: Path
    label: str
    records: list[Recorded]
    t0_ns: int
    touches: list[analysis.TouchSummary]
    strategy: str = ""  # the recording's reflex strategy (session metadata), if it says
    notes: list[str] = field(default_factory=list)  # what the recording cannot tell (summary.complete)


def load_session(path: Path, desc: RobotDescription, model: RobotModel, profile: Profile | None = None) -> Session:
    """A recording's touches; on simulated time (lockstep) without onsets, which are no latencies there."""
    records, metadata = read_recording(path)
    t0 = next((r.message.stamp_ns for r in records if r.key == "skin/pressure"), 0)
    strategy = metadata.get("session", {}).get("strategy", "")
    label = f"{path.stem} ({strategy})" if strategy else path.stem
    touches = analysis.summarize(records, desc, model)
    notes = summary.complete(touches, records, metadata, profile or load_profile(None), desc)
    if summary.is_lockstep(metadata):
        notes.insert(0, "on simulated time (lockstep): each reflex began within its skin sample's control cycle by "
                        "construction; no onset latency is measured (onset \"-\")")
    return Session(path, label, records, t0, touches, strategy, notes)


def line_up(sessions: list[Session], window_s: float) -> list[list[analysis.TouchSummary | None]]:
    """Rows of touches, one column per session; a touch missing from a session is None."""
    rows: list[list[analysis.TouchSummary | None]] = []
    anchors: list[tuple[int, float]] = []  # (pad, start s) of each row
    for col, session in enumerate(sessions):
        for touch in session.touches:
            start = (touch.start_ns - session.t0_ns) / 1e9
            row = next((i for i, (pad, s) in enumerate(anchors)
                        if pad == touch.pad and abs(s - start) <= window_s and rows[i][col] is None), None)
            if row is None:
                anchors.append((touch.pad, start))
                rows.append([None] * len(sessions))
                row = len(rows) - 1
            rows[row][col] = touch
    order = sorted(range(len(rows)), key=lambda i: anchors[i][1])
    return [rows[i] for i in order]


def peak_joint_speed(session: Session, touch: analysis.TouchSummary) -> float | None:
    """Largest joint speed between the touch's reflex onset and the task's resumption, rad/s."""
    if touch.reflex_seq == 0:
        return None
    onset = next((r.message.accepted_ns for r in session.records
                  if r.key == "robot/state" and r.message.reflex_seq == touch.reflex_seq and r.message.accepted), None)
    if onset is None:
        return None
    end = onset + round((touch.resumed_after_s or 3.0) * 1e9)
    speeds = [np.abs(r.message.dq).max() for r in session.records
              if r.key == "robot/state" and onset <= r.message.stamp_ns <= end]
    return float(max(speeds)) if speeds else None


def onset_ns(session: Session, touch: analysis.TouchSummary) -> int | None:
    """When the bridge accepted the first command of the touch's reflex, ns (None: no reflex)."""
    if touch.reflex_seq == 0:
        return None
    return next((r.message.accepted_ns for r in session.records
                 if r.key == "robot/state" and r.message.reflex_seq == touch.reflex_seq and r.message.accepted), None)


def trajectory(session: Session, start_ns: int, end_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """The arm's joint positions between two times: times (s from ``start_ns``) and q (rad), one row each."""
    states = [r.message for r in session.records
              if r.key == "robot/state" and start_ns <= r.message.stamp_ns <= end_ns]
    t = np.array([(s.stamp_ns - start_ns) / 1e9 for s in states])
    return t, np.array([s.q for s in states]).reshape(len(states), -1)


def trajectory_error(a: Session, ta: analysis.TouchSummary, b: Session, tb: analysis.TouchSummary,
                     default_s: float = 3.0) -> float | None:
    """Largest difference (rad) of ``b``'s reflex motion from ``a``'s: of the joints' displacements from
    their poses at the reflex onset, over the reflex and its return.

    Both are aligned at their reflex onsets (in time and in pose: a task met
    at another phase starts the reflex from another pose) and compared from
    there until the earlier of the two resumptions of the task (after it one
    arm runs the task again while the other may still return; ``default_s``
    if neither resumed), ``b``'s joint positions interpolated at ``a``'s
    state times. None unless both touches caused a reflex.
    """
    oa, ob = onset_ns(a, ta), onset_ns(b, tb)
    if oa is None or ob is None:
        return None
    span = min(ta.resumed_after_s or default_s, tb.resumed_after_s or default_s)
    t_a, q_a = trajectory(a, oa, oa + round(span * 1e9))
    t_b, q_b = trajectory(b, ob, ob + round(span * 1e9))
    if len(t_a) < 2 or len(t_b) < 2:
        return None
    inside = t_a <= t_b[-1]
    interpolated = np.column_stack([np.interp(t_a[inside], t_b, q_b[:, j]) for j in range(q_b.shape[1])])
    return float(np.abs((q_a[inside] - q_a[0]) - (interpolated - q_b[0])).max())


def command_streams(a: Session, b: Session) -> str:
    """Whether ``b``'s decoded commands are ``a``'s, message for message, or where they part."""
    ca = [r.message for r in a.records if keys.is_command(r.key)]
    cb = [r.message for r in b.records if keys.is_command(r.key)]
    first = next((i for i, (x, y) in enumerate(zip(ca, cb)) if x != y), None)
    if first is None and len(ca) == len(cb):
        return f"{b.label}: {len(cb)} commands, identical to {a.label}'s"
    if first is None:
        return f"{b.label}: {len(cb)} commands, {a.label} {len(ca)}: the same up to the shorter one's end"
    return (f"{b.label}: {len(cb)} commands, {a.label} {len(ca)}: they part at command {first} "
            f"(t = {(ca[first].stamp_ns - a.t0_ns) / 1e9:.3f} s in {a.label})")


def table(sessions: list[Session], rows: list[list[analysis.TouchSummary | None]]) -> str:
    header = ["touch", "t (s)", "pad", "file", "gain", "force (N)", "onset (ms)", "withdrawal (mm)", "toward (mm)",
              "other pad closer (mm)", "peak speed (rad/s)", "peak (m/s)", "toward (m/s)", "resumed (s)",
              "dq vs first (mrad)"]

    f = analysis.cell
    out = []
    for i, row in enumerate(rows, start=1):
        for session, touch in zip(sessions, row):
            if touch is None:
                out.append([str(i), "-", "-", session.label, "missing", *["-"] * (len(header) - 4)])
                continue
            error = None
            if session is not sessions[0] and row[0] is not None:
                error = trajectory_error(sessions[0], row[0], session, touch)
            out.append([
                str(i), f"{(touch.start_ns - session.t0_ns) / 1e9:.2f}", touch.name, session.label, f"{touch.gain:.3f}",
                f(touch.impact_n, ".0f"), f(touch.onset_latency_ms, ".2f"), f(touch.withdrawal_mm, ".1f"),
                f(touch.toward_mm, ".1f"),
                f(touch.other_approach_mm, ".1f"), f(peak_joint_speed(session, touch), ".2f"),
                f(touch.peak_speed_m_s, ".3f"), f(touch.peak_toward_m_s, ".3f"), f(touch.resumed_after_s, ".2f"),
                f(None if error is None else 1e3 * error, ".3f"),
            ])
    return analysis.format_table(header, out)


def world_table(sessions: list[Session], rows: list[list[analysis.TouchSummary | None]]) -> str | None:
    """The touches' measured figures in the files that have a physics world (None if none has): per touch and
    file, how far the pad moved toward the finger and into it, the peak force and pressure on the person, the
    energy put into them, and the share of their body area's quasi-static ISO/TS 15066 limits."""
    if not any(t is not None and t.peak_force_n is not None for row in rows for t in row):
        return None
    header = ["touch", "pad", "file", "pad toward finger (mm)", "into finger (mm)", "peak force (N)",
              "peak pressure (N/cm^2)", "energy (mJ)", "of ISO limit (%)"]
    f = analysis.cell
    out = []
    for i, row in enumerate(rows, start=1):
        for session, touch in zip(sessions, row):
            if touch is None:
                continue
            out.append([str(i), touch.name, session.label, f(touch.pressed_toward_mm, ".1f"),
                        f(touch.into_finger_mm, ".1f"), f(touch.peak_force_n, ".1f"),
                        f(touch.peak_pressure_n_cm2, ".1f"), f(None if touch.energy_j is None else 1e3 * touch.energy_j,
                                                               ".1f"),
                        f(None if touch.of_limit is None else 100 * touch.of_limit, ".0f")])
    return analysis.format_table(header, out)


TOWARD_COLOR = "#d62728"
FIGURE_BEFORE_S = 0.2  # the figure starts this long before the touch's first skin sample
FIGURE_AFTER_S = 5.0  # and ends at most this long after it (each file's sooner: see touch_motion)


@dataclass
class TouchMotion:
    """One file's motion around one touch, as the figure draws it."""

    t: np.ndarray  # s from the touch's first skin sample
    dq: np.ndarray  # joint displacements from the onset pose, rad, one row per state
    away_mm: np.ndarray  # touched pad along its normal at the onset: + away from the contact, - toward it
    other_mm: np.ndarray  # the other pads' largest approach to the contact point (- : closer), mm
    other_pad: np.ndarray  # which pad that is, per state
    onset_s: float | None  # the reflex onset (None: no reflex)
    resumed_s: float | None  # the task's resumption


def touch_motion(session: Session, touch: analysis.TouchSummary, model: RobotModel) -> TouchMotion | None:
    """The arm around ``touch`` in ``session``, measured as the per-touch table measures it.

    The contact is the touched pad's point at the reflex onset and the
    direction its outward normal there (:func:`analysis.contact_motion`; the
    pose at the touch's first skin sample if no reflex followed). The window
    runs from ``FIGURE_BEFORE_S`` before the touch until the task resumed
    (after that the task moves the arm, not the reflex), the session's next
    touch's reflex began, or ``FIGURE_AFTER_S`` after the touch, whichever
    comes first. The other pads' approach counts from the onset only (before
    it, they were where the task put them).
    """
    start = touch.start_ns
    onset = onset_ns(session, touch)
    end = start + round(FIGURE_AFTER_S * 1e9)
    if onset is not None and touch.resumed_after_s is not None:
        end = min(end, onset + round(touch.resumed_after_s * 1e9))
    following = [onset_ns(session, t) for t in session.touches if t.start_ns > start and t.reflex_seq]
    end = min([end, *(o for o in following if o is not None and o > (onset or start))])
    states = [r.message for r in session.records if r.key == "robot/state"
              and start - FIGURE_BEFORE_S * 1e9 <= r.message.stamp_ns <= end]
    if len(states) < 2:
        return None
    t = np.array([(s.stamp_ns - start) / 1e9 for s in states])
    q = np.array([s.q for s in states])
    stamps = np.array([s.stamp_ns for s in states], dtype=np.int64)
    first = min(int(np.searchsorted(stamps, start if onset is None else onset)), len(q) - 1)  # as summarize
    q0 = q[first]
    away, other, worst = analysis.contact_motion(model, q, touch.pad, q0)
    other[:first] = np.nan
    return TouchMotion(t, q - q0, 1e3 * away, -1e3 * other, worst,
                       None if onset is None else (onset - start) / 1e9,
                       None if onset is None or touch.resumed_after_s is None
                       else (onset - start) / 1e9 + touch.resumed_after_s)


def file_label(session: Session) -> str:
    """A file in the figure's legend: its name and its reflex (from the recording's metadata)."""
    from nwr.services.tools.figures import TITLES

    name = session.path.name
    return f"{name}: {TITLES.get(session.strategy, session.strategy)}" if session.strategy else name


def draw(sessions: list[Session], rows: list[list[analysis.TouchSummary | None]], model: RobotModel) -> Any:
    """The comparison figure (a matplotlib Figure), one block per touch that caused a reflex in any file.

    Each block: the touched pad's motion along its normal (withdrawal up,
    toward the contact down), the other pads' closest approach to the
    contact point, and one small panel per joint with its displacement from
    the onset pose; one colour per file throughout, time from the touch's
    first skin sample.
    """
    from nwr.services.tools.figures import _pyplot, fit_scale

    plt = _pyplot()
    joints = model.desc.joints
    pads = [p.name for p in model.desc.pads]
    reflex_rows = [(i, row) for i, row in enumerate(rows, start=1) if any(t is not None and t.reflex_seq for t in row)]
    n = max(1, len(reflex_rows))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    width = max(2 * len(joints), 10)
    fig = plt.figure(figsize=(2.3 * len(joints), 4.6 * n + 0.9), dpi=100, layout="constrained")
    blocks = fig.subfigures(n, 1, squeeze=False)[:, 0] if n > 1 else [fig.subfigures(1, 1)]
    for block, (number, row) in zip(blocks, reflex_rows):
        grid = block.add_gridspec(2, width, height_ratios=(1.35, 1))
        ax_n = block.add_subplot(grid[0, :width * 3 // 5])
        ax_o = block.add_subplot(grid[0, width * 3 // 5:], sharex=ax_n)
        ax_j = [block.add_subplot(grid[1, j * width // len(joints):(j + 1) * width // len(joints)], sharex=ax_n)
                for j in range(len(joints))]
        for ax in ax_j[1:]:
            ax.sharey(ax_j[0])
        first = next(t for t in row if t is not None)
        missing = []
        named: set[tuple[int, int]] = set()  # (pad, mm) already written on the other pads' panel
        for c, (session, touch) in enumerate(zip(sessions, row)):
            motion = None if touch is None else touch_motion(session, touch, model)
            if motion is None:
                missing.append(session.path.name)
                continue
            color, lw = colors[c % len(colors)], max(1.0, 2.6 - 0.5 * c)  # later files thinner: overlaps show
            style = "-" if motion.onset_s is not None else ":"
            ax_n.plot(motion.t, motion.away_mm, style, color=color, lw=lw)
            ax_o.plot(motion.t, motion.other_mm, style, color=color, lw=lw)
            for j, ax in enumerate(ax_j):
                ax.plot(motion.t, motion.dq[:, j], style, color=color, lw=max(0.8, lw - 0.6))
            for at, marker in ((motion.onset_s, "o"), (motion.resumed_s, "s")):
                if at is not None and motion.t[0] <= at <= motion.t[-1] + 0.1:  # the last state may precede it
                    k = int(np.argmin(np.abs(motion.t - at)))
                    ax_n.plot(motion.t[k], motion.away_mm[k], marker, color=color, ms=6, mec="k", mew=0.6)
            k = int(np.nanargmin(motion.other_mm))
            if motion.other_mm[k] < -5.0 and (motion.other_pad[k], round(motion.other_mm[k])) not in named:
                named.add((motion.other_pad[k], round(motion.other_mm[k])))  # name the pad where it came closest
                ax_o.annotate(pads[motion.other_pad[k]], (motion.t[k], motion.other_mm[k]), fontsize=7,
                              color=color, xytext=(4, 3), textcoords="offset points")
        ax_n.xaxis.set_major_locator(plt.MaxNLocator(5))  # shared by the block's panels: few enough for the joints'
        for ax in (ax_n, ax_o):
            ax.axhline(0.0, color="0.3", lw=0.8)
            fit_scale([ax], "mm")
            low, high = ax.get_ylim()
            ax.set_ylim(min(low, -0.1 * (high - low)), high)
            ax.axhspan(ax.get_ylim()[0], 0.0, color=TOWARD_COLOR, alpha=0.07, lw=0)
        ax_n.set_ylabel("touched pad along its normal (mm)\n+ withdrawal, \u2212 toward the contact", fontsize=8)
        ax_n.set_title(f"{first.name}: the touched pad's motion along its outward normal at the reflex onset",
                       fontsize=9)
        ax_o.set_ylabel("closest other pad: change in\nits distance to the contact (mm)", fontsize=8)
        ax_o.set_title("other pads: the closest approach to the contact point", fontsize=9)
        fit_scale(ax_j, "rad")
        for j, ax in enumerate(ax_j):
            ax.set_title(joints[j], fontsize=8)
            ax.axhline(0.0, color="0.6", lw=0.6)
            if j == 0:
                ax.set_ylabel("joint displacement\nfrom the onset (rad)", fontsize=8)
            else:
                ax.tick_params(labelleft=False)
        for ax in (ax_n, ax_o, *ax_j):
            ax.axvline(0.0, color="0.5", ls="--", lw=0.7)

            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
        for ax in ax_j:
            ax.set_xlabel("time from the touch (s)", fontsize=8)
        ax_n.set_xlabel("time from the touch's first skin sample (s)", fontsize=8)
        ax_o.set_xlabel("time from the touch (s)", fontsize=8)
        title = f"touch {number}: {first.name} ({first.region}) at {(first.start_ns - sessions[0].t0_ns) / 1e9:.2f} s"
        title += f", gain {max(t.gain for t in row if t is not None):.2f}"
        if missing:
            title += f"; not in {', '.join(missing)}"
        block.suptitle(title, fontsize=11, fontweight="bold", x=0.01, ha="left")
    files = [plt.Line2D([], [], color=colors[c % len(colors)], lw=max(1.0, 2.6 - 0.5 * c), label=file_label(s))
             for c, s in enumerate(sessions)]
    marks = [plt.Line2D([], [], ls="", marker="o", color="0.7", mec="k", label="reflex onset"),
             plt.Line2D([], [], ls="", marker="s", color="0.7", mec="k", label="task resumed"),
             plt.Line2D([], [], ls=":", color="0.4", label="no reflex in that file"),
             plt.Rectangle((0, 0), 1, 1, color=TOWARD_COLOR, alpha=0.15, lw=0, label="toward the contact")]
    # The files on the first row(s), the marks on the last: the legend fills its columns top to bottom.
    cols = 4
    blank = plt.Line2D([], [], ls="", label=" ")
    files += [blank] * (-len(files) % cols)
    marks += [blank] * (cols - len(marks))
    rows = [files[i:i + cols] for i in range(0, len(files), cols)] + [marks]
    handles = [row[c] for c in range(cols) for row in rows]
    fig.legend(handles=handles, loc="outside upper center", ncol=cols, fontsize=9)
    return fig


def figure(sessions: list[Session], rows: list[list[analysis.TouchSummary | None]], model: RobotModel,
           path: Path) -> Path:
    """Write :func:`draw`'s figure to ``path`` (PNG)."""
    from nwr.services.tools.figures import _pyplot

    fig = draw(sessions, rows, model)
    fig.savefig(path)
    _pyplot().close(fig)
    return path


def _run(args: argparse.Namespace) -> int:
    profile = profile_for(args)
    desc = load_description(profile.robot.description or None)
    model = RobotModel(desc)
    sessions = [load_session(Path(p), desc, model, profile) for p in args.files]
    rows = line_up(sessions, args.window)
    for session in sessions:
        for note in session.notes:
            print(f"{session.label}: {note}")
    print(table(sessions, rows))
    world = world_table(sessions, rows)
    if world is not None:
        print("\nthe physics world's fingers (measured; \"-\" in a file without one):\n" + world)
        for note in summary.iso_notes([t for row in rows for t in row if t is not None]):
            print(note)
    print("\nreflex quality per file (every touch of the file that started a reflex):")
    quality = [analysis.quality(session.touches, session.label) for session in sessions]
    print(analysis.format_table(analysis.QUALITY_HEADER, analysis.quality_rows(quality)))
    if world is not None:
        print(analysis.format_table(analysis.WORLD_QUALITY_HEADER, analysis.world_quality_rows(quality)))
    if len(sessions) > 1:
        print("\ncommand streams (robot/command/<name>, decoded) against the first file's:")
        for session in sessions[1:]:
            print("  " + command_streams(sessions[0], session))
    if args.figure != "none":
        out = Path(args.figure or f"{Path(args.files[0]).stem}-compare.png")
        figure(sessions, rows, model, out)
        print(f"\nwrote {out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("compare", help="line up the touches of several recordings and compare the reflexes",
                       description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("files", nargs="+", help="MCAP recordings (for example a session and its replays)")
    p.add_argument("--window", type=float, default=0.3, help="touches within this many seconds line up (default 0.3)")
    p.add_argument("--figure", help="PNG to write (default: <first file>-compare.png; 'none' for no figure)")
    p.set_defaults(handler=_run)
