"""The study's answer store: one SQLite file beside the study's recordings.

``recordings/study.sqlite`` (the profile's recorder directory) holds every
participant's answers, each linked to its participant, condition, counterbalanced
order, block and the block's recording (relative to the store's folder,
``<participant>/<participant>-b<block>-<condition>.mcap`` as ``nwr study`` names
it), and a copy of the questionnaire the store was created with: answers are
always read against the texts they were given with.

Why SQLite (the standard library's ``sqlite3``): one file that travels with
the recordings, transactions, and safe concurrent writers (a browser form
later, a command-line submission now). Each submission is written in one
transaction (``BEGIN IMMEDIATE``: its checks and its rows together), in WAL
mode with ``synchronous = FULL``: a crash loses nothing already answered and
never leaves half a form.

A second submission of the same form (the same participant and condition,
or the same participant's final form) is refused, naming the first one's
time; ``replace=True`` (``nwr study submit --replace``) explicitly replaces it.
Out-of-scale values, missing or unknown items, a block or order that
disagrees with the participant's other forms, and a forced choice naming a
condition the participant did not rate are refused with a :class:`StudyError`
naming the item. A store of another schema version, or another SQLite file,
is refused on opening.

The store also holds each session's plan (``nwr study``: a participant's
order and conditions, block by block, and when each block was recorded), so
the browser forms (``nwr.services.tools.study.web``) know a block's condition
and order without anyone typing them.

Evolution: a change to the tables bumps :data:`SCHEMA_VERSION`; an older
store is then refused (with its version and this one's) rather than misread.
A table only added (which older code ignores) is created on opening and
keeps the version: the ``blocks`` table came that way.
"""

from __future__ import annotations

import csv
import datetime as dt
import os
import re
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import msgspec

from nwr.common.errors import ConfigError, StudyError
from nwr.common.questionnaire import Questionnaire, load_questionnaire, parse_questionnaire

SCHEMA_VERSION = 1
FORMAT = "nwr-study-answers"
STORE_NAME = "study.sqlite"
NO_PREFERENCE = "none"  # a forced choice's "no preference"
# An open answer's length, characters: a few paragraphs. Longer is refused at submission (the web form says so
# and keeps the text); the report shows no more of any answer.
MAX_ANSWER_CHARS = 2000

# A participant ID is a pseudonym: a code such as P07 (up to 8 letters, an optional - or _, 1 to 6 digits), never
# a name or initials and a birth date. The key from codes to people is kept apart from the data (docs/study.md).
PARTICIPANT_PATTERN = r"^[A-Za-z]{0,8}[-_]?[0-9]{1,6}$"
Participant = Annotated[str, msgspec.Meta(pattern=PARTICIPANT_PATTERN)]
Condition = Annotated[str, msgspec.Meta(pattern=r"^[a-z][a-z0-9_-]{0,31}$")]
Positive = Annotated[int, msgspec.Meta(ge=1)]


class ConditionForm(msgspec.Struct, tag="condition", tag_field="form", forbid_unknown_fields=True, kw_only=True):
    """The questionnaire after one block: every Godspeed and custom item rated."""

    participant: Participant
    condition: Condition
    order: Positive  # the counterbalanced order (``nwr study --order``)
    block: Positive  # the condition's position in it, from 1
    ratings: dict[str, int]
    # The block's recording relative to the store's folder; empty: as ``nwr study`` names it.
    recording: str = ""


class FinalForm(msgspec.Struct, tag="final", tag_field="form", forbid_unknown_fields=True, kw_only=True):
    """The questionnaire after all blocks: forced choices (a condition or "none") and open answers."""

    participant: Participant
    choices: dict[str, str]
    answers: dict[str, str] = {}


Form = ConditionForm | FinalForm
FORM_DECODER = msgspec.json.Decoder(Form)


def check_participant(participant: str) -> str:
    """``participant`` if it is a pseudonymous code (:data:`PARTICIPANT_PATTERN`); StudyError otherwise."""
    if not re.fullmatch(PARTICIPANT_PATTERN, participant):
        raise StudyError(f"participant {participant!r}: a participant ID is a code such as P07 (up to 8 letters, "
                         "an optional '-' or '_', then 1 to 6 digits), never a name: keep the list linking codes "
                         "to people apart from the study's data")
    return participant


def recording_name(participant: str, block: int, condition: str) -> Path:
    """A block's recording relative to the recordings folder (``nwr study``'s naming)."""
    return Path(participant) / f"{participant}-b{block}-{condition}.mcap"


def decode_form(data: bytes, where: str) -> Form:
    """A submission as JSON (what a web form posts); StudyError naming the field otherwise."""
    try:
        return FORM_DECODER.decode(data)
    except msgspec.ValidationError as exc:
        raise StudyError(f"{where}: {exc} (a submission is a JSON object with \"form\": \"condition\" or "
                         "\"final\"; docs/study.md)") from exc
    except msgspec.DecodeError as exc:
        raise StudyError(f"{where} is not JSON: {exc}") from exc


@dataclass(frozen=True)
class Rating:
    participant: str
    condition: str
    order: int
    block: int
    recording: str
    item: str
    value: int
    submitted_at: str


@dataclass(frozen=True)
class Block:
    """A planned block of a session and how far it got."""

    participant: str
    order: int
    block: int
    condition: str
    recording: str
    recorded_at: str | None  # None: not recorded yet
    answered_at: str | None  # its per-condition form's submission; None: not answered yet


@dataclass(frozen=True)
class FinalAnswer:
    participant: str
    item: str
    kind: str  # "choice" or "open"
    text: str
    submitted_at: str


_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE submissions (
    id INTEGER PRIMARY KEY,
    participant TEXT NOT NULL,
    form TEXT NOT NULL CHECK (form IN ('condition', 'final')),
    condition TEXT NOT NULL,          -- '' for the final form
    order_n INTEGER,
    block INTEGER,
    recording TEXT,
    submitted_at TEXT NOT NULL,
    UNIQUE (participant, form, condition)
);
CREATE TABLE answers (
    submission INTEGER NOT NULL REFERENCES submissions (id) ON DELETE CASCADE,
    item TEXT NOT NULL,
    value INTEGER,                    -- a rating, 1..points
    text TEXT,                        -- a forced choice or an open answer
    PRIMARY KEY (submission, item)
);
"""
# Added after version 1, created on opening: a session's plan (nwr study), block by block.
_BLOCKS = """
CREATE TABLE IF NOT EXISTS blocks (
    participant TEXT NOT NULL,
    block INTEGER NOT NULL,
    order_n INTEGER NOT NULL,
    condition TEXT NOT NULL,
    recording TEXT NOT NULL,
    planned_at TEXT NOT NULL,
    recorded_at TEXT,                 -- NULL: not recorded yet
    PRIMARY KEY (participant, block)
);
"""


class Store:
    """One study's answers. ``Store(path)`` creates the file (with ``questionnaire``, default the packaged
    one) or opens it (with the copy it keeps); use as a context manager or call :meth:`close`."""

    def __init__(self, path: str | Path, questionnaire: str | Path | None = None, *, create: bool = True) -> None:
        self.path = Path(path)
        exists = self.path.exists()
        if not exists and not create:
            raise StudyError(f"no study store at {self.path}: answers are written there by `nwr study submit` "
                             "(or give --store PATH)")
        if not exists:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # Readable by its owner only (SQLite gives its -wal and -shm files the same permissions).
            os.close(os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        try:
            self.db = sqlite3.connect(self.path, isolation_level=None, timeout=10.0)
            self.db.execute("PRAGMA foreign_keys = ON")
            tables = {r[0] for r in self.db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        except sqlite3.DatabaseError as exc:
            raise StudyError(f"{self.path} is no study store (not an SQLite file: {exc}): give the study's "
                             f"{STORE_NAME}") from exc
        if not tables:
            q, text = load_questionnaire(questionnaire)
            self._create(q, text)
        else:
            self._check(tables)
            if questionnaire is not None:
                raise StudyError(f"{self.path} already keeps the questionnaire it was created with: "
                                 "drop --questionnaire, or start a new store for new texts")
        self.db.execute("PRAGMA journal_mode = WAL")
        self.db.execute("PRAGMA synchronous = FULL")
        self.db.execute(_BLOCKS)
        text = self._meta("questionnaire")
        try:
            self.questionnaire: Questionnaire = parse_questionnaire(text, f"{self.path}'s questionnaire")
        except ConfigError as exc:
            raise StudyError(str(exc)) from exc
        self.questionnaire_text = text

    def _create(self, q: Questionnaire, text: str) -> None:
        # In the script: executescript would first commit a transaction begun outside it.
        self.db.executescript("BEGIN IMMEDIATE;" + _SCHEMA.replace("CREATE TABLE", "CREATE TABLE IF NOT EXISTS"))
        self.db.executemany("INSERT OR IGNORE INTO meta VALUES (?, ?)", [
            ("format", FORMAT), ("schema_version", str(SCHEMA_VERSION)), ("questionnaire", text),
            ("questionnaire_name", q.name), ("created_at", _now())])
        self.db.execute("COMMIT")

    def _check(self, tables: set[str]) -> None:
        if "meta" not in tables:
            raise StudyError(f"{self.path} is an SQLite file but no study store (no meta table)")
        fmt = self._meta("format", "")
        if fmt != FORMAT:
            raise StudyError(f"{self.path} is no study store (format {fmt!r}, expected {FORMAT!r})")
        version = self._meta("schema_version", "?")
        if version != str(SCHEMA_VERSION):
            raise StudyError(f"{self.path} has schema version {version}; this nwr reads version {SCHEMA_VERSION}: "
                             "use the nwr release that wrote it (export its answers with `nwr study export`)")

    def _meta(self, key: str, default: str | None = None) -> str:
        row = self.db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        if row is None:
            if default is not None:
                return default
            raise StudyError(f"{self.path} has no {key!r} in its meta table: the store is damaged")
        return str(row[0])

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- writing -------------------------------------------------------------------

    def submit(self, form: Form, *, replace: bool = False) -> int:
        """Check ``form`` and write it in one transaction; its submission id. StudyError naming the item for
        a bad answer; for a form already submitted unless ``replace``."""
        check_participant(form.participant)  # a Struct built in Python is not validated as decoding does
        self.db.execute("BEGIN IMMEDIATE")  # the checks below read what this transaction then writes
        try:
            match form:
                case ConditionForm():
                    rows = self._check_condition(form)
                    key = (form.participant, "condition", form.condition)
                    what = f"the form for condition {form.condition!r}"
                    recording = form.recording or recording_name(form.participant, form.block,
                                                                 form.condition).as_posix()
                    extra: tuple[int | None, int | None, str | None] = (form.order, form.block, recording)
                case FinalForm():
                    rows = self._check_final(form)
                    key = (form.participant, "final", "")
                    what = "the final form (forced choices and open questions)"
                    extra = (None, None, None)
            old = self.db.execute("SELECT id, submitted_at FROM submissions WHERE participant = ? AND form = ? "
                                  "AND condition = ?", key).fetchone()
            if old is not None:
                if not replace:
                    raise StudyError(f"participant {form.participant} already submitted {what} at {old[1]}: a "
                                     "second submission is refused (to correct it, submit again with --replace)")
                self.db.execute("DELETE FROM submissions WHERE id = ?", (old[0],))
            cur = self.db.execute("INSERT INTO submissions (participant, form, condition, order_n, block, recording, "
                                  "submitted_at) VALUES (?, ?, ?, ?, ?, ?, ?)", (*key, *extra, _now()))
            sid = int(cur.lastrowid or 0)
            self.db.executemany("INSERT INTO answers VALUES (?, ?, ?, ?)", [(sid, *r) for r in rows])
            self.db.execute("COMMIT")
            return sid
        except BaseException:
            self.db.execute("ROLLBACK")
            raise

    def _check_condition(self, form: ConditionForm) -> list[tuple[str, int | None, str | None]]:
        q = self.questionnaire
        who = f"participant {form.participant}, condition {form.condition!r}"
        wanted = q.rated_items()
        unknown = sorted(set(form.ratings) - set(wanted))
        if unknown:
            raise StudyError(f"{who}: {', '.join(unknown)} is no item of questionnaire {q.name!r}")
        missing = [i for i in wanted if i not in form.ratings]
        if missing:
            raise StudyError(f"{who}: no answer to {', '.join(missing)}: every item of the per-condition form "
                             "is required")
        for item in wanted:
            value = form.ratings[item]
            if not 1 <= value <= q.points:
                raise StudyError(f"{who}: {item} = {value} is out of the scale 1 to {q.points}")
        for cond, order_n, block in self.db.execute(
                "SELECT condition, order_n, block FROM submissions WHERE participant = ? AND form = 'condition' "
                "AND condition != ?", (form.participant, form.condition)):
            if order_n != form.order:
                raise StudyError(f"{who}: order {form.order}, but the participant's form for {cond!r} says order "
                                 f"{order_n}: a participant has one counterbalanced order")
            if block == form.block:
                raise StudyError(f"{who}: block {form.block} was already answered for condition {cond!r}")
        return [(item, form.ratings[item], None) for item in wanted]

    def _check_final(self, form: FinalForm) -> list[tuple[str, int | None, str | None]]:
        q = self.questionnaire
        who = f"participant {form.participant}'s final form"
        rated = [r[0] for r in self.db.execute("SELECT condition FROM submissions WHERE participant = ? AND "
                                               "form = 'condition' ORDER BY block", (form.participant,))]
        known = {c.id for c in q.choice} | {o.id for o in q.open}
        unknown = sorted((set(form.choices) | set(form.answers)) - known)
        if unknown:
            raise StudyError(f"{who}: {', '.join(unknown)} is no question of questionnaire {q.name!r}")
        rows: list[tuple[str, int | None, str | None]] = []
        for choice in q.choice:
            if choice.id not in form.choices:
                raise StudyError(f"{who}: no answer to {choice.id} ({choice.text!r}): choose a condition or "
                                 f"{NO_PREFERENCE!r}")
            value = form.choices[choice.id]
            if value != NO_PREFERENCE and value not in rated:
                raise StudyError(f"{who}: {choice.id} = {value!r} is no condition the participant rated "
                                 f"({', '.join(rated) or 'none yet: submit the per-condition forms first'}); "
                                 f"or {NO_PREFERENCE!r} for no preference")
            rows.append((choice.id, None, value))
        for question in q.open:
            text = form.answers.get(question.id, "").strip()
            if question.required and not text:
                raise StudyError(f"{who}: no answer to {question.id} ({question.text!r}), which is required")
            if len(text) > MAX_ANSWER_CHARS:
                raise StudyError(f"{who}: the answer to {question.id} has {len(text)} characters, more than the "
                                 f"{MAX_ANSWER_CHARS} an open answer may have: shorten it")
            rows.append((question.id, None, text))
        return rows

    def plan(self, participant: str, order: int, conditions: Sequence[str], *, replace: bool = False) -> None:
        """Register a session: ``participant`` runs ``conditions`` (in this order), counterbalanced order
        ``order``. The same plan again is kept; another one is refused unless ``replace`` (``--overwrite``)."""
        check_participant(participant)
        planned = [(b.order, b.condition) for b in self.blocks(participant)]
        wanted = [(order, c) for c in conditions]
        if planned == wanted:
            return
        if planned and not replace:
            raise StudyError(f"participant {participant} is already planned with order {planned[0][0]} "
                             f"({' -> '.join(c for _, c in planned)}) in {self.path}: choose another participant "
                             "ID, or --overwrite")
        now = _now()
        self.db.execute("BEGIN IMMEDIATE")
        try:
            self.db.execute("DELETE FROM blocks WHERE participant = ?", (participant,))
            self.db.executemany("INSERT INTO blocks VALUES (?, ?, ?, ?, ?, ?, NULL)", [
                (participant, block, order, c, recording_name(participant, block, c).as_posix(), now)
                for block, c in enumerate(conditions, start=1)])
            self.db.execute("COMMIT")
        except BaseException:
            self.db.execute("ROLLBACK")
            raise

    def recorded(self, participant: str, block: int) -> None:
        """Mark a planned block recorded: its per-condition form is now due."""
        cur = self.db.execute("UPDATE blocks SET recorded_at = ? WHERE participant = ? AND block = ?",
                              (_now(), participant, block))
        if cur.rowcount != 1:
            raise StudyError(f"participant {participant} has no block {block} planned in {self.path}")

    # -- reading -------------------------------------------------------------------

    def blocks(self, participant: str | None = None) -> list[Block]:
        """The planned blocks (of ``participant``, or everyone's in the order they were planned)."""
        where, params = ("WHERE b.participant = ?", (participant,)) if participant is not None else ("", ())
        return [Block(*r) for r in self.db.execute(
            "SELECT b.participant, b.order_n, b.block, b.condition, b.recording, b.recorded_at, s.submitted_at "
            "FROM blocks b LEFT JOIN submissions s ON s.participant = b.participant AND s.form = 'condition' "
            f"AND s.condition = b.condition {where} ORDER BY b.planned_at, b.participant, b.block", params)]

    def current_participant(self) -> str | None:
        """The participant planned last (the running session's), None before any."""
        row = self.db.execute("SELECT participant FROM blocks ORDER BY planned_at DESC, rowid DESC "
                              "LIMIT 1").fetchone()
        return None if row is None else str(row[0])

    def submitted_at(self, participant: str, condition: str | None = None) -> str | None:
        """When ``participant`` submitted the form for ``condition`` (None: the final form); None if not yet."""
        form, cond = ("final", "") if condition is None else ("condition", condition)
        row = self.db.execute("SELECT submitted_at FROM submissions WHERE participant = ? AND form = ? AND "
                              "condition = ?", (participant, form, cond)).fetchone()
        return None if row is None else str(row[0])

    def ratings(self) -> list[Rating]:
        return [Rating(*r) for r in self.db.execute(
            "SELECT s.participant, s.condition, s.order_n, s.block, s.recording, a.item, a.value, s.submitted_at "
            "FROM submissions s JOIN answers a ON a.submission = s.id WHERE s.form = 'condition' "
            "ORDER BY s.participant, s.block, a.rowid")]

    def final_answers(self) -> list[FinalAnswer]:
        choices = {c.id for c in self.questionnaire.choice}
        return [FinalAnswer(p, item, "choice" if item in choices else "open", text or "", at) for p, item, text, at in
                self.db.execute("SELECT s.participant, a.item, a.text, s.submitted_at FROM submissions s JOIN "
                                "answers a ON a.submission = s.id WHERE s.form = 'final' "
                                "ORDER BY s.participant, a.rowid")]

    def export_csv(self, out: str | Path, *, free_text: bool = False) -> int:
        """Every answer in tidy long format, one row per participant x condition x item (the final form's
        answers with an empty condition); the number of rows. The open answers (free text, which may say who
        someone is) only with ``free_text``. Every cell that a spreadsheet would read as a formula is
        neutralised (:func:`csv_cell`)."""
        q = self.questionnaire
        header = ["participant", "order", "block", "condition", "recording", "form", "scale", "item", "reversed",
                  "value", "answer", "submitted_at"]
        n = 0
        with open(out, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(header)
            for r in self.ratings():
                scale = q.scale_of(r.item)
                w.writerow(csv_row([r.participant, r.order, r.block, r.condition, r.recording, "condition", scale.id,
                                    r.item, int(r.item in scale.reversed), r.value, "", r.submitted_at]))
                n += 1
            for a in self.final_answers():
                if a.kind == "open" and not free_text:
                    continue
                w.writerow(csv_row([a.participant, "", "", "", "", "final", a.kind, a.item, "", "", a.text,
                                    a.submitted_at]))
                n += 1
        return n


_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")
_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def csv_cell(value: object) -> object:
    """A value as a CSV cell that no spreadsheet runs as a formula (OWASP's CSV injection advice): text
    starting with = + - @ a tab or a carriage return gets a leading ``'``, unless it is a plain number (-3.5
    stays a number). Numbers and everything else pass unchanged."""
    if isinstance(value, str) and value.startswith(_FORMULA_START) and not _NUMBER.fullmatch(value):
        return "'" + value
    return value


def csv_row(values: Sequence[object]) -> list[object]:
    return [csv_cell(v) for v in values]


def _now() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
