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
from nwr.services.tools.study import web
from nwr.services.tools.study.store import MAX_ANSWER_CHARS, Store
from nwr.services.tools.study.web import allowed_hosts, bind_address, create_app, lan_warning, serve

ORDER = ("location", "cartesian", "uniform")  # the paper's order 2
HOST = "testserver"  # the TestClient's Host


@pytest.fixture
def store_path(tmp_path):
    path = tmp_path / "study.sqlite"
    with Store(path) as store:
        store.plan("P07", 2, ORDER)
        store.recorded("P07", 1)
    return path


class Client(TestClient):
    """The TestClient as the participant's browser: a POST carries the Origin of the page and the token of the
    form it was on (read from the form, as a browser sends it back)."""

    def post(self, url, *, data=None, headers=None, token=True, **kwargs):  # type: ignore[override]
        data = dict(data or {})
        if token:
            form = self.get(url).text
            found = re.search(r'name="token" value="([0-9a-f]+)"', form)
            data.setdefault("token", found.group(1) if found else "")
        return super().post(url, data=data, headers={"origin": f"http://{HOST}", **(headers or {})}, **kwargs)


@pytest.fixture
def client(store_path):
    with Client(create_app(store_path, [HOST])) as c:
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


# -- who may submit: the participant's own page only -----------------------------------------


def token_of(client, url: str) -> str:
    found = re.search(r'name="token" value="([0-9a-f]{64})"', client.get(url).text)
    assert found, url
    return found.group(1)


def nothing_stored(store_path) -> bool:
    with Store(store_path) as store:
        return store.ratings() == [] and store.submitted_at("P07", "location") is None


@pytest.mark.parametrize(("headers", "status", "why"), [
    ({"origin": "http://evil.example"}, 403, "A form from &#39;http://evil.example&#39; was refused"),
    ({"origin": "null"}, 403, "A form from &#39;null&#39; was refused"),  # a sandboxed frame or a data: page
    ({"origin": "http://testserver.evil.example"}, 403, "was refused"),
    ({"origin": "https://testserver"}, 403, "was refused"),  # not this server's scheme
    ({"origin": "", "referer": "http://evil.example/attack.html"}, 403,
     "sent from a page of &#39;http://evil.example&#39; was refused"),
    ({"origin": "", "referer": ""}, 403, "without an Origin or a Referer"),
])
def test_a_cross_site_post_is_refused_stores_nothing_and_does_not_lock_the_participant_out(
        client, store_path, headers, status, why):
    data = {**answers(store_path), "token": token_of(client, "/p/P07/block/1")}  # even with the form's own token
    send = {k: v for k, v in headers.items() if v}
    page = TestClient.post(client, "/p/P07/block/1", data=data, headers=send)
    if "origin" not in send:  # the TestClient adds no Origin of its own
        assert "origin" not in page.request.headers
    assert page.status_code == status and why in page.text, page.text
    assert "Nothing was saved" in page.text and 'id="title">Not sent from this questionnaire' in page.text
    assert nothing_stored(store_path)
    # The participant's own page still submits.
    assert client.get("/p/P07/block/1").status_code == 200
    own = client.post("/p/P07/block/1", data=answers(store_path, 2), follow_redirects=False)
    assert own.status_code == 303
    with Store(store_path) as store:
        assert {r.value for r in store.ratings()} == {2}


def test_a_post_from_the_servers_own_page_without_an_origin_is_accepted_by_its_referer(client, store_path):
    data = {**answers(store_path), "token": token_of(client, "/p/P07/block/1")}
    page = TestClient.post(client, "/p/P07/block/1", data=data, follow_redirects=False,
                           headers={"referer": "http://testserver/p/P07/block/1"})
    assert page.status_code == 303


@pytest.mark.parametrize("token", ["", "0" * 64, "other"])
def test_a_form_without_its_token_is_refused_and_stores_nothing(client, store_path, token):
    if token == "other":  # another participant's form's token: no fit
        token = token_of_other(client, store_path)
    page = client.post("/p/P07/block/1", data={**answers(store_path), "token": token}, token=False)
    assert page.status_code == 403 and 'id="title">Form expired' in page.text
    assert "Nothing was saved: reload the page" in page.text
    assert nothing_stored(store_path)
    assert client.post("/p/P07/block/1", data=answers(store_path), follow_redirects=False).status_code == 303


def token_of_other(client, store_path) -> str:
    """The token of another participant's form on the same server."""
    with Store(store_path) as store:
        store.plan("P08", 1, ("uniform", "location", "cartesian"))
        store.recorded("P08", 1)
    return token_of(client, "/p/P08/block/1")


def test_a_token_from_another_run_of_the_server_is_refused(store_path):
    with Client(create_app(store_path, [HOST])) as first, Client(create_app(store_path, [HOST])) as second:
        data = {**answers(store_path), "token": token_of(first, "/p/P07/block/1")}
        assert second.post("/p/P07/block/1", data=data, token=False).status_code == 403
        assert first.post("/p/P07/block/1", data=data, token=False, follow_redirects=False).status_code == 303


@pytest.mark.parametrize("host", ["evil.example", "evil.example:8770", "127.0.0.1:8770", "testserver:81"])
def test_a_request_for_a_foreign_host_is_refused_before_any_page(client, host):
    """DNS rebinding: a page of evil.example whose name now points at this machine reads nothing."""
    for method in ("GET", "POST"):
        page = client.request(method, "/", headers={"host": host}) if method == "GET" else \
            TestClient.post(client, "/p/P07/block/1", headers={"host": host, "origin": f"http://{host}"},
                            data={"token": "x"})
        assert page.status_code == 421, (method, page.status_code)
        assert 'id="title">Wrong address' in page.text and "http://testserver/ only" in page.text
        assert "P07" not in page.text  # nothing of the participant


def test_a_huge_post_is_refused_before_it_is_read_and_an_over_long_answer_shows_the_form_again(client, store_path):
    for block in (1, 2, 3):
        with Store(store_path) as store:
            store.recorded("P07", block)
        client.post(f"/p/P07/block/{block}", data=answers(store_path))
    with Store(store_path) as store:
        choices = {c.id: "cartesian" for c in store.questionnaire.choice}
    page = client.post("/p/P07/final", data={**choices, "liked_most": "x" * 1_000_000})
    assert page.status_code == 413 and "Answers too long" in page.text and "Nothing was saved" in page.text
    long = "y" * (MAX_ANSWER_CHARS + 1)
    page = client.post("/p/P07/final", data={**choices, "liked_most": long})
    assert page.status_code == 400
    assert f"{MAX_ANSWER_CHARS + 1} characters: at most {MAX_ANSWER_CHARS}, please shorten" in page.text
    assert long in page.text  # the text kept in the form, to shorten
    assert f'maxlength="{MAX_ANSWER_CHARS}"' in page.text
    with Store(store_path) as store:
        assert store.final_answers() == []
    ok = client.post("/p/P07/final", data={**choices, "liked_most": "y" * MAX_ANSWER_CHARS})
    assert "All questionnaires are answered" in ok.text


def test_an_unknown_page_or_method_is_a_page_too(client):
    for method, url, status in (("GET", "/admin", 404), ("POST", "/p/P07/thanks", 405), ("PUT", "/", 405)):
        page = client.request(method, url, headers={"origin": f"http://{HOST}"}, content=b"")
        assert page.status_code == status and 'id="title">' in page.text, (method, url, page.text)
        assert page.headers["content-type"].startswith("text/html")


def test_every_page_forbids_scripts_frames_loads_from_elsewhere_and_caching(client):
    for url in ("/", "/p/P07/block/1", "/p/P07/block/9", "/p/P07/thanks"):
        headers = client.get(url).headers
        csp = headers["content-security-policy"]
        assert "default-src 'none'" in csp and "form-action 'self'" in csp and "frame-ancestors 'none'" in csp
        assert headers["x-frame-options"] == "DENY" and headers["cache-control"] == "no-store"
    refused = client.get("/", headers={"host": "evil.example"}).headers
    assert refused["x-frame-options"] == "DENY"


@pytest.mark.parametrize(("host", "why"), [
    ("0.0.0.0", "every network of this machine"),
    ("::", "every network of this machine"),
    ("labpc.example", "not a name"),
    ("224.0.0.1", "multicast"),
])
def test_a_wildcard_a_name_or_a_multicast_address_is_refused(host, why):
    with pytest.raises(StudyError, match=why):
        bind_address(host)


def test_loopback_is_quiet_and_a_lan_address_is_said_once_loudly(store_path, capfd, monkeypatch):
    assert bind_address("localhost") == ("127.0.0.1", False)
    assert bind_address("::1") == ("::1", False)
    assert bind_address("192.168.1.20") == ("192.168.1.20", True)
    assert allowed_hosts("127.0.0.1", 8770) == {"127.0.0.1:8770", "localhost:8770"}
    assert allowed_hosts("192.168.1.20", 8770) == {"192.168.1.20:8770"}
    assert allowed_hosts("::1", 80) == {"[::1]:80", "localhost:80", "[::1]", "localhost"}
    with serve(store_path, port=0):
        pass
    assert capfd.readouterr().err == ""
    assert "not a private address" in lan_warning("8.8.8.8", 8770)
    assert "not a private" not in lan_warning("192.168.1.20", 8770)
    # A LAN address (here 127.0.0.1 taken for one: the tests address no other host) is said once, on stderr.
    monkeypatch.setattr(web, "bind_address", lambda host: ("127.0.0.1", True))
    with serve(store_path, "192.168.1.20", port=0) as server:
        pass
    err = capfd.readouterr().err
    assert err.count("!! The questionnaires are served on") == 1
    assert f"http://127.0.0.1:{server.port}/ to every machine" in err and "no login" in err


def test_the_real_server_refuses_a_foreign_host_and_a_cross_site_post(store_path):
    import httpx

    with serve(store_path, port=0) as server:
        home = f"127.0.0.1:{server.port}"
        assert httpx.get(server.url, headers={"host": "evil.example"}).status_code == 421
        page = httpx.get(server.url + "p/P07/block/1")
        token = re.search(r'name="token" value="([0-9a-f]{64})"', page.text).group(1)
        data = {**answers(store_path), "token": token}
        evil = httpx.post(server.url + "p/P07/block/1", data=data, headers={"origin": "http://evil.example"})
        assert evil.status_code == 403
        own = httpx.post(server.url + "p/P07/block/1", data=data, headers={"origin": f"http://{home}"})
        assert own.status_code == 303
    with Store(store_path) as store:
        assert store.submitted_at("P07", "location") is not None


def test_forms_on_a_wildcard_address_is_a_one_line_error(store_path, caplog):
    from nwr.services.cli import main

    assert main(["study", "forms", "--store", str(store_path), "--host", "0.0.0.0", "--port", "0"]) == 2
    assert "every network of this machine" in caplog.text


def test_a_session_with_forms_on_a_wildcard_address_is_refused_before_anything_is_written(tmp_path, caplog):
    from nwr.services.cli import main

    profile = tmp_path / "profile.toml"
    profile.write_text(f'[recorder]\ndirectory = "{tmp_path / "rec"}"\n')
    assert main(["--profile", str(profile), "study", "--participant", "P07", "--order", "1", "--forms", "0",
                 "--forms-host", "0.0.0.0"]) == 2
    assert "every network of this machine" in caplog.text and not (tmp_path / "rec").exists()
    assert main(["--profile", str(profile), "study", "--participant", "Anna", "--order", "1"]) == 2
    assert "a participant ID is a code such as P07" in caplog.text and not (tmp_path / "rec").exists()
