"""The questionnaires filled in a real headless Chromium (selenium), then analysed.

Skipped without /usr/bin/chromium and /usr/bin/chromedriver, unless NWR_REQUIRE_BROWSER=1 (CI), where
their absence fails.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from study_synthetic import CONDITIONS, condition_forms, final_forms

from nwr.services.tools.study import analysis as sa
from nwr.services.tools.study.main import orders
from nwr.services.tools.study.store import ConditionForm, FinalForm, Store
from nwr.services.tools.study.web import serve

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")

pytestmark = [pytest.mark.slow, pytest.mark.e2e]


@pytest.fixture
def browser() -> Iterator[object]:
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists()]
    if missing:
        why = f"{', '.join(missing)} missing (Debian: apt-get install chromium chromium-driver)"
        if os.environ.get("NWR_REQUIRE_BROWSER") == "1":
            pytest.fail(f"NWR_REQUIRE_BROWSER=1 but {why}")
        pytest.skip(why)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                "--window-size=1024,1366"):  # a tablet, upright
        options.add_argument(arg)
    options.binary_location = str(CHROMIUM)
    driver = webdriver.Chrome(options=options, service=Service(str(CHROMEDRIVER)))
    driver.implicitly_wait(0)
    try:
        yield driver
    finally:
        driver.quit()


def text_of(driver, element_id: str) -> str:
    """The text of the element ``element_id`` once the page that has it is loaded (a click's navigation may
    still run)."""
    from selenium.common.exceptions import TimeoutException
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as ec
    from selenium.webdriver.support.ui import WebDriverWait

    try:
        return str(WebDriverWait(driver, 10).until(ec.presence_of_element_located((By.ID, element_id))).text)
    except TimeoutException:
        pytest.fail(f"no #{element_id} on {driver.current_url}: {driver.find_element(By.TAG_NAME, 'body').text}")


def fill_condition_form(driver, form: ConditionForm, keyboard: bool) -> None:
    """Tap each answer, or (``keyboard``, five times quicker on a loaded machine) Tab to each item's radio
    group, Space to pick 1 and the right arrow up to the value."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    if keyboard:
        keys: list[str] = []
        for value in form.ratings.values():  # in the page's order: the questionnaire's
            keys += [Keys.TAB, Keys.SPACE, *[Keys.ARROW_RIGHT] * (value - 1)]
        ActionChains(driver).send_keys(*keys).perform()
    else:
        for item, value in form.ratings.items():
            driver.find_element(By.CSS_SELECTOR, f'input[name="{item}"][value="{value}"]').click()
    checked = driver.execute_script(  # read back in one call (an attribute a call is slow on a loaded machine)
        "return Object.fromEntries([...document.querySelectorAll('input:checked')].map(e => [e.name, +e.value]))")
    assert checked == form.ratings
    driver.find_element(By.ID, "submit").click()


def fill_final_form(driver, form: FinalForm) -> None:
    from selenium.webdriver.common.by import By

    for question, option in form.choices.items():
        driver.find_element(By.CSS_SELECTOR, f'input[name="{question}"][value="{option}"]').click()
    for question, text in form.answers.items():
        driver.find_element(By.ID, f"text-{question}").send_keys(text)
    driver.find_element(By.ID, "submit").click()


def test_a_simulated_study_filled_in_a_browser_finds_the_preferred_condition(browser, tmp_path):
    from selenium.webdriver.common.by import By

    driver = browser
    store_path = tmp_path / "study.sqlite"
    with Store(store_path) as store:
        q = store.questionnaire
    rng = np.random.default_rng(5)
    # Nine participants, three per counterbalanced order: with six, no pairwise Wilcoxon test could pass Holm's
    # correction over three pairs (its smallest exact p is 2/64, times 3).
    n = 9
    forms = condition_forms(q, rng, n, {"cartesian": 1.5})
    finals = final_forms(q, rng, n, {"cartesian": 6, "uniform": 1, "location": 1, "none": 1})
    assert {f.order for f in forms} == {1, 2, 3}

    with serve(store_path, port=0) as server, Store(store_path) as store:
        for i, final in enumerate(finals):
            mine = sorted((f for f in forms if f.participant == final.participant), key=lambda f: f.block)
            order = mine[0].order
            store.plan(final.participant, order, orders(CONDITIONS)[order - 1])  # as `nwr study` does
            for form in mine:
                store.recorded(form.participant, form.block)
                driver.get(server.url)  # the start page links the form that is due
                assert f"Participant {form.participant} (current)" in driver.page_source
                driver.find_element(By.CSS_SELECTOR, f"#participant-{form.participant} a.due").click()
                assert driver.current_url.endswith(f"/p/{form.participant}/block/{form.block}")
                if i == 0 and form.block == 1:
                    # One item left out: the browser itself refuses to submit (required), nothing is stored.
                    left_out = list(form.ratings)[-1]
                    for item, value in form.ratings.items():
                        if item != left_out:
                            driver.find_element(By.CSS_SELECTOR, f'input[name="{item}"][value="{value}"]').click()
                    driver.find_element(By.ID, "submit").click()
                    assert driver.current_url.endswith("/block/1") and store.submitted_at(
                        form.participant, form.condition) is None
                    driver.get(driver.current_url)  # a fresh form
                fill_condition_form(driver, form, keyboard=i > 0)
                assert text_of(driver, "title") == "Thank you!"
                assert store.submitted_at(form.participant, form.condition) is not None
            text_of(driver, "next")
            driver.find_element(By.ID, "next").click()  # after the last block: the final questionnaire
            assert driver.current_url.endswith(f"/p/{final.participant}/final")
            fill_final_form(driver, final)
            assert "All questionnaires are answered" in text_of(driver, "done")
        # A second submission of a form: refused with a clear page, the first answers kept.
        driver.get(f"{server.url}p/P01/block/1")
        assert text_of(driver, "title") == "Already answered"
        assert "already submitted" in text_of(driver, "message")

    with Store(store_path) as store:
        stored = {(r.participant, r.condition, r.order, r.block, r.item): r.value for r in store.ratings()}
        assert stored == {(f.participant, f.condition, f.order, f.block, item): v for f in forms
                          for item, v in f.ratings.items()}
        kept = {(a.participant, a.item): a.text for a in store.final_answers() if a.text}
        assert kept == {**{(f.participant, c): o for f in finals for c, o in f.choices.items()},
                        **{(f.participant, k): t for f in finals for k, t in f.answers.items()}}

    result, report, _, _ = sa.run(store_path, tmp_path / "analysis")
    assert result.complete == [f"P{i:02d}" for i in range(1, n + 1)] and not result.excluded
    for s in result.scales:
        assert s.p is not None and s.p < 0.05, (s.scale.name, s.p)
        for pair in s.pairs:
            if "cartesian" in (pair.a, pair.b):
                assert pair.p_holm < 0.05, (s.scale.name, pair)
                assert (pair.r > 0) == (pair.a == "cartesian"), (s.scale.name, pair)  # rated higher
    assert sum(result.votes["safest"].values()) == n
    assert result.votes["most_natural"].most_common(1)[0][0] == "cartesian"
    assert report.exists()


def test_a_session_with_forms_waits_for_each_blocks_questionnaire(browser, tmp_path):
    """``nwr study --forms``: after each block the session waits for its form, filled here in the browser."""
    import socket
    import subprocess
    import sys
    import time

    from selenium.webdriver.common.by import By

    driver = browser
    with socket.socket() as s:  # a free port for the forms
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    profile = tmp_path / "profile.toml"
    profile.write_text(f'[zenoh]\nbase_port = 17970\n[recorder]\ndirectory = "{tmp_path}"\n')
    log = tmp_path / "study.log"
    with open(log, "w") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "nwr.services.cli", "--profile", str(profile), "study", "--participant", "P03",
             "--order", "3", "--block-s", "3", "--follow-target", "1", "--forms", str(port)],
            stdout=out, stderr=subprocess.STDOUT, text=True)
    try:
        with Store(tmp_path / "study.sqlite") as store:
            q = store.questionnaire
        rng = np.random.default_rng(1)
        forms = [f for f in condition_forms(q, rng, 3, {}) if f.participant == "P03"]
        url = f"http://127.0.0.1:{port}/"
        deadline = time.monotonic() + 300  # three blocks with their start-ups, on a loaded machine
        for form in forms:
            while True:  # the session's page shows the form once its block is recorded
                assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
                try:
                    driver.get(url)
                except Exception:  # noqa: BLE001 - the server may not be up yet
                    time.sleep(0.5)
                    continue
                links = driver.find_elements(By.CSS_SELECTOR, "#participant-P03 a.due")
                if links:
                    break
                time.sleep(0.5)
            links[0].click()
            assert driver.current_url.endswith(f"/p/P03/block/{form.block}"), driver.current_url
            fill_condition_form(driver, form, keyboard=True)
            assert text_of(driver, "title") == "Thank you!"
        text_of(driver, "next")
        driver.find_element(By.ID, "next").click()
        fill_final_form(driver, FinalForm(participant="P03", choices={c.id: "none" for c in q.choice}))
        assert "All questionnaires are answered" in text_of(driver, "done")
        assert proc.wait(60) == 0, log.read_text()
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(30)
    output = log.read_text()
    assert f"questionnaires for participant P03: {url}" in output
    assert f"waiting for the questionnaire of block 1 (cartesian): {url}p/P03/block/1" in output
    assert f"waiting for the final questionnaire: {url}p/P03/final" in output
    with Store(tmp_path / "study.sqlite") as store:
        blocks = store.blocks("P03")
        assert [(b.block, b.condition, b.order) for b in blocks] == [(1, "cartesian", 3), (2, "uniform", 3),
                                                                     (3, "location", 3)]
        assert all(b.recorded_at and b.answered_at for b in blocks)
        assert {(r.block, r.condition) for r in store.ratings()} == {(1, "cartesian"), (2, "uniform"),
                                                                     (3, "location")}


def test_a_form_posted_from_another_sites_page_is_refused_and_the_participant_still_answers(browser, tmp_path):
    """A page of another origin (here another port of 127.0.0.1) that posts a filled-in form to the
    questionnaire: the browser sends its Origin, the server refuses it and stores nothing; then the
    participant's own form goes through."""
    import http.server
    import threading
    from functools import partial

    from selenium.webdriver.common.by import By

    driver = browser
    store_path = tmp_path / "study.sqlite"
    with Store(store_path) as store:
        q = store.questionnaire
        store.plan("P05", 1, CONDITIONS)
        store.recorded("P05", 1)
    form = next(f for f in condition_forms(q, np.random.default_rng(2), 5, {}) if f.participant == "P05"
                and f.block == 1)
    with serve(store_path, port=0) as server:
        fields = "".join(f'<input type="hidden" name="{k}" value="{v}">' for k, v in form.ratings.items())
        (tmp_path / "evil").mkdir()
        (tmp_path / "evil" / "index.html").write_text(
            f'<!doctype html><form method="post" action="{server.url}p/P05/block/1">{fields}'
            '<input type="hidden" name="token" value="guessed"><button id="go">Win a prize</button></form>')
        handler = partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path / "evil"))
        evil = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        threading.Thread(target=evil.serve_forever, daemon=True).start()
        try:
            driver.get(f"http://127.0.0.1:{evil.server_address[1]}/")
            driver.find_element(By.ID, "go").click()
            assert text_of(driver, "title") == "Not sent from this questionnaire"
            assert "Nothing was saved" in text_of(driver, "message")
        finally:
            evil.shutdown()
            evil.server_close()
        with Store(store_path) as store:
            assert store.submitted_at("P05", form.condition) is None
        driver.get(server.url + "p/P05/block/1")  # the participant's own form: not "Already answered"
        fill_condition_form(driver, form, keyboard=True)
        assert text_of(driver, "title") == "Thank you!"
    with Store(store_path) as store:
        assert {r.item: r.value for r in store.ratings()} == form.ratings
