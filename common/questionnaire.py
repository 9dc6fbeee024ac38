"""The study's questionnaire as data: ``common/study/questionnaire.toml`` decoded into Structs.

Per condition: Godspeed subscales (semantic differentials, a left and a
right anchor per item) and custom Likert groups (a statement per item), every
item rated 1 to ``points`` (5). After all conditions: forced-choice questions
(one condition, or no preference) and open questions. Decoding is strict: an
unknown field, a missing or empty text, a scale other than 1-5 or an id used
twice is a :class:`ConfigError` naming the field.
"""

from __future__ import annotations

import tomllib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import msgspec

from nwr.common.errors import ConfigError

QUESTIONNAIRE_PATH = Path(__file__).resolve().parent / "study" / "questionnaire.toml"

Text = Annotated[str, msgspec.Meta(min_length=1)]
ItemId = Annotated[str, msgspec.Meta(pattern=r"^[a-z][a-z0-9_]{0,47}$")]


class _Strict(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    pass


class PairItem(_Strict):
    """A Godspeed semantic differential: 1 = ``left``, 5 = ``right``."""

    id: ItemId
    left: Text
    right: Text
    # True: 5 means less of the subscale; flipped (points + 1 - x) before the mean.
    reversed: bool = False


class StatementItem(_Strict):
    """A Likert statement: 1 = strongly disagree, 5 = strongly agree."""

    id: ItemId
    text: Text
    reversed: bool = False


class Godspeed(_Strict):
    id: ItemId
    name: Text
    items: Annotated[list[PairItem], msgspec.Meta(min_length=1)]


class LikertGroup(_Strict):
    id: ItemId
    name: Text
    items: Annotated[list[StatementItem], msgspec.Meta(min_length=1)]


class Choice(_Strict):
    """Which condition was the most ...? One condition, or no preference."""

    id: ItemId
    short: Text  # the radar plot's axis label
    text: Text


class OpenQuestion(_Strict):
    id: ItemId
    text: Text
    required: bool = False


class Questionnaire(_Strict):
    name: Text
    # Only 5-point scales: the paper's, and what the analysis and the store assume.
    points: Literal[5]
    likert_left: Text
    likert_right: Text
    no_preference: Text
    labels: dict[str, Text] = {}
    godspeed: list[Godspeed] = []
    likert: list[LikertGroup] = []
    choice: list[Choice] = []
    open: list[OpenQuestion] = []

    def scales(self) -> Iterator[Scale]:
        """Every rated subscale or group, Godspeed first, in the file's order."""
        for g in self.godspeed:
            yield Scale(g.id, g.name, "godspeed", tuple(i.id for i in g.items),
                        frozenset(i.id for i in g.items if i.reversed))
        for lg in self.likert:
            yield Scale(lg.id, lg.name, "custom", tuple(i.id for i in lg.items),
                        frozenset(i.id for i in lg.items if i.reversed))

    def rated_items(self) -> list[str]:
        """The ids a per-condition form answers, every one required."""
        return [item for scale in self.scales() for item in scale.items]

    def scale_of(self, item: str) -> Scale:
        return next(s for s in self.scales() if item in s.items)

    def label(self, condition: str) -> str:
        return self.labels.get(condition, condition)


@dataclass(frozen=True)
class Scale:
    id: str
    name: str
    kind: Literal["godspeed", "custom"]
    items: tuple[str, ...]
    reversed: frozenset[str]


def parse_questionnaire(text: str, where: str = "questionnaire") -> Questionnaire:
    """``text`` (TOML) as a Questionnaire; ConfigError naming the field otherwise."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{where} is not valid TOML: {exc}") from exc
    try:
        q = msgspec.convert(raw, Questionnaire)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{where}: {exc} (see common/study/questionnaire.toml)") from exc
    seen: dict[str, str] = {}
    for field, ids in (("godspeed", [g.id for g in q.godspeed] + [i.id for g in q.godspeed for i in g.items]),
                       ("likert", [g.id for g in q.likert] + [i.id for g in q.likert for i in g.items]),
                       ("choice", [c.id for c in q.choice]), ("open", [o.id for o in q.open])):
        for i in ids:
            if i in seen:
                raise ConfigError(f"{where}: id {i!r} in {field} is already used in {seen[i]}: give each "
                                  "subscale, item and question its own id")
            seen[i] = field
    if not q.godspeed and not q.likert:
        raise ConfigError(f"{where}: no [[godspeed]] or [[likert]] subscale: there is nothing to rate")
    return q


def load_questionnaire(path: str | Path | None = None) -> tuple[Questionnaire, str]:
    """The questionnaire at ``path`` (default: the packaged one) and its text (the store keeps a copy)."""
    path = Path(path) if path is not None else QUESTIONNAIRE_PATH
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"questionnaire file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read questionnaire file {path}: {exc}") from exc
    return parse_questionnaire(text, str(path)), text
