"""The questionnaire's web forms over the answer store, through Starlette's TestClient."""

from __future__ import annotations

import re
import warnings

import pytest
from starlette.exceptions import StarletteDeprecationWarning

with warnings.catch_warnings():
    # starlette 1.10 prefers httpx2 for its TestClient; httpx 0.28 (the test extra) still works.
    warnings.filterwarnings("ignore", "Using `httpx` with `starlette.testclient` is deprecated",
                            StarletteDeprecationWarning)
    from starlette.testclient import TestClient

from nwr.common.errors import StudyError
from nwr.services.tools.study.store import Store
from nwr.services.tools.study.web import create_app, serve

ORDER = ("location", "cartesian", "uniform")  # the paper's order 2


@pytest.fixture
def store_path(tmp_path):
    path = tmp_path / "study.sqlite"
    with Store(path) as store:
        store.plan("P07", 2, ORDER)
        store.recorded("P07", 1)
    return path


@pytest.fixture
def client(store_path):
    with TestClient(create_app(store_path)) as c:
        yield c


def answers(store_path, value: int = 4) -> dict[str, str]:
    with Store(store_path) as store:
        return {item: str(value) for item in store.questionnaire.rated_items()}


def test_the_form_shows_every_item_of_the_questionnaire_as_required(client, store_path):
    page = client.get("/p/P07/block/1")
    assert page.status_code == 200
    with Store(store_path) as store:
        q = store.questionnaire
    for g in q.godspeed:
        assert g.name in page.text
        for item in g.items:
            assert item.left in page.text and item.right in page.text
    for lg in q.likert:
        for statement in lg.items:
            assert statement.text in page.text
    for item in q.rated_items():
        radios = re.findall(rf'<input type="radio" name="{item}" value="(\d)" required', page.text)
        assert radios == ["1", "2", "3", "4", "5"], item
    assert "block 1 of 3 (LR)" in page.text  # the condition comes from the plan, as its label
    assert "<script" not in page.text and "http" not in page.text.split("<body>")[1]  # no JS, no external assets


def test_the_index_shows_the_current_participant_and_the_form_due(client, store_path):
    with Store(store_path) as store:
        store.plan("P08", 3, ("cartesian", "uniform", "location"))
    page = client.get("/")
    assert "Participant P08 (current)" in page.text
    assert "/p/P07/block/1" in page.text  # P07's first block is recorded: its form is due
    assert "Block 1 is not recorded yet" in page.text  # P08's is not


@pytest.mark.parametrize(("change", "why"), [
    ({"animacy_3": None}, "no answer"),
    ({"safety_3": "7"}, "7 is out of the scale 1 to 5"),
    ({"natural_1": "0"}, "0 is out of the scale 1 to 5"),
    ({"comfort_2": "a lot"}, "is not a number"),
])
def test_a_missing_or_out_of_scale_answer_is_rejected_and_nothing_stored(client, store_path, change, why):
    data = answers(store_path)
    for item, value in change.items():
        if value is None:
            del data[item]
        else:
            data[item] = value
    page = client.post("/p/P07/block/1", data=data)
    assert page.status_code == 400
    assert "Nothing was saved: 1 item not answered or not on the scale" in page.text
    assert why in page.text.replace("&#39;", "'")
    item = next(iter(change))
    assert f'class="item missing" id="item-{item}"' in page.text
    assert 'name="animacy_1" value="4" required\n                checked' in page.text  # the given answers kept
    with Store(store_path) as store:
        assert store.ratings() == [] and store.submitted_at("P07", "location") is None


def test_a_valid_form_is_stored_linked_to_its_block_and_a_second_one_refused(client, store_path):
    page = client.post("/p/P07/block/1", data=answers(store_path, 2), follow_redirects=False)
    assert page.status_code == 303 and page.headers["location"].endswith("/p/P07/thanks")
    assert "Please wait for the next block (block 2)" in client.get("/p/P07/thanks").text
    with Store(store_path) as store:
        rows = store.ratings()
        assert {(r.participant, r.condition, r.order, r.block, r.recording) for r in rows} == \
            {("P07", "location", 2, 1, "P07/P07-b1-location.mcap")}
        assert len(rows) == len(store.questionnaire.rated_items()) and {r.value for r in rows} == {2}
        at = store.submitted_at("P07", "location")
    again = client.post("/p/P07/block/1", data=answers(store_path, 5))
    assert again.status_code == 409 and "Already answered" in again.text and at in again.text
    with Store(store_path) as store:
        assert {r.value for r in store.ratings()} == {2}
    assert client.get("/p/P07/block/1").status_code == 409  # the form itself is no longer offered


def test_a_block_not_recorded_or_not_planned_has_no_form(client):
    assert "has not been run yet" in client.get("/p/P07/block/2").text
    assert client.get("/p/P07/block/9").status_code == 404
    assert client.get("/p/P99/final").status_code == 404


def test_the_final_form_comes_after_every_block_and_checks_its_choices(client, store_path):
    assert "every block" in client.get("/p/P07/final").text
    for block in (1, 2, 3):
        with Store(store_path) as store:
            store.recorded("P07", block)
        assert client.post(f"/p/P07/block/{block}", data=answers(store_path)).status_code == 200  # after redirect
    page = client.get("/p/P07/final")
    assert page.status_code == 200
    with Store(store_path) as store:
        q = store.questionnaire
    for c in q.choice:
        assert re.findall(rf'name="{c.id}" value="([a-z]+)" required', page.text) == [*ORDER, "none"]
        assert c.text in page.text
    choices = {c.id: "cartesian" for c in q.choice}
    bad = client.post("/p/P07/final", data={**choices, "safest": "whole-arm"})
    assert bad.status_code == 400 and "&#39;whole-arm&#39; is none of the choices" in bad.text
    missing = client.post("/p/P07/final", data={k: v for k, v in choices.items() if k != "most_natural"})
    assert missing.status_code == 400 and "1 question not" in missing.text
    with Store(store_path) as store:
        assert store.final_answers() == []
    ok = client.post("/p/P07/final", data={**choices, "most_natural": "none", "liked_most": " smooth "})
    assert "All questionnaires are answered" in ok.text
    with Store(store_path) as store:
        final = {a.item: a.text for a in store.final_answers()}
    assert final["most_natural"] == "none" and final["safest"] == "cartesian" and final["liked_most"] == "smooth"
    assert "Already answered" in client.post("/p/P07/final", data=choices).text


def test_the_server_runs_in_a_thread_and_stops(store_path):
    import httpx

    with serve(store_path, port=0) as server:
        assert httpx.get(server.url + "p/P07/block/1").status_code == 200
        with pytest.raises(StudyError, match="cannot serve the questionnaire"):
            serve(store_path, port=server.port)
    assert not server.thread.is_alive()
    with pytest.raises(httpx.ConnectError):
        httpx.get(server.url)
