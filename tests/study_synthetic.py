"""Synthetic study answers: a seeded model of participants rating conditions, for the study's tests."""

from __future__ import annotations

import numpy as np

from nwr.common.questionnaire import Questionnaire
from nwr.services.tools.study.main import orders
from nwr.services.tools.study.store import ConditionForm, FinalForm, Rating, recording_name

CONDITIONS = ("uniform", "location", "cartesian")


def condition_forms(q: Questionnaire, rng: np.random.Generator, n: int, effect: dict[str, float],
                    conditions: tuple[str, ...] = CONDITIONS) -> list[ConditionForm]:
    """``n`` participants in the Latin square's orders: each item 3 + participant bias + the condition's
    ``effect`` + noise, rounded into 1..5 (reversed items stored reversed)."""
    square = orders(conditions)
    forms = []
    for i in range(n):
        order = i % len(square) + 1
        bias = rng.normal(0, 0.6)
        for block, condition in enumerate(square[order - 1], start=1):
            ratings = {}
            for scale in q.scales():
                for item in scale.items:
                    v = int(np.clip(np.rint(3 + bias + effect.get(condition, 0.0) + rng.normal(0, 0.8)), 1, 5))
                    ratings[item] = 6 - v if item in scale.reversed else v
            forms.append(ConditionForm(participant=f"P{i + 1:02d}", condition=condition, order=order, block=block,
                                       ratings=ratings))
    return forms


def final_forms(q: Questionnaire, rng: np.random.Generator, n: int, weights: dict[str, float]) -> list[FinalForm]:
    options = list(weights)
    p = np.array([weights[o] for o in options])
    return [FinalForm(participant=f"P{i + 1:02d}",
                      choices={c.id: str(rng.choice(options, p=p / p.sum())) for c in q.choice},
                      answers={q.open[0].id: f"participant {i + 1} liked the return"} if q.open else {})
            for i in range(n)]


def ratings_of(forms: list[ConditionForm]) -> list[Rating]:
    """The rows a store gives back for ``forms`` (for the analysis alone, without a store)."""
    return [Rating(f.participant, f.condition, f.order, f.block,
                   recording_name(f.participant, f.block, f.condition).as_posix(), item, value, "")
            for f in forms for item, value in f.ratings.items()]
