"""What participants expect of the challenge's site and commands: signing in with the team's token (a session
cookie: HttpOnly, SameSite=Strict; forms with a CSRF token, refused from another origin), the team's own history
with each submission's reason and result file, choosing finals on the page and from the command line, the
participants' guide, a submission's page with both tracks, its breakdowns, toolkit and split checksum, a refused
submission that does not use a daily try, `submit`'s exit codes as its help says, and a stalled download as one
line."""

from __future__ import annotations

import re
import socket
import threading

import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")
pytest.importorskip("argon2")

import httpx  # noqa: E402
from challenge_helpers import LiveServer, challenge_with_teams, get, post, wait_for_state  # noqa: E402

from dsr_bench.cli import main  # noqa: E402


@pytest.fixture
def challenge(tmp_path, tmp_path_factory):
    yield from challenge_with_teams(tmp_path_factory, tmp_path)


def _serve(layout, **overrides) -> LiveServer:
    from dsr_bench.challenge.server import Settings, create_app

    return LiveServer(create_app(layout.root, settings=Settings(keep_free=0, auth_max_delay=0.01, board_cache=0.0,
                                                                overrides=overrides or None)))


def _upload(url: str, token: str, predictions, tmp_path, method: str) -> httpx.Response:
    from dsr_bench.challenge.client import pack

    pack(predictions, tmp_path / f"{method}.tar")
    return post(f"{url}/api/submissions", params={"method": method}, content=(tmp_path / f"{method}.tar").read_bytes(),
                headers={"Authorization": f"Bearer {token}"})


def _score_all(layout) -> int:
    from dsr_bench.challenge.worker import run_worker

    return run_worker(str(layout.root), layout.default_db_url(), once=True)


def _sign_in(url: str, token: str) -> httpx.Client:
    """A browser-like client signed in with `token` (its cookie jar holds the session)."""
    client = httpx.Client(base_url=url, timeout=300.0)
    reply = client.post("/login", data={"token": token})
    assert reply.status_code == 303 and reply.headers["location"] == "/me", reply.text
    return client


def _csrf(page: str) -> str:
    return re.search(r'name="csrf" value="([0-9a-f]+)"', page).group(1)


def test_a_team_signs_in_sees_its_history_and_chooses_finals_on_its_page(challenge, tmp_path):
    layout, sessions, tokens, predictions = challenge
    with _serve(layout, max_final=1) as live:
        good = _upload(live.url, tokens["alpha"], predictions, tmp_path, "good").json()["id"]
        (predictions / "seq_0001.h5").unlink()
        broken = _upload(live.url, tokens["alpha"], predictions, tmp_path, "broken").json()["id"]
        assert _score_all(layout) == 2

        anonymous = httpx.get(f"{live.url}/me", timeout=300.0)
        assert anonymous.status_code == 303 and anonymous.headers["location"] == "/login"
        wrong = httpx.post(f"{live.url}/login", data={"token": tokens["alpha"][:-2] + "xx"}, timeout=300.0)
        assert wrong.status_code == 401 and "invalid or revoked token" in wrong.text
        assert "set-cookie" not in wrong.headers
        login = httpx.post(f"{live.url}/login", data={"token": tokens["alpha"]}, timeout=300.0)
        cookie = login.headers["set-cookie"]
        assert "HttpOnly" in cookie and "SameSite=strict" in cookie and "Path=/" in cookie, cookie
        assert tokens["alpha"] not in cookie

        alpha = _sign_in(live.url, tokens["alpha"])
        page = alpha.get("/me")
        assert page.status_code == 200 and page.headers["x-frame-options"] == "DENY"
        text = page.text
        assert "Team alpha: your submissions" in text
        assert f'href="/submissions/{good}"' in text and f'href="/submissions/{broken}"' in text
        assert "seq_0001.h5: missing prediction file" in text  # why the refused one was refused
        assert "1 of 5 submissions used today" in text  # the refused one gave its try back
        assert f'id="final-{good}"' in text and f'id="final-{broken}"' not in text  # only a scored one can be final
        assert f'href="/api/submissions/{good}/result"' in text

        result = alpha.get(f"/api/submissions/{good}/result")
        assert result.headers["content-disposition"] == f'attachment; filename="submission-{good}.json"'
        data = result.json()
        assert data["format"] == "dsr-bench-challenge-result" and set(data["scores"]) == {"public"}
        assert "iou_ordered" in data["scores"]["public"]["metrics"] and data["scores"]["public"]["breakdowns"]
        refused = alpha.get(f"/api/submissions/{broken}/result").json()
        assert refused["state"] == "refused" and "seq_0001.h5: missing prediction file" in refused["messages"]

        csrf = _csrf(text)
        assert alpha.post("/me/final", data={"sid": good, "final": "1"}).status_code == 403  # no CSRF token
        assert alpha.post("/me/final", data={"sid": good, "final": "1", "csrf": csrf},
                          headers={"Origin": "https://evil.example"}).status_code == 403
        beta = _sign_in(live.url, tokens["beta"])
        assert beta.post("/me/final", data={"sid": good, "final": "1", "csrf": csrf}).status_code == 403  # not its
        assert beta.post("/me/final", data={"sid": good, "final": "1",
                                            "csrf": _csrf(beta.get("/me").text)}).status_code == 400  # not its own
        chosen = alpha.post("/me/final", data={"sid": good, "final": "1", "csrf": csrf})
        assert chosen.status_code == 303 and chosen.headers["location"] == "/me"
        assert get(f"{live.url}/api/submissions/{good}").json()["final"] is True
        assert "unselect" in alpha.get("/me").text

        forged = httpx.Client(base_url=live.url, timeout=300.0)
        forged.cookies.set("dsr_session", alpha.cookies["dsr_session"][:-1] + "0")
        assert forged.get("/me").status_code == 303  # a tampered cookie signs nobody in
        assert alpha.post("/logout", data={"csrf": csrf}).status_code == 303
        assert alpha.get("/me").status_code == 303
    from dsr_bench.challenge.service import revoke_team

    with _serve(layout) as live:  # a new server process: every session ends (the token stays valid)
        again = _sign_in(live.url, tokens["alpha"])
        revoke_team(sessions, "alpha")
        assert again.get("/me").status_code == 303  # a revoked team's session ends at once


def test_the_submission_page_shows_both_tracks_breakdowns_toolkit_and_checksum(challenge, tmp_path):
    from dsr_bench import __version__
    from dsr_bench.challenge.host import expected_truth_checksum, load_pins
    from dsr_bench.challenge.layout import open_challenge

    layout, sessions, tokens, predictions = challenge
    with _serve(layout) as live:
        sid = _upload(live.url, tokens["alpha"], predictions, tmp_path, "static").json()["id"]
        _score_all(layout)
        view = get(f"{live.url}/api/submissions/{sid}").json()
        page = get(f"{live.url}/submissions/{sid}").text
    metrics = view["scores"]["public"]["metrics"]
    assert "motion_2d" in metrics  # the static predictions hold motion_2d: both tracks are scored
    assert "<h3>3D track</h3>" in page and "<h3>2D track</h3>" in page and "2D flow MSE" in page
    assert "IoU of mostly occluded objects" in page and "flow MSE of moved objects" in page
    config = open_challenge(layout.root)[1]
    checksum = expected_truth_checksum(load_pins(layout), config["public"], metrics)[:12]
    assert f"<code>{checksum}</code>" in page and f"<td>{__version__}</td>" in page
    assert '<a href="/">leaderboard</a>' in page and '<a href="/teams/alpha">team alpha</a>' in page
    assert f'href="/api/submissions/{sid}/result"' in page
    assert "private" not in page  # not revealed


def test_a_refused_submission_does_not_use_a_daily_try(challenge, tmp_path):
    layout, sessions, tokens, predictions = challenge
    (predictions / "seq_0001.h5").rename(tmp_path / "kept.h5")
    with _serve(layout, daily_limit=1) as live:
        broken = _upload(live.url, tokens["alpha"], predictions, tmp_path, "broken")
        assert broken.status_code == 202
        pending = _upload(live.url, tokens["alpha"], predictions, tmp_path, "while queued")
        assert pending.status_code == 429  # a queued one holds its try until it is scored or refused
        _score_all(layout)
        assert wait_for_state(live.url, broken.json()["id"])["state"] == "refused"
        (tmp_path / "kept.h5").rename(predictions / "seq_0001.h5")
        assert _upload(live.url, tokens["alpha"], predictions, tmp_path, "fixed").status_code == 202
        assert _upload(live.url, tokens["alpha"], predictions, tmp_path, "one more").status_code == 429


def test_the_participants_guide(challenge):
    layout, *_ = challenge
    with _serve(layout, daily_limit=3, max_final=2) as live:
        page = get(f"{live.url}/participate").text
        board = get(f"{live.url}/").text
    for command in (f"dsr-bench challenge download inputs --server {live.url}", "dsr-bench predict --model static",
                    f"dsr-bench submit predictions --server {live.url}",
                    f"dsr-bench challenge final --server {live.url}"):
        assert command in page, command
    assert "3 submissions per team per UTC day" in page and "at most 2" in page and 'href="/me"' in page
    assert 'href="/participate"' in board


class _Worker:
    """A worker thread scoring what is queued until the block ends."""

    def __init__(self, layout):
        from dsr_bench.challenge.worker import run_worker

        self.stop = threading.Event()
        self.thread = threading.Thread(target=run_worker, args=(str(layout.root), layout.default_db_url()),
                                       kwargs={"stop": self.stop, "poll": 0.1}, daemon=True)

    def __enter__(self) -> _Worker:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(600)


def test_submit_exit_codes_and_finals_from_the_command_line(challenge, tmp_path, capsys):
    layout, sessions, tokens, predictions = challenge
    token = tokens["alpha"]
    with _serve(layout, daily_limit=2, max_final=1) as live, _Worker(layout):
        args = ["--server", live.url, "--token", token]
        assert main(["submit", str(predictions), *args, "--method", "mine", "--final"]) == 0
        out = capsys.readouterr().out
        sid = re.search(r"submission ([0-9a-f]{32}): scored", out).group(1)
        assert f"submission {sid}: chosen as one of your final submissions" in out
        assert main(["challenge", "final", *args]) == 0
        listing = capsys.readouterr().out
        assert re.search(rf"{sid} .* scored .*'mine'.*FINAL", listing), listing
        assert main(["challenge", "final", sid, *args, "--undo"]) == 0
        assert "not a final submission" in capsys.readouterr().out
        assert get(f"{live.url}/api/submissions/{sid}").json()["final"] is False

        (predictions / "seq_0001.h5").rename(tmp_path / "kept.h5")
        assert main(["submit", str(predictions), *args, "--method", "broken"]) == 1  # stored, refused
        assert "no score: fix the problems above" in capsys.readouterr().err
        (tmp_path / "kept.h5").rename(predictions / "seq_0001.h5")
        assert main(["submit", str(predictions), *args, "--method", "second"]) == 0
        capsys.readouterr()
        assert main(["submit", str(predictions), *args, "--method", "third"]) == 2  # the quota: one line
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "has used its 2 submissions of today" in err, err
        other = ["--server", live.url, "--token", tokens["beta"]]
        assert main(["challenge", "final", sid, *other]) == 2  # not beta's
        assert "no submission" in capsys.readouterr().err
    assert main(["submit", "--help"]) == 0
    helptext = " ".join(capsys.readouterr().out.split())
    assert "Exit 0: scored" in helptext and "1: stored but refused or failed" in helptext
    assert "2: one line, nothing scored" in helptext


def test_a_stalled_download_is_one_line_and_keeps_nothing(tmp_path, monkeypatch, capsys):
    import dsr_bench.challenge.client as client

    monkeypatch.setattr(client, "READ_TIMEOUT", 0.5)
    listener = socket.create_server(("127.0.0.1", 0))
    accepted = []
    threading.Thread(target=lambda: accepted.append(listener.accept()), daemon=True).start()  # never answers
    url = f"http://127.0.0.1:{listener.getsockname()[1]}"
    try:
        assert main(["challenge", "download", str(tmp_path / "inputs"), "--server", url]) == 2
    finally:
        listener.close()
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "ReadTimeout" in err and "try again" in err, err
    assert not (tmp_path / "inputs").exists()
