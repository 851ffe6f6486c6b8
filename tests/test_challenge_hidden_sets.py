"""A challenge's further hidden set of real annotated captures (`challenge add-hidden-set`) and the reference rows
the server scores on its hidden sets itself (`challenge add-references`): pinned, exported as inputs only, scored
separately, shown in their own tables; bad input refused in one line."""

import json
import shutil
import threading

import h5py
import pytest

pytest.importorskip("fastapi")
pytest.importorskip("httpx")
pytest.importorskip("argon2")

from challenge_helpers import DEADLINE, LiveServer, challenge_with_teams, get, post  # noqa: E402

from dsr_bench.cli import main  # noqa: E402


def write_annotated(folder, count: int, seed: int = 10, source: str = "annotated"):
    """`count` sequence files shaped like the annotator's exports (root attribute source "annotated", seed -1, an
    annotation record), named seq_0000.h5, ... like the simulated hidden set's (the names collide on purpose)."""
    from dsr_bench.dataset.digests import digest_attrs
    from dsr_bench.dataset.sequence import write_sequence
    from dsr_bench.testing import synthetic_arrays

    folder.mkdir(parents=True)
    for i in range(count):
        arrays, attrs, meshes = synthetic_arrays(num_steps=2, num_objects=2, seed=seed + i)
        attrs.update(sequence=f"seq_{i:04d}", source=source, policy="recorded", object_set="annotated",
                     generator_args={"annotator": 1, "capture": f"seq_{i:04d}"},
                     annotation={"capture": f"seq_{i:04d}", "status": [["confirmed"] * 2] * 3})
        if source == "annotated":
            attrs["seed"] = -1
        attrs.update(digest_attrs(arrays, attrs["objects"]))
        write_sequence(folder / f"seq_{i:04d}.h5", arrays, attrs, meshes)
    return folder


@pytest.fixture
def challenge(tmp_path, tmp_path_factory):
    yield from challenge_with_teams(tmp_path_factory, tmp_path)


def _serve(layout):
    from dsr_bench.challenge.server import Settings, create_app

    return LiveServer(create_app(layout.root, settings=Settings(keep_free=0, auth_max_delay=0.01, board_cache=0.0,
                                                                leaderboard=layout.root / "no-board")))


def _upload(url, token, predictions, tmp_path, method) -> str:
    from dsr_bench.challenge.client import pack

    archive = tmp_path / f"{method}.tar"
    pack(predictions, archive)
    reply = post(f"{url}/api/submissions", params={"method": method}, content=archive.read_bytes(),
                 headers={"Authorization": f"Bearer {token}"})
    assert reply.status_code == 202, reply.text
    return reply.json()["id"]


def _score_all(layout) -> int:
    from dsr_bench.challenge.worker import run_worker

    return run_worker(str(layout.root), layout.default_db_url(), once=True)


def test_a_real_hidden_set_is_pinned_exported_scored_apart_and_shown(challenge, tmp_path, capsys):
    from dsr_bench.challenge.worker import run_worker, wait_for

    layout, sessions, tokens, simulated_only = challenge
    stop = threading.Event()  # a worker running since before the set was added (it reads the new pins)
    worker = threading.Thread(target=run_worker, args=(str(layout.root), layout.default_db_url()),
                              kwargs={"stop": stop, "poll": 0.1}, daemon=True)
    worker.start()
    try:
        _with_a_running_worker(layout, sessions, tokens, simulated_only, tmp_path, capsys, wait_for)
    finally:
        stop.set()
        worker.join(DEADLINE)


def _with_a_running_worker(layout, sessions, tokens, simulated_only, tmp_path, capsys, wait_for):
    from dsr_bench.challenge.layout import open_challenge, write_config
    from dsr_bench.dataset.manifest import file_sha256
    from dsr_bench.models.predictors import load_predictor, predict_split
    from dsr_bench.scoring.evaluate import evaluate

    real = write_annotated(tmp_path / "real", 2)
    assert main(["challenge", "add-hidden-set", str(layout.root), str(real)]) == 0
    assert "hidden set 'real' added: 2 annotated sequences (1 public, 1 private)" in capsys.readouterr().out
    config = open_challenge(layout.root)[1]
    entry = config["hidden_sets"]["real"]
    assert entry["sequences"] == ["seq_real_0000", "seq_real_0001"]
    assert len(entry["public"]) == len(entry["private"]) == 1
    pins = json.loads(layout.pins.read_text())["sequences"]
    for i, name in enumerate(entry["sequences"]):  # pinned: the copy is the file given, byte for byte
        assert pins[name]["sha256"] == file_sha256(real / f"seq_{i:04d}.h5") == file_sha256(
            layout.root / "hidden-real" / f"{name}.h5")
        assert pins[name]["scored"]

    # the inputs hold the real captures beside the simulated sequences: observations and actions only
    names = (layout.inputs / "splits" / "challenge.txt").read_text().split()
    assert names == ["seq_0000", "seq_0001", "seq_real_0000", "seq_real_0001"]
    assert set(json.loads((layout.inputs / "digests.json").read_text())) == {f"{n}.h5" for n in names}
    out = tmp_path / "exported"
    assert main(["challenge", "export-inputs", str(layout.root), str(out)]) == 0
    for folder in (layout.inputs, out):
        with h5py.File(folder / "seq_real_0001.h5") as f:
            arrays = set()
            f.visit(lambda n, arrays=arrays: arrays.add(n) if isinstance(f[n], h5py.Dataset) else None)
            assert arrays == {"tsdf", "action", "cameras/front/color", "cameras/front/depth"}
            assert f.attrs["source"] == "challenge-inputs" and f.attrs["sequence"] == "seq_real_0001"
            assert "annotation" not in f.attrs and f.attrs["seed"] == 0

    # a submission with predictions of both sets is scored on each apart; one of the simulated set only, on it
    both = tmp_path / "both"
    predict_split(load_predictor("static"), layout.inputs, names, both)
    partial = tmp_path / "partial"
    predict_split(load_predictor("static"), layout.inputs, names[:3], partial)
    with _serve(layout) as live:
        sid = _upload(live.url, tokens["alpha"], both, tmp_path, "both sets")
        sim = _upload(live.url, tokens["beta"], simulated_only, tmp_path, "simulated only")
        half = _upload(live.url, tokens["beta"], partial, tmp_path, "half the real set")
        assert [wait_for(sessions, s, timeout=DEADLINE) for s in (sid, sim, half)] == ["scored", "scored", "refused"]
        status = get(f"{live.url}/api/submissions/{sid}").json()
        assert status["state"] == "scored" and set(status["scores"]) == {"public", "real-public"}
        assert get(f"{live.url}/api/submissions/{sim}").json()["state"] == "scored"
        refused = get(f"{live.url}/api/submissions/{half}").json()
        assert refused["state"] == "refused" and "seq_real_0001.h5: missing prediction file" in refused["messages"]
        for part in ("public", "private"):  # the numbers are evaluate's on that part of the real set
            direct = tmp_path / f"direct-{part}"
            direct.mkdir()
            for n in entry[part]:
                shutil.copy(both / f"{n}.h5", direct)
            shutil.copy(both / "meta.json", direct)
            expected = evaluate(direct, layout.root / "hidden-real", part, workers=1).results["metrics"]
            if part == "public":
                assert status["scores"]["real-public"]["metrics"] == pytest.approx(expected)
        board = get(f"{live.url}/api/leaderboard").json()
        assert sorted(r["method"] for r in board["tracks"]["3D"]) == ["both sets", "simulated only"]
        assert [r["id"] for r in board["hidden_sets"]["real"]["tracks"]["3D"]] == [sid]
        page = get(live.url + "/").text
        assert "3D track, hidden set real (annotated sequences) (public part)" in page
        assert "hidden set real, public part" in get(f"{live.url}/submissions/{sid}").text

        write_config(layout, {**open_challenge(layout.root)[1], "reveal_private": True})
        board = get(f"{live.url}/api/leaderboard").json()
        assert [r["id"] for r in board["hidden_sets"]["real"]["final"]["3D"]] == [sid]
        assert board["hidden_sets"]["real"]["final"]["3D"][0]["metrics"] == pytest.approx(expected)
        assert "Final ranking, 3D track, hidden set real" in get(live.url + "/").text

        # the server's reference rows are scored on the real set too
        assert main(["challenge", "add-references", str(layout.root)]) == 0
        reference = capsys.readouterr().out.split("queued as submission ")[1].split()[0]
        assert wait_for(sessions, reference, timeout=DEADLINE) == "scored"
        references = get(f"{live.url}/api/leaderboard").json()["hidden_references"]
        assert [r["method"] for r in references["real"]["public"]["3D"]] == ["static"]
        assert references["real"]["private"]["3D"][0]["metrics"] == pytest.approx(expected)  # the same predictor


def test_adding_a_hidden_set_refuses_bad_input(challenge, tmp_path, capsys):
    from dsr_bench.challenge.layout import open_challenge

    layout, *_ = challenge
    root = str(layout.root)
    cases = [
        (["add-hidden-set", root, str(tmp_path / "missing")], "is not a directory"),
        (["add-hidden-set", root, str(write_annotated(tmp_path / "sim", 2, source="synthetic"))],
         "not an annotated export (its source is 'synthetic'"),
        (["add-hidden-set", root, str(write_annotated(tmp_path / "one", 1))], "holds 1 sequence file(s)"),
        (["add-hidden-set", root, str(tmp_path / "sim"), "--name", "Real!"], "--name 'Real!'"),
        (["add-hidden-set", root, str(tmp_path / "sim"), "--name", "simulated"], "--name 'simulated'"),
    ]
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "a.h5").write_bytes(b"not hdf5")
    (tmp_path / "junk" / "b.h5").write_bytes(b"not hdf5")
    cases.append((["add-hidden-set", root, str(tmp_path / "junk")], "not a sequence file"))
    for args, message in cases:
        assert main(["challenge", *args]) == 2, args
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, (args, err)
    assert "hidden_sets" not in open_challenge(layout.root)[1]  # nothing was added
    real = write_annotated(tmp_path / "real", 2)
    assert main(["challenge", "add-hidden-set", root, str(real)]) == 0
    capsys.readouterr()
    assert main(["challenge", "add-hidden-set", root, str(real)]) == 2
    assert "hidden set 'real' is already in" in capsys.readouterr().err
    assert main(["challenge", "add-hidden-set", root, str(real), "--name", "again"]) == 2
    assert "is already hidden in this challenge (as seq_real_0000)" in capsys.readouterr().err
    assert not list(layout.root.glob(".hidden-*")) and not list(layout.root.glob(".inputs.*"))


def test_reference_rows_are_scored_by_the_server_on_the_hidden_set(challenge, tmp_path, capsys):
    from dsr_bench.challenge.layout import open_challenge, write_config

    layout, sessions, tokens, predictions = challenge
    root = str(layout.root)
    # static and push, a learned 3D model and a 2D-track model with their shipped CPU-track weights (~3 s here)
    assert main(["challenge", "add-references", root, "--models", "static,push,dsr,2dflow"]) == 0
    out = capsys.readouterr().out
    assert all(f"{m}: queued as submission" in out for m in ("static", "push", "dsr", "2dflow"))
    with _serve(layout) as live:
        mine = _upload(live.url, tokens["alpha"], predictions, tmp_path, "static")  # the same predictor, submitted
        assert _score_all(layout) == 5
        board = get(f"{live.url}/api/leaderboard").json()
        assert [r["id"] for r in board["tracks"]["3D"]] == [mine]  # reference rows are not ranked submissions
        references = board["hidden_references"]["simulated"]
        assert set(references) == {"public"}  # the private part's only once revealed
        rows = {r["method"]: r for r in references["public"]["3D"]}
        assert set(rows) == {"static", "push", "dsr"}
        assert [r["method"] for r in references["public"]["2D"]] == ["2dflow"]  # its own track's table
        assert rows["dsr"]["metrics"] != pytest.approx(rows["static"]["metrics"])  # the model's own predictions
        submitted = get(f"{live.url}/api/submissions/{mine}").json()["scores"]["public"]["metrics"]
        assert rows["static"]["metrics"] == pytest.approx(submitted)  # scored by the same workers, the same way
        assert rows["push"]["metrics"]["motion_full"] != pytest.approx(rows["static"]["metrics"]["motion_full"])
        page = get(live.url + "/").text
        assert f'<a href="/submissions/{rows["static"]["id"]}">static</a>' in page
        assert "reference, scored by this server on the hidden set" in page
        assert "2D track (public part)" in page and ">2dflow</a>" in page
        assert get(f"{live.url}/teams/%28reference%20rows%29").status_code == 404

        write_config(layout, {**open_challenge(layout.root)[1], "reveal_private": True})
        board = get(f"{live.url}/api/leaderboard").json()
        assert [r["id"] for r in board["final"]["3D"]] == [mine]
        private = {r["method"]: r for r in board["hidden_references"]["simulated"]["private"]["3D"]}
        mine_private = get(f"{live.url}/api/submissions/{mine}").json()["scores"]["private"]["metrics"]
        assert private["static"]["metrics"] == pytest.approx(mine_private)

    for models, message in (("oracle", "reads the ground truth"), ("nope", "not a model"), (",", "is empty")):
        assert main(["challenge", "add-references", root, "--models", models]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err


def test_a_team_named_like_the_reference_team_is_refused(challenge, capsys):
    from dsr_bench.challenge.references import REFERENCE_TEAM
    from dsr_bench.challenge.service import add_team

    layout, sessions, *_ = challenge
    add_team(sessions, REFERENCE_TEAM)
    assert main(["challenge", "add-references", str(layout.root)]) == 2
    assert f"a team named {REFERENCE_TEAM!r} exists" in capsys.readouterr().err
    assert not layout.submissions.exists() or not list(layout.submissions.glob("*.tar"))
