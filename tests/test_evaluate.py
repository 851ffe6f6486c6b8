"""`dsr-bench predict` and `dsr-bench evaluate`: exact oracle, pinned reference scores, strict checks."""

import json
import os
import shutil

import h5py
import numpy as np
import pytest

from dsr_bench.cli import main
from dsr_bench.errors import UserError
from dsr_bench.scoring.evaluate import evaluate
from dsr_bench.dataset.manifest import load_manifest, split_digest
from dsr_bench.scoring.predictions import write_predictions
from dsr_bench.testing import write_synthetic_dataset

#: static model on the generated fixture (tests/conftest.py): pinned, so a metric or generator
#: change shows up here and must be explained.
#: Re-pinned for dsr-bench 0.2 (the authors' policy, dynamics and scenes, corner sampling, official masks).
STATIC_PINNED = {"motion_visible": 49.231133778889976, "motion_full": 0.20987134084632317,
                 "iou_unordered": 0.15332702722922023, "iou_ordered": 0.15332702722922023}


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    return write_synthetic_dataset(tmp_path_factory.mktemp("ev") / "data", num_sequences=3, num_steps=2)


def _predict(model, data, out):
    assert main(["predict", "--model", model, "--data", str(data), "--out", str(out)]) == 0
    return out


def test_oracle_scores_exactly(generated_dataset, tmp_path):
    pred = _predict("oracle", generated_dataset, tmp_path / "oracle")
    assert main(["evaluate", str(pred), "--data", str(generated_dataset), "--out", str(tmp_path / "r.json")]) == 0
    results = json.loads((tmp_path / "r.json").read_text())
    m = results["metrics"]
    assert m["iou_unordered"] == 1.0 and m["iou_ordered"] == 1.0
    assert m["motion_visible"] == 0.0 and m["motion_full"] == 0.0 and m["motion_2d"] == 0.0
    assert results["split"] == "all" and results["coverage"] == {"scored": 2, "expected": 2, "partial": False}
    assert results["split_checksum"] == split_digest(load_manifest(generated_dataset), "all")
    assert results["pinned"] is False  # "all" is not one of the benchmark's named, pinned splits
    assert len(results["predictions_checksum"]) == 64 and results["meta"]["name"] == "oracle"
    assert len(results["per_step"]["iou_ordered"]) == 3


def test_static_scores_are_pinned(generated_dataset, tmp_path):
    pred = _predict("static", generated_dataset, tmp_path / "static")
    results = evaluate(pred, generated_dataset, workers=1).results
    for key, value in STATIC_PINNED.items():
        assert results["metrics"][key] == pytest.approx(value, rel=1e-6), key
    assert results["breakdowns"]["motion_static_objects"] < 1e-3 < results["breakdowns"]["motion_moved_objects"]


def test_push_yardstick_moves_every_object_voxel_along_the_push(generated_dataset, tmp_path):
    """`push`: the static masks, every voxel of them moved PUSH_YARDSTICK_DISTANCE along the action's direction
    (in voxels, components dy, dx, dz), zero elsewhere; in 2D the same vector (metres) at pixels above the table."""
    from dsr_bench.constants import VOXEL_SIZE
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.geometry import direction_vector
    from dsr_bench.models.predictors import PUSH_YARDSTICK_DISTANCE

    static = _predict("static", generated_dataset, tmp_path / "static")
    push = _predict("push", generated_dataset, tmp_path / "push")
    with SequenceReader(generated_dataset / "seq_0000.h5") as seq, h5py.File(push / "seq_0000.h5") as p, \
            h5py.File(static / "seq_0000.h5") as s:
        assert np.array_equal(p["mask"][()], s["mask"][()]) and not np.any(s["motion"][()])
        assert not np.any(s["motion_2d"][()])  # no motion in 2D either
        for t, (d, _, _) in enumerate(seq.read("action")):
            dx, dy = direction_vector(int(d)) * PUSH_YARDSTICK_DISTANCE / VOXEL_SIZE
            occupied = p["mask"][t] > 0
            motion = p["motion"][t].astype(np.float64)
            assert occupied.any() and not np.any(motion[:, ~occupied])
            assert np.allclose(motion[:, occupied].T, [dy, dx, 0.0], atol=0.02)  # float16
            moved_2d = np.abs(p["motion_2d"][t]).sum(-1) > 0
            above = np.nan_to_num(seq.read("cameras/front/points", t)[..., 2], nan=0.0) > 0.005
            assert np.array_equal(moved_2d, above) or (dx == 0 and dy == 0)


def test_parallel_and_serial_agree(synthetic, tmp_path):
    pred = _predict("static", synthetic, tmp_path / "s")
    a = evaluate(pred, synthetic, workers=1).results
    b = evaluate(pred, synthetic, workers=2).results
    assert a["metrics"] == b["metrics"] and a["per_step"] == b["per_step"]


def test_every_problem_reported_and_no_score(synthetic, tmp_path, capsys):
    pred = _predict("oracle", synthetic, tmp_path / "bad")
    (pred / "seq_0000.h5").unlink()  # missing
    shutil.copy(pred / "seq_0001.h5", pred / "seq_0042.h5")  # extra
    with h5py.File(pred / "seq_0001.h5", "r+") as f:  # NaN motion and an out-of-range slot
        f["motion"][0, 0, 0, 0, 0] = np.nan
        f["mask"][1, 0, 0, 0] = 200
    (pred / "meta.json").write_text("{not json")
    outside = tmp_path / "outside.h5"
    shutil.copy(pred / "seq_0002.h5", outside)
    (pred / "seq_0002.h5").unlink()
    os.symlink(outside, pred / "seq_0002.h5")  # escapes the directory
    assert main(["evaluate", str(pred), "--data", str(synthetic)]) == 1
    err = capsys.readouterr().err
    for text in ("seq_0000.h5: missing prediction file", "seq_0042.h5: extra file",
                 "seq_0001.h5: motion[0]: NaN or inf", "seq_0001.h5: mask: slot id 200", "meta.json: not valid JSON",
                 "seq_0002.h5: resolves outside the predictions directory", "no score"):
        assert text in err, text
    assert "mask IoU" not in err


def test_wrong_shapes_and_truncation_then_allow_partial(synthetic, tmp_path, capsys):
    pred = _predict("oracle", synthetic, tmp_path / "p")
    with h5py.File(pred / "seq_0000.h5", "r+") as f:
        motion = f["motion"][()]
        del f["motion"]
        f["motion"] = motion.astype(np.float64)
    raw = (pred / "seq_0001.h5").read_bytes()
    (pred / "seq_0001.h5").write_bytes(raw[: len(raw) // 3])
    evaluation = evaluate(pred, synthetic, workers=1)
    text = " ".join(f"{w}: {m}" for w, m in evaluation.problems)
    assert "motion: dtype float64" in text and "seq_0001.h5: unreadable" in text and evaluation.results is None
    assert main(["evaluate", str(pred), "--data", str(synthetic), "--allow-partial"]) == 0
    captured = capsys.readouterr()
    assert "scored 1 of 3 sequences" in captured.err and "mask IoU" in captured.out


def test_write_predictions_refuses_bad_arrays(tmp_path):
    mask = np.zeros((2, 128, 128, 48), np.uint8)
    with pytest.raises(UserError, match="motion must be"):
        write_predictions(tmp_path / "x.h5", mask, np.zeros((2, 3, 128, 128, 48), np.float64), 4)
    mask[0, 0, 0, 0] = 7
    with pytest.raises(UserError, match="slot 7 > num_slots 4"):
        write_predictions(tmp_path / "x.h5", mask, np.zeros((2, 3, 128, 128, 48), np.float16), 4)
    assert not list(tmp_path.iterdir())


def test_predict_errors(synthetic, tmp_path, capsys, monkeypatch):
    from dsr_bench.models import predictors

    # without shipped weights (an installation that lacks them), a learned model needs --checkpoint or --weights
    monkeypatch.setattr(predictors, "SHIPPED_WEIGHTS", tmp_path / "none")
    assert main(["predict", "--model", "gtwarp", "--data", str(synthetic), "--out", str(tmp_path / "o")]) == 2
    assert "--checkpoint" in capsys.readouterr().err and not (tmp_path / "o").exists()
    assert main(["predict", "--model", "magic", "--data", str(synthetic), "--out", str(tmp_path / "o")]) == 2
    assert "choose one of" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path / "none"), "--data", str(synthetic)]) == 2


def _error_line(capsys) -> str:
    """stderr of a command that failed with a user error: exactly one line `error: ...`."""
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err


def test_evaluate_infers_data_and_split_from_the_predictions_meta(synthetic, tmp_path, capsys, monkeypatch):
    """`predict` records the dataset (absolute) and split in meta.json; `evaluate PRED_DIR` without --data scores
    against them, saying on one line what it inferred; results carry the method's meta, not the machine's path."""
    monkeypatch.chdir(synthetic.parent)
    pred = _predict("static", synthetic.name, tmp_path / "s")  # a relative --data: recorded absolute
    meta = json.loads((pred / "meta.json").read_text())
    assert meta["data"] == str(synthetic.resolve()) and meta["split"] == "test" and meta["name"] == "static"
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert main(["evaluate", str(pred), "--out", "inferred.json"]) == 0
    err = capsys.readouterr().err
    assert f"data: {synthetic.resolve()}, split: test (from {pred / 'meta.json'})" in err.splitlines()
    assert "no results JSON" not in err
    before = sorted(tmp_path.rglob("*"))
    assert main(["evaluate", str(pred)]) == 0 and sorted(tmp_path.rglob("*")) == before  # no --out: says so
    assert capsys.readouterr().err.splitlines()[-1] == ("no results JSON or per-step plots written (no --out): add "
                                                        "--out results.json to write both (results.json and "
                                                        "results-steps.png)")
    assert main(["evaluate", str(pred), "--data", str(synthetic), "--split", "test", "--out", "given.json"]) == 0
    assert "(from " not in capsys.readouterr().err  # nothing inferred, nothing said
    inferred, given = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("inferred", "given"))
    assert inferred["metrics"] == given["metrics"] and inferred["split"] == "test"
    assert "data" not in inferred["meta"] and "split" not in inferred["meta"]


def test_evaluate_infers_the_split_of_the_named_dataset_only(tmp_path, capsys):
    """With two splits, --split would be needed; meta.json's split is taken when --data is the dataset it names."""
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=1)
    (data / "splits" / "first.txt").write_text("seq_0000\n")
    assert main(["manifest", str(data)]) == 0
    pred = tmp_path / "pred"
    assert main(["predict", "--model", "oracle", "--data", str(data), "--split", "first", "--out", str(pred)]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(pred), "--data", str(data), "--out", str(tmp_path / "r.json")]) == 0
    assert f"split: first (from {pred / 'meta.json'})" in capsys.readouterr().err.splitlines()
    assert json.loads((tmp_path / "r.json").read_text())["coverage"]["expected"] == 1
    other = tmp_path / "other"
    shutil.copytree(data, other)
    assert main(["evaluate", str(pred), "--data", str(other)]) == 2  # another dataset: its split is not inferred
    assert "choose one with --split" in _error_line(capsys)


def test_explicit_data_wins_over_meta(synthetic, tmp_path, capsys):
    """A given --data is used even when meta.json names another (moved) dataset and split; nothing is inferred."""
    pred = _predict("oracle", synthetic, tmp_path / "p")
    meta = json.loads((pred / "meta.json").read_text())
    (pred / "meta.json").write_text(json.dumps(dict(meta, data=str(tmp_path / "moved"), split="nope")))
    capsys.readouterr()
    assert main(["evaluate", str(pred), "--data", str(synthetic)]) == 0
    assert "(from " not in capsys.readouterr().err


@pytest.mark.parametrize("meta, message", [
    (None, "meta.json not found"),
    ({"name": "x"}, "meta.json names no dataset directory"),
    ({"name": "x", "data": ""}, "meta.json names no dataset directory"),
    ({"name": "x", "data": "/no/such/dataset"},
     "meta.json names the dataset directory '/no/such/dataset', which does not exist"),
    ("{not json", "meta.json: not valid JSON"),
])
def test_evaluate_without_data_fails_naming_the_missing_thing_and_the_fix(synthetic, tmp_path, capsys, meta, message):
    pred = _predict("oracle", synthetic, tmp_path / "p")
    if meta is None:
        (pred / "meta.json").unlink()
    else:
        (pred / "meta.json").write_text(meta if isinstance(meta, str) else json.dumps(meta))
    capsys.readouterr()
    assert main(["evaluate", str(pred)]) == 2
    err = _error_line(capsys)
    assert message in err and "--data DIR" in err, err


# -- a 2D-only submission (motion_2d alone): the 2D track of image-space models --

def _as_2d_only(src, dst, offset: float = 0.0):
    """Copy of a predictions directory with every file rewritten as motion_2d alone (+ `offset` metres in dx)."""
    shutil.copytree(src, dst)
    for path in sorted(dst.glob("*.h5")):
        with h5py.File(path, "r") as f:
            flow = f["motion_2d"][()].astype(np.float32)
        flow[..., 1] += offset
        path.unlink()
        write_predictions(path, motion_2d=flow)
    return dst


def test_write_predictions_2d_only_and_its_refusals(tmp_path):
    flow = np.zeros((2, 240, 320, 3), np.float16)
    path = write_predictions(tmp_path / "a.h5", motion_2d=flow, num_slots=4)  # num_slots: unused without mask
    with h5py.File(path, "r") as f:
        assert sorted(f) == ["motion_2d"] and "num_slots" not in f.attrs and f["motion_2d"].shape == flow.shape
    mask, motion = np.zeros((2, 128, 128, 48), np.uint8), np.zeros((2, 3, 128, 128, 48), np.float16)
    with h5py.File(write_predictions(tmp_path / "b.h5", mask, motion, 4, flow), "r") as f:  # positional, as before
        assert sorted(f) == ["mask", "motion", "motion_2d"] and f.attrs["num_slots"] == 4
    for kwargs, message in [({"mask": mask, "motion_2d": flow}, "mask without motion; mask and motion come together"),
                            ({"motion": motion, "num_slots": 4}, "motion without mask"),
                            ({}, "no arrays"),
                            ({"mask": mask, "motion": motion}, "num_slots is required with mask"),
                            ({"motion_2d": flow[..., :2]}, r"motion_2d must be \(T, 240, 320, 3\)"),
                            ({"mask": mask, "motion": motion, "num_slots": 4, "motion_2d": flow[:1]}, "T as in mask"),
                            ({"motion_2d": np.full((1, 240, 320, 3), np.nan, np.float32)}, "motion_2d has NaN")]:
        with pytest.raises(UserError, match=message):
            write_predictions(tmp_path / "x.h5", **kwargs)
    assert not (tmp_path / "x.h5").exists()


def test_2d_only_submission_is_scored_on_the_2d_flow_alone(synthetic, tmp_path, capsys):
    """motion_2d alone: the same 2D scores as the full submission it came from, nothing 3D in the results, the
    terminal table and the per-step plot; an offset of 1 cm in dx costs exactly 1 cm² on every object pixel."""
    from dsr_bench.scoring.plots import TWO_D_TITLE, step_series

    full = _predict("push", synthetic, tmp_path / "push")
    assert main(["evaluate", str(full), "--out", str(tmp_path / "full.json")]) == 0
    only = _as_2d_only(full, tmp_path / "only")
    capsys.readouterr()
    assert main(["evaluate", str(only), "--out", str(tmp_path / "only.json")]) == 0
    out = capsys.readouterr().out
    assert "2D flow MSE" in out and "2D-only" in out and "mask IoU" not in out and "motion_visible" not in out
    a, b = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("full", "only"))
    assert b["metrics"] == {"motion_2d": a["metrics"]["motion_2d"]} and a["metrics"]["motion_2d"] > 0
    assert b["per_step"] == {"motion_2d": a["per_step"]["motion_2d"]} and b["breakdowns"] == {}
    assert all(v == {"motion_2d": a["per_sequence"][k]["motion_2d"]} for k, v in b["per_sequence"].items())
    assert b["coverage"] == a["coverage"] and b["meta"]["name"] == "push"
    assert (tmp_path / "only-steps.png").stat().st_size > 0
    series, _ = step_series(b)
    assert [p["title"] for p in series["panels"]] == [TWO_D_TITLE] and series["objects"] is None
    oracle = _as_2d_only(_predict("oracle", synthetic, tmp_path / "oracle"), tmp_path / "o0")
    assert evaluate(oracle, synthetic, workers=1).results["metrics"] == {"motion_2d": 0.0}
    shifted = evaluate(_as_2d_only(tmp_path / "oracle", tmp_path / "o1", offset=0.01), synthetic, workers=1).results
    assert shifted["metrics"]["motion_2d"] == pytest.approx(1.0, rel=1e-5)


def test_mixed_3d_and_2d_only_submission_is_refused_naming_one_of_each(synthetic, tmp_path, capsys):
    from dsr_bench.scoring.evaluate import aggregate, score_sequence

    pred = _predict("oracle", synthetic, tmp_path / "p")
    with h5py.File(pred / "seq_0001.h5", "r") as f:
        flow = f["motion_2d"][()]
    (pred / "seq_0001.h5").unlink()
    write_predictions(pred / "seq_0001.h5", motion_2d=flow)
    for partial in ([], ["--allow-partial"]):
        assert main(["evaluate", str(pred), "--out", str(tmp_path / "r.json"), *partial]) == 1
        err = capsys.readouterr().err
        line = next(line for line in err.splitlines() if "mixed submission" in line)
        assert line.strip().startswith(f"{pred}: ") and "seq_0000.h5 holds mask and motion" in line
        assert "seq_0001.h5 holds motion_2d alone" in line and "no score" in err
    assert not (tmp_path / "r.json").exists()
    scored = {n: score_sequence((n, str(pred / f"{n}.h5"), str(synthetic / f"{n}.h5")))[2]
              for n in ("seq_0000", "seq_0001")}
    with pytest.raises(UserError, match="seq_0000.h5 holds mask and motion .* but seq_0001.h5 holds motion_2d alone"):
        aggregate(scored)


def test_2d_only_submission_needs_the_2d_ground_truth(synthetic, tmp_path, capsys):
    from dsr_bench.scoring.evaluate import score_sequence

    data = tmp_path / "data"
    shutil.copytree(synthetic, data)
    for path in data.glob("seq_*.h5"):
        with h5py.File(path, "r+") as f:
            del f["cameras/front/scene_flow_2d"]
    only = _as_2d_only(_predict("oracle", synthetic, tmp_path / "oracle"), tmp_path / "only")
    assert main(["evaluate", str(only), "--data", str(data)]) == 1
    err = capsys.readouterr().err
    assert f"seq_0000.h5: a 2D-only prediction (motion_2d without mask and motion), but its ground truth {data}" in err
    assert "has no cameras/front/scene_flow_2d" in err and "no score" in err
    _, problems, values = score_sequence(("seq_0000", str(only / "seq_0000.h5"), str(data / "seq_0000.h5")))
    assert values is None and "has no cameras/front/scene_flow_2d" in problems[0]
    full = _predict("oracle", synthetic, tmp_path / "full")  # a 3D submission is still scored there, without 2D
    results = evaluate(full, data, workers=1).results
    assert "motion_2d" not in results["metrics"] and results["metrics"]["iou_ordered"] == 1.0
