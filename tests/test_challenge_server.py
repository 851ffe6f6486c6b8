"""The challenge server's promises: no route, file name or message gives away the hidden ground truth, the secret
seed or another team's predictions; tokens are checked, revocable and their failures slowed; the daily quota,
phases, final selections, the private part's reveal and a host's re-score; a worker SIGKILLed mid-evaluation is
replaced and the job scored once; a server stopped mid-upload leaves nothing visible."""

import html
import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")
pytest.importorskip("argon2")

import httpx  # noqa: E402
from challenge_helpers import LiveServer, copy_challenge, get, post  # noqa: E402

SEED = "987654321987654321"  # the template challenge's secret seed


@pytest.fixture
def challenge(tmp_path, tmp_path_factory):
    from dsr_bench.challenge.db import open_database
    from dsr_bench.challenge.layout import Layout
    from dsr_bench.challenge.service import add_team

    root, predictions = copy_challenge(tmp_path_factory, tmp_path)
    layout = Layout(root)
    engine, sessions = open_database(layout.default_db_url())
    tokens = {name: add_team(sessions, name) for name in ("alpha", "<script>alert(1)</script>")}
    yield layout, sessions, tokens, predictions
    engine.dispose()


def _serve(layout, leaderboard=None, **overrides):
    """A live server of `layout` with the configuration's `overrides` (e.g. daily_limit=2) and the local
    `leaderboard` folder (default: the clone's)."""
    from dsr_bench.challenge.server import Settings, create_app

    return LiveServer(create_app(layout.root, settings=Settings(keep_free=0, auth_max_delay=0.01, board_cache=0.0,
                                                                overrides=overrides or None, leaderboard=leaderboard)))


def _upload(url, token, predictions, tmp_path, method="static") -> httpx.Response:
    from dsr_bench.challenge.client import pack

    archive = tmp_path / f"{method}.tar"
    pack(predictions, archive)
    return post(f"{url}/api/submissions", params={"method": method}, content=archive.read_bytes(),
                headers={"Authorization": f"Bearer {token}"})


def _score_all(layout) -> int:
    from dsr_bench.challenge.worker import run_worker

    return run_worker(str(layout.root), layout.default_db_url(), once=True)


def test_no_route_gives_away_the_hidden_set_the_seed_or_another_teams_work(challenge, tmp_path):
    layout, sessions, tokens, predictions = challenge
    with _serve(layout) as live:
        mine = _upload(live.url, tokens["alpha"], predictions, tmp_path).json()["id"]
        (predictions / "seq_0001.h5").unlink()  # a refused one too: its messages are shown
        refused = _upload(live.url, tokens["alpha"], predictions, tmp_path, "partial").json()["id"]
        assert _score_all(layout) == 2
        other = tokens["<script>alert(1)</script>"]
        pages = ["/", "/api/leaderboard", f"/api/submissions/{mine}", f"/submissions/{mine}",
                 f"/api/submissions/{refused}", f"/submissions/{refused}", "/teams/alpha", "/api/inputs",
                 "/api/inputs/seq_0000.h5", "/api/inputs/digests.json"]
        bodies = {page: get(live.url + page).content for page in pages}
        assert all(get(live.url + page).status_code == 200 for page in pages if "digests" not in page)
        history = get(f"{live.url}/api/me/submissions", headers={"Authorization": f"Bearer {other}"})
        assert history.status_code == 200 and history.json()["submissions"] == []  # not alpha's
        bodies["history"] = history.content
        for page, body in bodies.items():
            assert SEED.encode() not in body, page
            for leak in (b"per_step", b"per_sequence", b"predictions_sha256", str(layout.root).encode(),
                         b"ground_truth_sha256", b"secret_seed"):
                assert leak not in body, (page, leak)
        status = json.loads(bodies[f"/api/submissions/{mine}"])
        assert status["state"] == "scored" and set(status["scores"]) == {"public"}  # the private part stays hidden
        refusal = json.loads(bodies[f"/api/submissions/{refused}"])
        assert refusal["state"] == "refused"
        assert "seq_0001.h5: missing prediction file" in refusal["messages"]
        for name in ("..%2Fsecret_seed", "%2E%2E%2Fchallenge.json", "challenge.json", "pins.json", "secret_seed",
                     "..%2Fhidden%2Fseq_0000.h5", ".%2E%2Fsubmissions", "digests.json%00"):
            reply = get(f"{live.url}/api/inputs/{name}")
            assert reply.status_code == 404 and SEED.encode() not in reply.content, name
        raw = get(f"{live.url}/api/inputs/../secret_seed")  # normalised by the client: still not the seed
        assert SEED.encode() not in raw.content
        for path in ["/api/submissions/..%2F..%2Fsecret_seed", f"/api/submissions/{mine}/archive",
                     f"/submissions/{mine}.tar"]:
            assert get(live.url + path).status_code == 404
    assert SEED not in "".join(p.name for p in layout.root.rglob("*"))


def test_pages_escape_team_and_method_names(challenge, tmp_path):
    layout, sessions, tokens, predictions = challenge
    with _serve(layout) as live:
        sid = _upload(live.url, tokens["<script>alert(1)</script>"], predictions, tmp_path,
                      "<img src=x onerror=alert(2)>").json()["id"]
        _score_all(layout)
        for page in ("/", f"/submissions/{sid}", "/teams/%3Cscript%3Ealert(1)%3C%2Fscript%3E"):
            body = get(live.url + page).text
            assert "<script>alert(1)" not in body and "<img src=x" not in body, page
            assert "&lt;script&gt;alert(1)&lt;/script&gt;" in body or "&lt;img src=x" in body, page


def _board_rows(page: str, heading: str) -> tuple[str, list[str]]:
    """The header row and the body rows (each `<tr>...</tr>` as served) of the table that follows `heading`."""
    table = page[page.index(heading):]
    table = table[table.index("<table"):table.index("</table>")]
    head = re.search(r"<thead>(.*?)</thead>", table).group(1)
    return head, re.findall(r"<tr>.*?</tr>", table[table.index("<tbody>"):])


def test_server_and_local_leaderboard_render_rows_alike_and_escape_method_names(challenge, tmp_path, board):
    """The challenge's leaderboard shows the local leaderboard's reference rows of its split, each rendered cell for
    cell as the local index.html renders it (the one renderer), and a hostile method name is escaped on both."""
    from test_leaderboard import _put, _results

    from dsr_bench.leaderboard.board import build
    from dsr_bench.leaderboard.entries import markdown_cell

    layout, sessions, tokens, predictions = challenge
    split = "procedural-novel-mini"  # pinned to "c" * 64 by the board fixture
    _put(board, _results("static", motion_visible=0.9, motion_full=0.05, iou_ordered=0.2, iou_unordered=0.25))
    _put(board, _results("push", motion_visible=3.0, motion_full=0.07, iou_ordered=0.5, iou_unordered=0.55))
    _put(board, _results("oracle", motion_visible=0.0, motion_full=0.0, iou_ordered=1.0, iou_unordered=1.0))
    build(board)
    local_head, local_rows = _board_rows((board / "index.html").read_text(), f'id="{split}-3d-reproduced"')
    assert len(local_rows) == 3 and any(r.startswith("<tr><td>static</td>") for r in local_rows)

    hostile = "<img src=x onerror=alert(3)>|*x*"
    with _serve(layout, leaderboard=board, split=split) as live:
        head, rows = _board_rows(get(live.url + "/").text, "3D track (public part)")
        lead = "<td></td><td></td>"  # a reference row has no rank and no team
        assert head == ('<tr><th onclick="sortTable(this)">#</th><th onclick="sortTable(this)">team</th>'
                        + local_head[len("<tr>"):])
        assert rows == ["<tr>" + lead + r[len("<tr>"):] for r in local_rows]
        api = get(live.url + "/api/leaderboard").json()
        assert api["reference_split"] == split
        static = {r["method"]: r for r in api["reference_rows"]["3D"]}["static"]
        assert sorted(r["method"] for r in api["reference_rows"]["3D"]) == ["oracle", "push", "static"]
        assert static["metrics"]["iou_ordered"] == pytest.approx(0.2) and static["split_checksum"] == "c" * 12

        sid = _upload(live.url, tokens["alpha"], predictions, tmp_path, hostile).json()["id"]
        other = _upload(live.url, tokens["<script>alert(1)</script>"], predictions, tmp_path, "static").json()["id"]
        _score_all(layout)
        page = get(live.url + "/").text
        head, rows = _board_rows(page, "3D track (public part)")
        assert len(rows) == 5 and rows[0].startswith('<tr><td>1</td><td><a href="/teams/alpha">alpha</a></td>')
        assert f'<a href="/submissions/{sid}">{html.escape(hostile)}</a>' in rows[0]
        # a submission named like a reference row is a submission: ranked, not noted "reference", no yardstick
        named_static = next(r for r in rows if f'href="/submissions/{other}"' in r)
        assert named_static.startswith("<tr><td>2</td>") and "reference" not in named_static
        # submissions (hidden set) are marked apart from the reference rows (a public split): those stay as local
        assert 'class="' not in named_static and rows[2:] == ["<tr>" + lead + r[len("<tr>"):] for r in local_rows]
        assert "<img src=x" not in page
        for path in (f"/submissions/{sid}", "/teams/alpha"):
            shown = get(live.url + path).text
            assert "<img src=x" not in shown and html.escape(hostile) in shown, path

    _put(board, _results(hostile, iou_ordered=0.4))
    build(board)
    readme, index = (board / "README.md").read_text(), (board / "index.html").read_text()
    assert "<img src=x" not in readme and "<img src=x" not in index
    assert f"| {markdown_cell(hostile)} |" in readme and "\\|" in markdown_cell(hostile)
    assert f"<td>{html.escape(hostile)}</td>" in index


def test_reference_rows_come_from_the_split_or_one_generated_alike():
    """A challenge on procedural-novel-test, which the clone's leaderboard has no rows of, shows the reference rows
    of cpu-novel-test (its first 100 sequences: the same generator settings); a split with no such rows, none."""
    from pathlib import Path

    from dsr_bench.challenge.service import reference_rows

    root = Path(__file__).resolve().parents[1] / "leaderboard"
    shown, rows = reference_rows(root, "procedural-novel-test")
    assert shown == "cpu-novel-test" and set(rows) == {"3D", "2D"}
    assert sorted(r["method"] for r in rows["3D"]) == ["oracle", "push", "static"]
    assert all(len(r["_per_unit"]) == 100 and r["checksum"] for r in rows["3D"])  # its 100 sequences
    assert reference_rows(root, "synthetic") == (None, {}) == reference_rows(root / "missing", "cpu-novel-test")


def test_tokens_wrong_malformed_revoked_and_slowed(challenge, tmp_path):
    from dsr_bench.challenge.service import revoke_team

    layout, sessions, tokens, predictions = challenge
    good = tokens["alpha"]
    from dsr_bench.challenge.server import Settings, create_app

    with LiveServer(create_app(layout.root, settings=Settings(keep_free=0, auth_limit=4,
                                                              auth_max_delay=0.01))) as live:
        def me(token):
            return get(f"{live.url}/api/me/submissions", headers={"Authorization": f"Bearer {token}"})

        assert me(good).status_code == 200
        wrong = good[:-4] + ("AAAA" if not good.endswith("AAAA") else "BBBB")
        for bad in (wrong, "garbage", "dsrc_000000000000_" + "x" * 43):
            assert me(bad).status_code == 401
        assert get(f"{live.url}/api/me/submissions").status_code == 401
        blocked = me(good)  # 4 failures from this address: even the right token waits now
        assert blocked.status_code == 429 and int(blocked.headers["retry-after"]) > 0
    with _serve(layout) as live:
        revoke_team(sessions, "alpha")
        assert _upload(live.url, good, predictions, tmp_path).status_code == 401


def test_daily_quota(challenge, tmp_path):
    layout, sessions, tokens, predictions = challenge
    with _serve(layout, daily_limit=2) as live:
        assert _upload(live.url, tokens["alpha"], predictions, tmp_path).status_code == 202
        assert _upload(live.url, tokens["alpha"], predictions, tmp_path).status_code == 202
        third = _upload(live.url, tokens["alpha"], predictions, tmp_path)
        assert third.status_code == 429 and "2 submissions of today" in third.json()["detail"]
        assert _upload(live.url, tokens["<script>alert(1)</script>"], predictions, tmp_path).status_code == 202


def test_phases_final_selection_reveal_and_rescore(challenge, tmp_path):
    import datetime as dt

    from sqlalchemy import select

    from dsr_bench.challenge.db import Score, utcnow
    from dsr_bench.challenge.layout import open_challenge, write_config
    from dsr_bench.challenge.service import add_phase, request_rescore

    layout, sessions, tokens, predictions = challenge
    now = utcnow()
    add_phase(sessions, "final", now + dt.timedelta(days=1), now + dt.timedelta(days=2))
    with _serve(layout) as live:
        closed = _upload(live.url, tokens["alpha"], predictions, tmp_path)
        assert closed.status_code == 403 and "opens" in closed.json()["detail"]
    add_phase(sessions, "development", now - dt.timedelta(hours=1), now + dt.timedelta(hours=1))
    auth = {"Authorization": f"Bearer {tokens['alpha']}"}
    with _serve(layout, max_final=1) as live:
        first = _upload(live.url, tokens["alpha"], predictions, tmp_path).json()["id"]
        second = _upload(live.url, tokens["alpha"], predictions, tmp_path, "again").json()["id"]
        assert post(f"{live.url}/api/submissions/{first}/final", json={"final": True},
                    headers=auth).status_code == 400  # queued, not scored yet
        _score_all(layout)
        assert get(f"{live.url}/api/submissions/{first}").json()["phase"] == "development"
        chosen = post(f"{live.url}/api/submissions/{first}/final", json={"final": True}, headers=auth)
        assert chosen.status_code == 200 and chosen.json()["final"] is True
        over = post(f"{live.url}/api/submissions/{second}/final", json={"final": True}, headers=auth)
        assert over.status_code == 400 and "unselect one first" in over.json()["detail"]
        padded = b'{"final": true, "pad": "' + b"x" * 8_000_000 + b'"}'  # read only up to the limit, then refused
        huge = post(f"{live.url}/api/submissions/{second}/final", content=padded, headers=auth)
        assert huge.status_code == 413 and "at most 4096 bytes" in huge.json()["detail"]
        other = {"Authorization": f"Bearer {tokens['<script>alert(1)</script>']}"}
        assert post(f"{live.url}/api/submissions/{second}/final", json={"final": True},
                    headers=other).status_code == 400  # not that team's
        board = get(f"{live.url}/api/leaderboard").json()
        assert len(board["tracks"]["3D"]) == 2 and "final" not in board
        config = open_challenge(layout.root)[1]
        write_config(layout, {**config, "reveal_private": True})
        board = get(f"{live.url}/api/leaderboard").json()
        assert [row["id"] for row in board["final"]["3D"]] == [first]
        assert "private" in get(f"{live.url}/api/submissions/{first}").json()["scores"]
        assert "Final ranking" in get(live.url + "/").text
    assert request_rescore(sessions) == 2
    assert _score_all(layout) == 2
    with sessions() as session:
        scores = session.scalars(select(Score).where(Score.submission_id == first)).all()
    from dsr_bench import __version__

    assert sorted((s.run, s.current) for s in scores) == [(1, False), (1, False), (2, True), (2, True)]
    assert {s.toolkit_version for s in scores} == {__version__}
    old = {s.part: json.loads(s.metrics) for s in scores if s.run == 1}
    new = {s.part: json.loads(s.metrics) for s in scores if s.run == 2}
    assert old == new  # the same toolkit scores the same


WORKER = """
import sys, time
import dsr_bench.challenge.worker as w
real = w.evaluate_submission
def slow(*args):
    print("evaluating", flush=True)
    time.sleep(60)
    return real(*args)
w.evaluate_submission = slow
w.run_worker(sys.argv[1], sys.argv[2], lease=1.0)
"""


def test_a_worker_killed_mid_evaluation_is_replaced_and_the_job_scored_once(challenge, tmp_path):
    from sqlalchemy import func, select

    from dsr_bench.challenge.db import Score, Submission
    from dsr_bench.challenge.worker import run_worker

    layout, sessions, tokens, predictions = challenge
    with _serve(layout) as live:
        sid = _upload(live.url, tokens["alpha"], predictions, tmp_path).json()["id"]
    proc = subprocess.Popen([sys.executable, "-c", WORKER, str(layout.root), layout.default_db_url()],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "evaluating"
        with sessions() as session:
            assert session.get(Submission, sid).state == "running"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    time.sleep(1.2)  # its lease (1 s) expires
    assert run_worker(str(layout.root), layout.default_db_url(), once=True) == 1
    with sessions() as session:
        sub = session.get(Submission, sid)
        assert sub.state == "scored" and sub.attempts == 2
        assert session.scalar(select(func.count()).select_from(Score).where(Score.submission_id == sid)) == 2


def test_what_a_stopped_server_left_is_never_visible(challenge, tmp_path):
    layout, sessions, tokens, predictions = challenge
    layout.uploads.mkdir(exist_ok=True)
    layout.submissions.mkdir(exist_ok=True)
    (layout.uploads / ".part-deadbeef").write_bytes(b"half an upload")
    orphan = layout.submissions / ("ab" * 16 + ".tar")  # renamed, but the server died before its row
    orphan.write_bytes(b"x")
    with _serve(layout) as live:
        assert not list(layout.uploads.iterdir()) and not orphan.exists()
        assert get(f"{live.url}/api/submissions/{'ab' * 16}").status_code == 404
        sid = _upload(live.url, tokens["alpha"], predictions, tmp_path).json()["id"]
    with _serve(layout) as live:  # a restart keeps what was accepted
        assert get(f"{live.url}/api/submissions/{sid}").json()["state"] == "queued"
        assert layout.archive(sid).is_file()
