"""The study's questionnaires as a local web page (``nwr study --forms``, ``nwr study forms``).

A Starlette app over one answer store (:mod:`nwr.services.tools.study.store`):
the index shows the running session's participant and the form that is due;
``/p/<participant>/block/<n>`` is the per-condition form of a recorded block
(Godspeed semantic differentials and the custom Likert items), and
``/p/<participant>/final`` the comparative form (forced choices with "no
preference", open questions). The condition and order come from the session's
plan in the store, never from the person filling in the form.

Every rated item and forced choice is ``required`` in the HTML and checked
again here; a missing or out-of-scale answer re-renders the form with a
message and stores nothing. Each valid submission goes to the store at once,
in its own transaction; a second one of the same form is refused with a
message page. Plain HTML from ``common/study/templates``: no JavaScript, no
external assets (the lab machine may be offline).
"""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jinja2
import uvicorn
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import RedirectResponse, Response
from starlette.routing import Route
from starlette.templating import Jinja2Templates

from nwr.common.errors import StudyError
from nwr.common.questionnaire import QUESTIONNAIRE_PATH, Questionnaire
from nwr.services.tools.study.store import NO_PREFERENCE, Block, ConditionForm, FinalForm, Store

log = logging.getLogger(__name__)

TEMPLATES = QUESTIONNAIRE_PATH.parent / "templates"
DEFAULT_PORT = 8770


def parse_ratings(q: Questionnaire, data: Mapping[str, str]) -> tuple[dict[str, int], dict[str, str]]:
    """A per-condition form's posted fields as ratings, and a message per item that is missing or off the
    scale (empty: the form is complete)."""
    ratings: dict[str, int] = {}
    errors: dict[str, str] = {}
    for item in q.rated_items():
        raw = data.get(item, "").strip()
        if not raw:
            errors[item] = "no answer"
            continue
        try:
            value = int(raw)
        except ValueError:
            errors[item] = f"{raw!r} is not a number from 1 to {q.points}"
            continue
        if not 1 <= value <= q.points:
            errors[item] = f"{value} is out of the scale 1 to {q.points}"
            continue
        ratings[item] = value
    return ratings, errors


def parse_final(q: Questionnaire, options: list[str], data: Mapping[str, str]
                ) -> tuple[dict[str, str], dict[str, str], dict[str, str]]:
    """A final form's posted fields as choices and open answers, and a message per question that is missing
    or names no option (``options``: the participant's conditions and "none")."""
    choices: dict[str, str] = {}
    answers: dict[str, str] = {}
    errors: dict[str, str] = {}
    for choice in q.choice:
        value = data.get(choice.id, "").strip()
        if not value:
            errors[choice.id] = "no answer"
        elif value not in options:
            errors[choice.id] = f"{value!r} is none of the choices"
        else:
            choices[choice.id] = value
    for question in q.open:
        text = data.get(question.id, "").strip()
        if question.required and not text:
            errors[question.id] = "no answer"
        answers[question.id] = text
    return choices, answers, errors


@dataclass(frozen=True)
class Due:
    """What a participant has to fill in next."""

    participant: str
    blocks: list[Block]
    form: str  # "block", "final", "done" or "wait" (the next block is not recorded yet)
    block: Block | None = None  # the block whose form is due


def due(store: Store, participant: str) -> Due:
    blocks = store.blocks(participant)
    for b in blocks:
        if b.answered_at is None:
            return Due(participant, blocks, "block" if b.recorded_at is not None else "wait", b)
    if store.submitted_at(participant) is None:
        return Due(participant, blocks, "final")
    return Due(participant, blocks, "done")


def create_app(store_path: str | Path) -> Starlette:
    """The forms over the store at ``store_path`` (created if missing, with the packaged questionnaire)."""
    store_path = Path(store_path)
    with Store(store_path) as store:
        q = store.questionnaire
    env = jinja2.Environment(loader=jinja2.FileSystemLoader(TEMPLATES), autoescape=True,
                             undefined=jinja2.StrictUndefined)
    templates = Jinja2Templates(env=env)

    def page(request: Request, name: str, status: int = 200, **context: Any) -> Response:
        return templates.TemplateResponse(request, name, {"q": q, "no_pref": NO_PREFERENCE, **context},
                                          status_code=status)

    def message(request: Request, title: str, text: str, status: int, participant: str | None = None) -> Response:
        return page(request, "message.html", status, title=title, text=text, participant=participant)

    def open_store() -> Store:
        return Store(store_path, create=False)

    def block_of(store: Store, participant: str, n: int) -> Block | None:
        return next((b for b in store.blocks(participant) if b.block == n), None)

    async def index(request: Request) -> Response:
        with open_store() as store:
            current = store.current_participant()
            everyone = list(dict.fromkeys(b.participant for b in store.blocks()))
            dues = [due(store, p) for p in everyone]
        return page(request, "index.html", current=current, dues=dues[::-1])

    async def condition_form(request: Request) -> Response:
        participant = request.path_params["participant"]
        n = request.path_params["block"]
        with open_store() as store:
            block = block_of(store, participant, n)
            if block is None:
                return message(request, "No such block", f"Participant {participant} has no block {n} in this "
                               "study's plan: start the session with `nwr study`.", 404)
            if block.answered_at is not None:
                return message(request, "Already answered", f"The questionnaire for block {n} of participant "
                               f"{participant} was already submitted at {block.answered_at}. Thank you!", 409,
                               participant)
            if block.recorded_at is None:
                return message(request, "Not yet", f"Block {n} of participant {participant} has not been run yet: "
                               "its questionnaire comes after it.", 409, participant)
            total = len(store.blocks(participant))
            if request.method == "GET":
                return page(request, "condition.html", block=block, total=total, values={}, errors={})
            data = {k: v for k, v in (await request.form()).items() if isinstance(v, str)}
            ratings, errors = parse_ratings(q, data)
            if errors:
                return page(request, "condition.html", 400, block=block, total=total, values=data, errors=errors)
            form = ConditionForm(participant=participant, condition=block.condition, order=block.order,
                                 block=block.block, ratings=ratings, recording=block.recording)
            try:
                store.submit(form)
            except StudyError as exc:
                return message(request, "Not stored", str(exc), 409, participant)
        log.info("participant %s, block %d (%s): questionnaire stored", participant, n, block.condition)
        return RedirectResponse(request.url_for("thanks", participant=participant).path, status_code=303)

    async def final_form(request: Request) -> Response:
        participant = request.path_params["participant"]
        with open_store() as store:
            state = due(store, participant)
            if not state.blocks:
                return message(request, "No such participant", f"Participant {participant} has no session in "
                               "this study: start it with `nwr study`.", 404)
            if state.form == "done":
                return message(request, "Already answered", f"Participant {participant}'s final questionnaire was "
                               f"already submitted at {store.submitted_at(participant)}. Thank you!", 409, participant)
            if state.form != "final":
                return message(request, "Not yet", "The final questionnaire comes after every block's: "
                               f"{len([b for b in state.blocks if b.answered_at is None])} still to answer.", 409,
                               participant)
            options = [b.condition for b in state.blocks] + [NO_PREFERENCE]
            if request.method == "GET":
                return page(request, "final.html", participant=participant, blocks=state.blocks, values={},
                            errors={})
            data = {k: v for k, v in (await request.form()).items() if isinstance(v, str)}
            choices, answers, errors = parse_final(q, options, data)
            if errors:
                return page(request, "final.html", 400, participant=participant, blocks=state.blocks, values=data,
                            errors=errors)
            try:
                store.submit(FinalForm(participant=participant, choices=choices, answers=answers))
            except StudyError as exc:
                return message(request, "Not stored", str(exc), 409, participant)
        log.info("participant %s: final questionnaire stored", participant)
        return RedirectResponse(request.url_for("thanks", participant=participant).path, status_code=303)

    async def thanks(request: Request) -> Response:
        participant = request.path_params["participant"]
        with open_store() as store:
            state = due(store, participant)
        return page(request, "thanks.html", due=state)

    return Starlette(routes=[
        Route("/", index, name="index"),
        Route("/p/{participant}/block/{block:int}", condition_form, methods=["GET", "POST"], name="block"),
        Route("/p/{participant}/final", final_form, methods=["GET", "POST"], name="final"),
        Route("/p/{participant}/thanks", thanks, name="thanks"),
    ])


class FormServer:
    """The forms served by uvicorn in a background thread; :meth:`stop` (or ``with``) ends it."""

    def __init__(self, store_path: str | Path, host: str = "127.0.0.1", port: int = DEFAULT_PORT) -> None:
        app = create_app(store_path)
        # Bound here: a port in use is an error now, and port 0 gives a free one.
        self.sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.sock.bind((host, port))
        except OSError as exc:
            self.sock.close()
            raise StudyError(f"cannot serve the questionnaire on {host}:{port}: {exc} (another --forms PORT?)"
                             ) from exc
        self.host = host
        self.port = int(self.sock.getsockname()[1])
        config = uvicorn.Config(app, log_config=None, access_log=False, lifespan="off", timeout_graceful_shutdown=2)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]},
                                       name="study-forms", daemon=True)
        self.thread.start()
        while not self.server.started:
            if not self.thread.is_alive():
                self.sock.close()
                raise StudyError(f"the questionnaire's server on {self.url} did not start (see the log above)")
            self.thread.join(0.02)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(10.0)
        self.sock.close()

    def __enter__(self) -> FormServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def serve(store_path: str | Path, host: str = "127.0.0.1", port: int = DEFAULT_PORT) -> FormServer:
    """Start serving the forms of the store at ``store_path`` in a background thread; call ``.stop()``."""
    return FormServer(store_path, host, port)
