"""``nwr study``: the paper's within-subject protocol on the live pipeline.

Three conditions, uniform (UR), location-dependent (LR) and Cartesian (CR),
in one of three counterbalanced orders (a Latin square: every condition once
in every position); ``--conditions`` runs others (any reflex strategies,
e.g. ``uniform,cartesian,whole-arm``), in as many orders as there are
conditions. All the planners run from the start; between blocks
the active one is switched (``control/active``) without restarting
anything, and each block is recorded to its own file,
``recordings/<participant>/<participant>-b<block>-<condition>.mcap``, with
the participant, order, block and condition in the session metadata.

During a block the arm draws the figure-eight and the planner lights the
target pad; with the simulated skin, ``--follow-target`` makes a simulated
participant press it every few seconds at varying pressures.

The session's plan (participant, order, conditions block by block, and
when each block was recorded) goes to the study's answer store beside the
recordings (``recordings/study.sqlite``). With ``--forms [PORT]`` the
questionnaires are served as a local web page (``--forms-host`` the address
a tablet reaches); after each block the session waits until that block's
form is submitted, after the last one until the final form is. ``nwr study
forms`` serves them alone (answers after a session).

The questionnaire's answers go to the same store: ``nwr study submit
FORM.json`` writes one form, ``nwr study export --csv OUT`` writes them all in long format and
``nwr study analyze`` runs the paper's analysis (docs/study.md).
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.errors import ConfigError, NwrError
from nwr.common.node import Node
from nwr.services.pipeline.graph import Layout, Unit, recorder_args, units
from nwr.services.pipeline.supervisor import failed, spawn, stop_all
from nwr.services.planner import strategies
from nwr.services.profile import profile_for
from nwr.services.tools.study.store import STORE_NAME, Store, check_participant, recording_name

if TYPE_CHECKING:
    from nwr.services.tools.study.web import FormServer

log = logging.getLogger(__name__)

FORMS_PORT = 8770  # nwr study --forms (study_web.DEFAULT_PORT, without importing starlette at start-up)

# The paper's conditions: UR, LR, CR.
PAPER_CONDITIONS = ("uniform", "location", "cartesian")


def orders(conditions: tuple[str, ...]) -> tuple[tuple[str, ...], ...]:
    """The counterbalanced orders of ``conditions``: a cyclic Latin square (every condition once in every
    position), the first order the conditions as given."""
    return tuple(conditions[i:] + conditions[:i] for i in range(len(conditions)))


# The three counterbalanced orders of the paper's study (a 3 x 3 Latin square).
ORDERS = orders(PAPER_CONDITIONS)


def order_of(n: int, conditions: tuple[str, ...] = PAPER_CONDITIONS) -> tuple[str, ...]:
    square = orders(conditions)
    if not 1 <= n <= len(square):
        raise ConfigError(f"--order {n}: the study has orders 1 to {len(square)}: "
                          + "; ".join(f"{i + 1} = {' -> '.join(o)}" for i, o in enumerate(square)))
    return square[n - 1]


def conditions_of(text: str | None) -> tuple[str, ...]:
    """``--conditions``: reflex strategies, comma-separated, two or more, each once (default: the paper's)."""
    if not text:
        return PAPER_CONDITIONS
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    for name in names:
        strategies.check(name)
    if len(names) < 2 or len(set(names)) != len(names):
        raise ConfigError(f"--conditions {text!r}: two or more reflex strategies, each once")
    return names


def block_path(directory: Path, participant: str, block: int, condition: str) -> Path:
    return directory / recording_name(participant, block, condition)


class Switcher:
    """Asks the bridge to follow a planner and waits until it does (after any reflex in progress)."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.owner = ""
        self.changed = threading.Condition()
        self.publish = node.publisher(keys.CONTROL_ACTIVE)
        self.seq = 0
        node.subscribe(keys.ROBOT_STATE, self._on_state)

    def _on_state(self, state: m.RobotState) -> None:
        with self.changed:
            self.owner = state.owner
            self.changed.notify_all()

    def switch(self, name: str, timeout_s: float = 15.0) -> bool:
        self.publish(m.SwitchRequest(seq=self.seq, stamp_ns=self.node.clock.now_ns(), name=name,
                                     requested_by="nwr study"))
        self.seq += 1
        with self.changed:
            return self.changed.wait_for(lambda: self.owner == name, timeout_s)


def _run(args: argparse.Namespace) -> int:
    profile = profile_for(args)
    conditions = conditions_of(args.conditions)
    order = order_of(args.order, conditions)
    check_participant(args.participant)
    if args.forms_port is not None:  # a wildcard or a name for the forms: refused before anything is written
        from nwr.services.tools.study.web import bind_address

        bind_address(args.forms_host)
    directory = Path(profile.recorder.directory)
    paths = [block_path(directory, args.participant, i + 1, c) for i, c in enumerate(order)]
    existing = [p for p in paths if p.exists()]
    if existing and not args.overwrite:
        raise ConfigError(f"{existing[0]} exists: choose another participant ID, or --overwrite")
    paths[0].parent.mkdir(parents=True, exist_ok=True)
    store = Store(directory / STORE_NAME)
    forms = None
    try:
        store.plan(args.participant, args.order, order, replace=args.overwrite)
        if args.forms_port is not None:
            from nwr.services.tools.study.web import serve

            forms = serve(store.path, args.forms_host, args.forms_port)
            print(f"questionnaires for participant {args.participant}: {forms.url}", flush=True)
        return _run_blocks(args, profile, conditions, order, paths, store, forms)
    finally:
        if forms is not None:
            forms.stop()
        store.close()


def _wait_for_form(store: Store, stop: threading.Event, url: str, participant: str, condition: str | None,
                   what: str) -> bool:
    """Wait until ``participant``'s form (``condition``'s, None: the final one) is in the store; False if the
    study is interrupted first."""
    print(f"waiting for {what}: {url}", flush=True)
    log.info("waiting for %s (%s)", what, url)
    while store.submitted_at(participant, condition) is None:
        if stop.wait(0.5):
            log.warning("study interrupted while waiting for %s", what)
            return False
    log.info("%s submitted", what)
    return True


def _run_blocks(args: argparse.Namespace, profile: Profile, conditions: tuple[str, ...], order: tuple[str, ...],
                paths: list[Path], store: Store, forms: FormServer | None) -> int:
    # The gateway starts once the others are alive; each block has its own recorder.
    layout = Layout(planners=list(conditions), active=order[0], gateway=None)
    procs = {u.label: spawn(u, args.profile, args.log_level) for u in units(layout)}
    done: list[tuple[int, str, Path]] = []
    try:
        with Node("study", profile.robot.name, profile.zenoh, token=False) as node:
            node.install_signal_handlers()
            missing = node.wait_for(list(procs), timeout_s=30.0)
            if missing:
                log.error("services %s did not come up within 30 s", missing)
                return 1
            gateway = ["--follow-target", str(args.follow_target)] if args.follow_target else []
            procs["gateway"] = spawn(Unit("gateway", "gateway", tuple(gateway)), args.profile, args.log_level)
            switcher = Switcher(node)
            for block, (condition, path) in enumerate(zip(order, paths), start=1):
                if not switcher.switch(condition):
                    log.error("the bridge did not switch to %r within 15 s: stopping the study", condition)
                    return 1
                log.info("block %d of %d: %s, %.0f s, recording to %s", block, len(order), condition, args.block_s,
                         path)
                labels = {"participant": args.participant, "order": str(args.order), "block": str(block),
                          "condition": condition}
                recorder = spawn(Unit("recorder", "recorder", tuple(recorder_args(path, path.stem, condition, labels))),
                                 args.profile, args.log_level)
                if node.wait_for(["recorder"], timeout_s=15.0):
                    log.error("the recorder of block %d did not start", block)
                    recorder.kill()
                    return 1
                stopped = node.stop.wait(args.block_s)
                if failed(stop_all({"recorder": recorder}, 15.0)):  # killed if it hangs: the next block goes on
                    log.warning("the recorder of block %d did not stop cleanly: %s may be unfinished", block, path)
                done.append((block, condition, path))
                store.recorded(args.participant, block)
                if stopped:
                    log.warning("study interrupted during block %d", block)
                    break
                if forms is not None:
                    url = f"{forms.url}p/{args.participant}/block/{block}"
                    if not _wait_for_form(store, node.stop, url, args.participant, condition,
                                          f"the questionnaire of block {block} ({condition})"):
                        break
                    if block == len(order) and not _wait_for_form(
                            store, node.stop, f"{forms.url}p/{args.participant}/final", args.participant, None,
                            "the final questionnaire"):
                        break
                for _ in range(20):  # its token must be gone before the next recorder's
                    if "recorder" not in node.alive_services(0.3):
                        break
    finally:
        stop_all(procs)
    _print_blocks(done, profile)
    complete = len(done) == len(order)
    if forms is not None:
        complete = complete and store.submitted_at(args.participant) is not None
    return 0 if complete else 1


def _print_blocks(done: list[tuple[int, str, Path]], profile: Profile) -> None:
    from nwr.common.recordings import read_recording
    from nwr.common.robot import load_description
    from nwr.services.tools.recordings import analysis

    desc = load_description(profile.robot.description or None)
    print("\nblock  condition  touches  reflexes  onset p50 (ms)  approached  file")
    for block, condition, path in done:
        try:  # a recorder that was killed leaves an unfinished file: say so, the other blocks still count
            records, _ = read_recording(path)
        except NwrError as exc:
            print(f"{block:5d}  {condition:9s}  unreadable: {exc}")
            continue
        touches = analysis.summarize(records, desc)
        reflexes = [t for t in touches if t.reflex_seq]
        onsets = [t.onset_latency_ms for t in reflexes if t.onset_latency_ms is not None]
        approached = sum(1 for t in reflexes if (t.toward_mm or 0) > 1.0)
        p50 = f"{np.median(onsets):.2f}" if onsets else "-"
        print(f"{block:5d}  {condition:9s}  {len(touches):7d}  {len(reflexes):8d}  {p50:>14s}  {approached:10d}  "
              f"{path}")


def _store_path(args: argparse.Namespace) -> Path:
    return Path(args.store) if args.store else Path(profile_for(args).recorder.directory) / STORE_NAME


def _submit(args: argparse.Namespace) -> int:
    from nwr.services.tools.study.store import Store, decode_form

    with Store(_store_path(args), args.questionnaire) as store:
        for path in args.forms:
            form = decode_form(Path(path).read_bytes(), path)
            store.submit(form, replace=args.replace)
            what = f"condition {form.condition!r}" if hasattr(form, "condition") else "final form"
            log.info("%s: participant %s, %s written to %s", path, form.participant, what, store.path)
    return 0


def _export(args: argparse.Namespace) -> int:
    from nwr.services.tools.study.store import Store

    with Store(_store_path(args), create=False) as store:
        n = store.export_csv(args.csv, free_text=args.free_text)
    left_out = "" if args.free_text else " (open answers left out: --free-text to include them)"
    print(f"{n} answers from {store.path} written to {args.csv}{left_out}")
    return 0


def _forms(args: argparse.Namespace) -> int:
    from nwr.common.errors import StudyError
    from nwr.services.tools.study.web import serve

    path = _store_path(args)
    if not path.exists():
        raise StudyError(f"no study store at {path}: `nwr study` creates it with the first session "
                         "(or give --store PATH)")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with serve(path, args.host, args.port) as server:
        print(f"questionnaires of {path}: {server.url} (Ctrl-C to stop)", flush=True)
        while server.thread.is_alive() and not stop.wait(0.5):
            pass
    return 0


def _analyze(args: argparse.Namespace) -> int:
    from nwr.common.robot import load_description
    from nwr.services.tools.study import analysis as study_analysis

    store = _store_path(args)
    out = Path(args.out) if args.out else store.parent / "study-analysis"
    description = profile_for(args).robot.description or None
    result, report, pictures, tables = study_analysis.run(store, out, lambda: load_description(description),
                                                          exclude_degraded=args.exclude_degraded)
    for participant, why in result.excluded.items():
        log.warning("participant %s excluded from the within-subject tests: %s", participant, why)
    print(f"{len(result.complete)} of {len(result.participants)} participants in the tests; report {report}; "
          f"figures {', '.join(p.name for p in pictures) or 'none'}; one row per block in "
          f"{', '.join(t.name for t in tables)}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("study", help="run the paper's three-condition study protocol (or other conditions), one "
                                     "recording per block",
                       description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    # Required for a session (checked in _session): argparse would also demand them of `nwr study analyze`.
    p.add_argument("--participant", help="participant ID, a pseudonymous code such as P07 (up to 8 letters, an "
                                         "optional - or _, 1 to 6 digits; names the recordings' folder); required "
                                         "for a session")
    p.add_argument("--order", type=int, help="required for a session: "
                        "counterbalanced order (a cyclic Latin square of the conditions); the paper's: "
                        + "; ".join(f"{i + 1} = {' -> '.join(o)}" for i, o in enumerate(ORDERS)))
    p.add_argument("--conditions", metavar="R1,R2,...",
                   help="the reflex strategies to compare, comma-separated (default: the paper's "
                        f"{','.join(PAPER_CONDITIONS)}; e.g. uniform,cartesian,whole-arm)")
    p.add_argument("--block-s", type=float, default=300.0, help="duration of each block, s (the study: about 5 min)")
    p.add_argument("--follow-target", type=float, metavar="SECONDS",
                   help="simulated participant: press the target pad every SECONDS (simulated skin)")
    p.add_argument("--overwrite", action="store_true", help="replace the participant's existing recordings")
    p.add_argument("--forms", dest="forms_port", type=int, nargs="?", const=FORMS_PORT, metavar="PORT",
                   help=f"serve the questionnaires as a web page (port {FORMS_PORT} if none given) and wait after "
                        "each block until its form is submitted, after the last for the final form")
    p.add_argument("--forms-host", default="127.0.0.1", metavar="ADDRESS",
                   help="the address the forms are served on (default 127.0.0.1: this machine only; the lab "
                        "network's address of this machine for a tablet, said loudly on stderr; requests naming "
                        "another host, and forms posted from other pages, are refused)")

    def _session(args: argparse.Namespace) -> int:
        missing = [flag for flag, value in (("--participant", args.participant), ("--order", args.order))
                   if value is None]
        if missing:
            p.error(f"the following arguments are required: {', '.join(missing)}")
        return _run(args)

    p.set_defaults(handler=_session)
    answers = p.add_subparsers(dest="study_command", metavar="{submit,forms,export,analyze}",
                               title="the questionnaire's answers (docs/study.md)")
    store_help = f"the study's answer store (default: the profile's recordings folder/{STORE_NAME})"
    s = answers.add_parser("submit", help="write filled-in forms (JSON) to the study's answer store",
                           description="Write each FORM (a JSON object: \"form\": \"condition\" with participant, "
                                       "condition, order, block and ratings; or \"form\": \"final\" with "
                                       "participant, choices and answers) in one transaction each. A form already "
                                       "submitted is refused unless --replace.")
    s.add_argument("forms", nargs="+", metavar="FORM", help="a submission as JSON (docs/study.md)")
    s.add_argument("--store", metavar="PATH", help=store_help)
    s.add_argument("--questionnaire", metavar="FILE",
                   help="a new store's questionnaire (default: the packaged common/study/questionnaire.toml)")
    s.add_argument("--replace", action="store_true", help="replace a form already submitted")
    s.set_defaults(handler=_submit)
    f = answers.add_parser("forms", help="serve the questionnaires as a web page (answers after a session)",
                           description="Serve the per-condition and final questionnaires of every session in the "
                                       "store (nwr study registers them) until Ctrl-C.")
    f.add_argument("--store", metavar="PATH", help=store_help)
    f.add_argument("--port", type=int, default=FORMS_PORT, help=f"TCP port (default {FORMS_PORT})")
    f.add_argument("--host", default="127.0.0.1", metavar="ADDRESS",
                   help="the address to serve on (default 127.0.0.1: this machine only; this machine's LAN "
                        "address for a tablet, said loudly on stderr)")
    f.set_defaults(handler=_forms)
    e = answers.add_parser("export", help="every answer as CSV, one row per participant x condition x item",
                           description="Every answer in tidy long format: one row per participant x condition x "
                                       "item, with order, block, recording, subscale and whether it is reversed; "
                                       "the final form's answers with an empty condition. The open answers (free "
                                       "text) only with --free-text. A cell a spreadsheet would run as a formula "
                                       "(starting with = + - @, a tab or CR, other than a number) starts with '.")
    e.add_argument("--csv", required=True, metavar="OUT", help="the CSV file to write")
    e.add_argument("--free-text", action="store_true",
                   help="include the open answers (free text, which may identify someone; left out by default)")
    e.add_argument("--store", metavar="PATH", help=store_help)
    e.set_defaults(handler=_export)
    a = answers.add_parser("analyze", help="the paper's analysis of the answers and recordings: report and figures",
                           description=study_analysis_doc(), formatter_class=argparse.RawDescriptionHelpFormatter)
    a.add_argument("--store", metavar="PATH", help=store_help)
    a.add_argument("--out", metavar="DIR", help="where report.md and the figures go (default: study-analysis/ "
                                                 "beside the store)")
    a.add_argument("--exclude-degraded", action="store_true",
                   help="leave out of the tests the answers of blocks during which the bridge rejected commands or "
                        "stopped the arm (the report and the study table list them either way)")
    a.set_defaults(handler=_analyze)


def study_analysis_doc() -> str:
    """The analysis module's docstring, for ``--help`` (without importing scipy and matplotlib at start-up)."""
    import ast

    source = Path(__file__).with_name("analysis.py").read_text(encoding="utf-8")
    return (ast.get_docstring(ast.parse(source)) or "").split("\n\n", 1)[1]
