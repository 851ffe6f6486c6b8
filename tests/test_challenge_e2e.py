"""A challenge as its host and a participant run it, end to end: `dsr-bench challenge create` with the real
generator (2 hidden sequences of 2 pushes from a secret seed), `dsr-bench serve` on a loopback port (uvicorn and a
worker process), `challenge add-team`, `challenge download`, `dsr-bench predict` on the downloaded inputs and
`dsr-bench submit`, which sees its submission go from queued to scored; and a real browser (Debian's chromium
through chromium-driver) watching a submission's page do the same, then signing in with the team's token, seeing
the team's history and choosing its final submission on its page; every page fits a 1400 px window."""

import json
import os
import re
import shutil
import signal
import stat
import subprocess
import sys

import h5py
import pytest

pytest.importorskip("pybullet")
pytest.importorskip("fastapi")
pytest.importorskip("httpx")
pytest.importorskip("argon2")

from challenge_helpers import DEADLINE, free_port, get, post, serve_args, wait_until, wait_until_serving  # noqa: E402

from dsr_bench.cli import main  # noqa: E402


@pytest.fixture(scope="module")
def created(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e") / "challenge"
    assert main(["challenge", "create", str(root), "--split", "procedural-novel-test", "-n", "2", "--steps", "2"]) == 0
    return root


@pytest.fixture(scope="module")
def server(created):
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "dsr_bench", *serve_args(created, port)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    url = f"http://127.0.0.1:{port}"
    try:
        wait_until_serving(url, proc)
    except RuntimeError as exc:
        proc.kill()
        raise RuntimeError(f"dsr-bench serve did not start ({exc}): {proc.communicate()[0]}") from None
    yield url
    proc.send_signal(signal.SIGINT)
    proc.wait(DEADLINE)


def test_create_keeps_the_seed_inside_and_exports_inputs_only(created, tmp_path):
    from dsr_bench.challenge.layout import open_challenge
    from dsr_bench.dataset.scored import file_scored_digests

    layout, config = open_challenge(created)
    assert stat.S_IMODE(created.stat().st_mode) == 0o700
    assert stat.S_IMODE(layout.seed.stat().st_mode) == 0o600
    seed = layout.seed.read_text().strip()
    with h5py.File(layout.hidden / "seq_0000.h5") as f:  # the hidden sequences come from the secret seed
        assert json.loads(f.attrs["generator_args"])["base_seed"] == int(seed)
        assert json.loads(f.attrs["generator_args"])["objects"] == "procedural-novel"
    assert sorted(config["public"] + config["private"]) == ["seq_0000", "seq_0001"] and config["public"]
    pins = json.loads(layout.pins.read_text())["sequences"]
    assert pins["seq_0001"]["scored"] == file_scored_digests(layout.hidden / "seq_0001.h5")
    for path in [layout.config, layout.pins, *layout.inputs.rglob("*")]:
        if path.is_file():
            assert seed.encode() not in path.read_bytes(), path
    with h5py.File(layout.inputs / "seq_0000.h5") as f:
        names: list[str] = []
        f.visit(lambda n: names.append(n) if isinstance(f[n], h5py.Dataset) else None)
        assert sorted(names) == ["action", "cameras/front/color", "cameras/front/depth", "tsdf"]
        assert json.loads(f.attrs["objects"]) == [] and json.loads(f.attrs["generator_args"]) == {}
    assert main(["challenge", "create", str(created), "--split", "procedural-novel-test", "-n", "2"]) == 2  # not empty
    assert main(["challenge", "export-inputs", str(created), str(layout.inputs)]) == 2  # exists: refused


def test_a_participant_downloads_predicts_submits_and_sees_the_score(created, server, tmp_path, capsys):
    assert main(["challenge", "add-team", str(created), "team one"]) == 0
    token = capsys.readouterr().out.strip().splitlines()[-1]
    inputs, predictions = tmp_path / "inputs", tmp_path / "predictions"
    assert main(["challenge", "download", str(inputs), "--server", server]) == 0
    assert main(["predict", "--model", "static", "--data", str(inputs), "--out", str(predictions)]) == 0
    capsys.readouterr()
    assert main(["submit", str(predictions), "--server", server, "--token", token, "--method", "static"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"submission [0-9a-f]{32}: queued", out) and re.search(r"submission [0-9a-f]{32}: scored", out)
    assert "public part: " in out and "iou_ordered" in out
    board = get(f"{server}/api/leaderboard").json()
    assert [row["team"] for row in board["tracks"]["3D"]] == ["team one"]
    # beside it, the clone's leaderboard's reference rows of a split generated like procedural-novel-test
    assert board["reference_split"] == "cpu-novel-test"
    assert sorted(r["method"] for r in board["reference_rows"]["3D"]) == ["oracle", "push", "static"]
    (predictions / "seq_0000.h5").unlink()
    assert main(["submit", str(predictions), "--server", server, "--token", token, "--method", "broken"]) == 1
    captured = capsys.readouterr()
    assert f"{predictions / 'seq_0000.h5'}: missing prediction file" in captured.err
    assert "no score: fix the problems above" in captured.err
    assert main(["submit", str(predictions), "--server", server, "--token", token[:-2] + "xx", "--method", "m"]) == 2
    assert "invalid or revoked token" in capsys.readouterr().err


def _chromium():
    webdriver = pytest.importorskip("selenium.webdriver")
    driver_path = shutil.which("chromedriver")
    binary = next((b for b in ("/usr/bin/chromium", shutil.which("chromium") or "") if b and os.path.exists(b)), None)
    if not driver_path or not binary:
        pytest.skip("Debian's chromium and chromium-driver are not installed (apt-get install chromium-driver)")
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1400,900"):
        options.add_argument(arg)
    from selenium.webdriver.chrome.service import Service

    return webdriver.Chrome(service=Service(driver_path), options=options)


def test_a_browser_sees_a_submission_go_from_queued_to_scored(created, server, tmp_path, capsys):
    from dsr_bench.challenge.client import pack

    browser = _chromium()
    try:
        assert main(["challenge", "add-team", str(created), "<b>browser</b> team"]) == 0
        token = capsys.readouterr().out.strip().splitlines()[-1]
        predictions = tmp_path / "predictions"
        from dsr_bench.models.predictors import load_predictor, predict_split

        predict_split(load_predictor("static"), created / "inputs", ["seq_0000", "seq_0001"], predictions)
        pack(predictions, tmp_path / "p.tar")
        reply = post(f"{server}/api/submissions", params={"method": "static (browser)"},
                     content=(tmp_path / "p.tar").read_bytes(), headers={"Authorization": f"Bearer {token}"})
        sid = reply.json()["id"]
        browser.get(f"{server}/submissions/{sid}")
        seen = {browser.find_element("id", "state").text}

        def page_scored() -> bool:
            browser.refresh()
            seen.add(browser.find_element("id", "state").text)
            return "scored" in seen

        if "scored" not in seen:
            wait_until(page_scored, f"the page of submission {sid} showing it scored (seen: {seen})", interval=0.5)
        assert seen & {"queued", "running"} and "scored" in seen
        assert "public part" in browser.page_source
        shots = os.environ.get("DSR_BENCH_SCREENSHOTS")
        if shots:
            browser.save_screenshot(os.path.join(shots, "challenge-submission.png"))
        browser.get(server + "/")
        row = [tr.text for tr in browser.find_elements("css selector", "tbody tr") if "<b>browser</b> team" in tr.text]
        assert row and "static (browser)" in row[0]
        assert not browser.find_elements("css selector", "td b")  # the team's markup shown as text, not rendered
        assert any(tr.text.startswith("static ") for tr in browser.find_elements("css selector", "tbody tr"))
        assert _fits(browser), "the leaderboard is wider than the window"
        browser.find_element("link text", "<b>browser</b> team").click()
        assert "Team <b>browser</b> team" in browser.find_element("tag name", "h1").text
        if shots:
            browser.get(server + "/")
            browser.save_screenshot(os.path.join(shots, "challenge-leaderboard.png"))

        # the team signs in with its token: its history, and its final choice made on its page
        browser.get(server + "/me")
        assert browser.current_url.endswith("/login")
        browser.find_element("id", "token").send_keys(token)
        browser.find_element("id", "sign-in").click()
        wait_until(lambda: "Team <b>browser</b> team: your submissions" in _text(browser, "tag name", "h1"),
                   "the browser signed in and shown the team's page")
        row = _text(browser, "id", f"row-{sid}")
        assert "static (browser)" in row and "scored" in row
        final_cell = f"#row-{sid} td:nth-child(6)"  # submitted, method, state, track, public part, final, ...
        assert _text(browser, "css selector", final_cell) == "choose as final"
        browser.find_element("id", f"final-{sid}").click()
        wait_until(lambda: _text(browser, "css selector", final_cell).split() == ["final", "unselect"],
                   "the team's page showing its final choice after the form was sent")
        assert get(f"{server}/api/submissions/{sid}").json()["final"] is True
        assert _fits(browser), "the team's page is wider than the window"
        if shots:
            browser.save_screenshot(os.path.join(shots, "challenge-history.png"))
        browser.get(f"{server}/submissions/{sid}")
        assert _fits(browser), "the submission's page is wider than the window"
    finally:
        browser.quit()


def _text(browser, by: str, what: str) -> str:
    """The text of the element found, "" while the page is being replaced (the element went stale)."""
    from selenium.common.exceptions import NoSuchElementException, StaleElementReferenceException

    try:
        return browser.find_element(by, what).text
    except (NoSuchElementException, StaleElementReferenceException):
        return ""


def _fits(browser) -> bool:
    """Whether the page needs no horizontal scrolling in the browser's window (1400 px)."""
    return browser.execute_script("return document.documentElement.scrollWidth <= window.innerWidth")
