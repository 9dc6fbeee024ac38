"""``nwr compare A.mcap B.mcap ...``: the same touches, reflex against reflex.

Touches are lined up across recordings by pad and by start time from each
recording's first skin sample (within ``--window`` seconds), which is how a
replay of one session against several reflex services lines up. Per touch
and file: pad, gain, onset latency, the touched pad's withdrawal along its
normal, how far it came toward the contact, the largest approach of any
other pad to the contact point, the peak joint speed during the reflex and
its return, the time until the task resumed, and how far the reflex motion
strayed from the first file's (the largest difference of the joints'
displacements from their onset poses, from the reflex onset until the earlier
of the two resumptions, the two aligned at their onsets). Below the table, each file's command stream against the
first's: identical decoded messages (a deterministic replay of the first
file), or where they part. A PNG overlays, per touch, the joint
trajectories and the touched pad's distance from the contact.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nwr.common import keys
from nwr.common.config import profile_for
from nwr.common.recordings import Recorded, read_recording
from nwr.common.robot import RobotDescription, RobotModel, load_description
from nwr.services.tools import analysis


@dataclass
class Session:
    path: Path
    label: str
    records: list[Recorded]
    t0_ns: int
    touches: list[analysis.TouchSummary]


def load_session(path: Path, desc: RobotDescription, model: RobotModel) -> Session:
    records, metadata = read_recording(path)
    t0 = next((r.message.stamp_ns for r in records if r.key == "skin/pressure"), 0)
    strategy = metadata.get("session", {}).get("strategy", "")
    label = f"{path.stem} ({strategy})" if strategy else path.stem
    return Session(path, label, records, t0, analysis.summarize(records, desc, model))


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
    header = ["touch", "t (s)", "pad", "file", "gain", "onset (ms)", "withdrawal (mm)", "toward (mm)",
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
                f(touch.onset_latency_ms, ".2f"), f(touch.withdrawal_mm, ".1f"), f(touch.toward_mm, ".1f"),
                f(touch.other_approach_mm, ".1f"), f(peak_joint_speed(session, touch), ".2f"),
                f(touch.peak_speed_m_s, ".3f"), f(touch.peak_toward_m_s, ".3f"), f(touch.resumed_after_s, ".2f"),
                f(None if error is None else 1e3 * error, ".3f"),
            ])
    return analysis.format_table(header, out)


def figure(sessions: list[Session], rows: list[list[analysis.TouchSummary | None]], model: RobotModel,
           path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reflex_rows = [row for row in rows if any(t is not None and t.reflex_seq for t in row)]
    n = max(1, len(reflex_rows))
    fig, axes = plt.subplots(n, 2, figsize=(11, 2.6 * n), dpi=110, squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for r, row in enumerate(reflex_rows):
        ax_q, ax_d = axes[r]
        for c, (session, touch) in enumerate(zip(sessions, row)):
            if touch is None or not touch.reflex_seq:
                continue
            onset = next((x.message.accepted_ns for x in session.records if x.key == "robot/state"
                          and x.message.reflex_seq == touch.reflex_seq and x.message.accepted), None)
            if onset is None:
                continue
            window = [x.message for x in session.records if x.key == "robot/state"
                      and onset - 2e8 <= x.message.stamp_ns <= onset + 3e9]
            t = np.array([s.stamp_ns - onset for s in window]) / 1e9
            q = np.array([s.q for s in window])
            color = colors[c % len(colors)]
            for j in range(q.shape[1]):
                ax_q.plot(t, q[:, j], color=color, lw=1, alpha=0.8, label=session.label if j == 0 else None)
            q0 = q[np.argmin(np.abs(t))]
            contact = model.pad_point(q0, touch.pad)
            distance = [np.linalg.norm(model.pad_point(x, touch.pad) - contact) for x in q]
            ax_d.plot(t, 1e3 * np.asarray(distance), color=color, lw=1.5, label=session.label)
        first = next(t for t in row if t is not None)
        ax_q.set_title(f"touch on {first.name}: joint positions (rad)", fontsize=9)
        ax_d.set_title(f"touch on {first.name}: pad's distance from the contact (mm)", fontsize=9)
        for ax in (ax_q, ax_d):
            ax.set_xlabel("time from the reflex onset (s)", fontsize=8)
            ax.tick_params(labelsize=7)
        ax_d.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _run(args: argparse.Namespace) -> int:
    profile = profile_for(args)
    desc = load_description(profile.robot.description or None)
    model = RobotModel(desc)
    sessions = [load_session(Path(p), desc, model) for p in args.files]
    rows = line_up(sessions, args.window)
    print(table(sessions, rows))
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
