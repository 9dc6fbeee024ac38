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

Only the participant's own page can submit a form (:func:`refusal`, the
:class:`Guard` around the app, and a token per form):

- the server is bound to one address, loopback unless a LAN address is given
  (:func:`bind_address`; a wildcard or a name is refused, a LAN address said
  loudly once on stderr, :func:`lan_warning`);
- every request's Host must name that address and port (a foreign Host is a
  DNS rebinding page reading the participant's forms: 421);
- every POST must come from one of the server's own pages: its Origin (or,
  without one, its Referer) must be the server's own (403), and it must
  carry the form's token, an HMAC of the form's path under a secret drawn
  with :mod:`secrets` when the server starts (403: reload the form);
- a POST body over :data:`MAX_BODY_BYTES` is refused (413) before it is read;
  an open answer over :data:`~nwr.services.tools.study.store.MAX_ANSWER_CHARS`
  shows the form again with a message.

A refused request stores nothing, so a cross-site POST cannot lock the
participant out of their own form ("Already answered"). Every refusal is a
page with its reason and an HTTP status; every response forbids framing,
scripts and loads from elsewhere (Content-Security-Policy) and caching.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import logging
import secrets
import socket
import sys
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import jinja2
import uvicorn
from starlette.applications import Starlette
from starlette.datastructures import Headers, MutableHeaders
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import RedirectResponse, Response
from starlette.routing import Route
from starlette.templating import Jinja2Templates
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from nwr.common.errors import StudyError
from nwr.common.questionnaire import QUESTIONNAIRE_PATH, Questionnaire
from nwr.services.tools.study.store import MAX_ANSWER_CHARS, NO_PREFERENCE, Block, ConditionForm, FinalForm, Store

log = logging.getLogger(__name__)

TEMPLATES = QUESTIONNAIRE_PATH.parent / "templates"
DEFAULT_PORT = 8770
# A form's post is a few kB (the final form's open answers at most 4 x MAX_ANSWER_CHARS characters, each up to
# 4 bytes in UTF-8, percent-encoded 3 times over): anything larger is refused before it is read.
MAX_BODY_BYTES = 256 * 1024
# Every page: no scripts, no frames, nothing loaded from elsewhere, forms posted only back here, nothing cached.
SECURITY_HEADERS = {
    "content-security-policy": "default-src 'none'; style-src 'unsafe-inline'; form-action 'self'; "
                               "frame-ancestors 'none'; base-uri 'none'",
    "x-content-type-options": "nosniff",
    "x-frame-options": "DENY",
    "referrer-policy": "same-origin",
    "cache-control": "no-store",
}


# -- who may ask: the server's own address, its own pages ---------------------------------


def bind_address(host: str) -> tuple[str, bool]:
    """The address to serve on for ``--forms-host``/``--host`` and whether it is off this machine (a LAN
    address). StudyError for a name (other than localhost), a wildcard (every network of the machine) or a
    multicast address: the Host check needs the one address the tablet uses."""
    text = host.strip().strip("[]")
    if text.lower() == "localhost":
        return "127.0.0.1", False
    try:
        address = ipaddress.ip_address(text)
    except ValueError:
        raise StudyError(f"--forms-host {host!r}: give an IP address of this machine (e.g. 127.0.0.1, or its "
                         "address on the lab network such as 192.168.1.20), not a name") from None
    if address.is_unspecified:
        raise StudyError(f"--forms-host {host!r} would serve the questionnaires on every network of this machine: "
                         "give the one address the tablet reaches (this machine's address on the lab network)")
    if address.is_multicast:
        raise StudyError(f"--forms-host {host!r} is a multicast address: give this machine's own address")
    return str(address), not address.is_loopback


def lan_warning(address: str, port: int) -> str:
    """What ``nwr study`` says, once, on stderr, when the forms are served off this machine."""
    where = "" if ipaddress.ip_address(address).is_private else (
        " This is not a private address: the forms may be reachable from the internet.")
    host = f"[{address}]" if ":" in address else address
    return ("\n" + "!" * 78 + f"\n!! The questionnaires are served on http://{host}:{port}/ to every machine that "
            f"reaches {address}.{where}\n!! The pages have no login: anyone on that network can read the current "
            "participant's\n!! forms. Use a closed lab network, and stop the server after the session.\n"
            + "!" * 78)


def allowed_hosts(address: str, port: int) -> frozenset[str]:
    """The Host headers a request may carry: the address the server is bound to with its port (and, for
    loopback, ``localhost``); lower case."""
    ip = ipaddress.ip_address(address)
    names = [f"[{ip}]" if ip.version == 6 else str(ip)]
    if ip.is_loopback:
        names.append("localhost")
    hosts = {f"{n}:{port}" for n in names}
    if port == 80:  # a browser leaves the default port out
        hosts |= set(names)
    return frozenset(h.lower() for h in hosts)


@dataclass(frozen=True)
class Refusal:
    """Why a request is refused: its HTTP status and the page's title and text."""

    status: int
    title: str
    text: str


def _origin_of(url: str) -> str:
    parts = urlsplit(url)
    return f"{parts.scheme}://{parts.netloc}".lower() if parts.scheme and parts.netloc else ""


def refusal(method: str, headers: Mapping[str, str], hosts: Iterable[str]) -> Refusal | None:
    """Whether to refuse a request before it reaches a page (None: let it through). ``headers``: lower-case
    names; ``hosts``: :func:`allowed_hosts`. Pure: the :class:`Guard` middleware and the tests call it."""
    hosts = frozenset(hosts)
    home = min(hosts, key=lambda h: (h.startswith("localhost"), len(h)))
    host = headers.get("host", "").lower()
    if host not in hosts:
        return Refusal(421, "Wrong address", f"These questionnaires are served as http://{home}/ only, and this "
                       f"request asked for {host or 'no host'!r}. Open the address that `nwr study` printed. "
                       "(A page on another site that points its name at this machine is refused this way.)")
    if method in ("GET", "HEAD"):
        return None
    if method != "POST":
        return Refusal(405, "Not allowed", f"{method} is not used by the questionnaires.")
    origins = {f"http://{h}" for h in hosts}
    origin = headers.get("origin")
    if origin is not None:
        if origin.lower() not in origins:
            return Refusal(403, "Not sent from this questionnaire", f"A form from {origin!r} was refused: only "
                           f"the pages of http://{home}/ may submit answers. Nothing was saved.")
    else:
        referer = _origin_of(headers.get("referer", ""))
        if not referer:
            return Refusal(403, "Not sent from this questionnaire", "A form without an Origin or a Referer was "
                           "refused: submit it from the questionnaire's page in a browser. Nothing was saved.")
        if referer not in origins:
            return Refusal(403, "Not sent from this questionnaire", f"A form sent from a page of {referer!r} was "
                           f"refused: only the pages of http://{home}/ may submit answers. Nothing was saved.")
    length = headers.get("content-length")
    if length is None or not length.isdigit():
        return Refusal(411, "Not saved", "The answers came without their length: submit the form from the "
                       "questionnaire's page in a browser. Nothing was saved.")
    if int(length) > MAX_BODY_BYTES:
        return Refusal(413, "Answers too long", f"The answers were {int(length) // 1024} kB, more than the "
                       f"{MAX_BODY_BYTES // 1024} kB a questionnaire takes (each open answer at most "
                       f"{MAX_ANSWER_CHARS} characters). Go back, shorten the longest answer and submit again. "
                       "Nothing was saved.")
    return None


class Guard:
    """ASGI middleware: :func:`refusal` before any page, a refusal page for what it refuses, and the
    :data:`SECURITY_HEADERS` on every response."""

    def __init__(self, app: ASGIApp, hosts: frozenset[str], render: Any) -> None:
        self.app, self.hosts, self.render = app, hosts, render

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_secured(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in SECURITY_HEADERS.items():
                    headers[name] = value
            await send(message)

        why = refusal(scope["method"], Headers(scope=scope), self.hosts)
        if why is None:
            await self.app(scope, receive, send_secured)
            return
        log.warning("refused %s %s (Host %r, Origin %r): %s", scope["method"], scope["path"],
                    Headers(scope=scope).get("host"), Headers(scope=scope).get("origin"), why.title)
        response = self.render(Request(scope), why)
        await response(scope, receive, send_secured)


def form_token(secret: bytes, path: str) -> str:
    """The token a form at ``path`` carries: an HMAC of its path under the server's secret (drawn at start
    with :mod:`secrets`), so a page elsewhere cannot know it and a form of one participant does not fit
    another's."""
    return hmac.new(secret, path.encode(), hashlib.sha256).hexdigest()


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
        elif len(text) > MAX_ANSWER_CHARS:
            errors[question.id] = (f"{len(text)} characters: at most {MAX_ANSWER_CHARS}, please shorten the "
                                   "answer")
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


def create_app(store_path: str | Path, hosts: Iterable[str]) -> Starlette:
    """The forms over the store at ``store_path`` (created if missing, with the packaged questionnaire), for
    requests whose Host is one of ``hosts`` (:func:`allowed_hosts` of the address served on)."""
    store_path = Path(store_path)
    secret = secrets.token_bytes(32)
    with Store(store_path) as store:
        q = store.questionnaire
    env = jinja2.Environment(loader=jinja2.FileSystemLoader(TEMPLATES), autoescape=True,
                             undefined=jinja2.StrictUndefined)
    templates = Jinja2Templates(env=env)

    def page(request: Request, name: str, status: int = 200, **context: Any) -> Response:
        token = form_token(secret, request.url.path)
        return templates.TemplateResponse(request, name, {"q": q, "no_pref": NO_PREFERENCE, "token": token,
                                                          "max_answer": MAX_ANSWER_CHARS, **context},
                                          status_code=status)

    def refused(request: Request, why: Refusal) -> Response:
        return message(request, why.title, why.text, why.status)

    async def posted(request: Request) -> tuple[dict[str, str], Response | None]:
        """A POST's fields, or the refusal of a form without this server's token for this page."""
        data = {k: v for k, v in (await request.form()).items() if isinstance(v, str)}
        if not hmac.compare_digest(data.get("token", ""), form_token(secret, request.url.path)):
            log.warning("refused a form for %s without its token", request.url.path)
            return data, message(request, "Form expired", "This form did not come from this questionnaire's "
                                 "server as it runs now (it was restarted, or the form came from elsewhere). "
                                 "Nothing was saved: reload the page and answer again.", 403)
        return data, None

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
            data, bad = await posted(request)
            if bad is not None:
                return bad
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
            data, bad = await posted(request)
            if bad is not None:
                return bad
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

    async def no_page(request: Request, exc: Exception) -> Response:
        status = getattr(exc, "status_code", 404)
        return message(request, "No such page", f"There is no page {request.url.path!r} here "
                       f"({request.method}): start from the questionnaires' start page.", status)

    return Starlette(routes=[
        Route("/", index, name="index"),
        Route("/p/{participant}/block/{block:int}", condition_form, methods=["GET", "POST"], name="block"),
        Route("/p/{participant}/final", final_form, methods=["GET", "POST"], name="final"),
        Route("/p/{participant}/thanks", thanks, name="thanks"),
    ], middleware=[Middleware(Guard, hosts=frozenset(h.lower() for h in hosts), render=refused)],
        exception_handlers={404: no_page, 405: no_page})


class FormServer:
    """The forms served by uvicorn in a background thread; :meth:`stop` (or ``with``) ends it. ``host``: an
    address (:func:`bind_address`; loopback by default); a LAN address is said once, loudly, on stderr."""

    def __init__(self, store_path: str | Path, host: str = "127.0.0.1", port: int = DEFAULT_PORT) -> None:
        host, lan = bind_address(host)
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
        try:
            app = create_app(store_path, allowed_hosts(host, self.port))
        except BaseException:
            self.sock.close()
            raise
        if lan:
            print(lan_warning(host, self.port), file=sys.stderr, flush=True)
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
