"""A corpus of malformed submissions: `dsr-bench evaluate` refuses each with one line naming the
file and the problem, exits non-zero and writes no results; none can borrow the ground truth's
score, hang or crash it. Each case starts from a valid oracle submission and breaks one thing."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from dsr_bench.cli import main
from dsr_bench.scoring.evaluate import pin_warning
from dsr_bench.dataset.manifest import load_manifest, split_digest
from dsr_bench.dataset.splits import SPLITS, Split
from dsr_bench.models.predictors import MODEL_NAMES
from dsr_bench.testing import write_synthetic_dataset
from helpers import pin_split

TARGET = "seq_0000.h5"


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("malformed") / "data", num_sequences=2, num_steps=2)


@pytest.fixture(scope="module")
def oracle(data, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("oracle") / "pred"
    assert main(["predict", "--model", "oracle", "--data", str(data), "--out", str(out)]) == 0
    return out


@pytest.fixture
def pred(oracle, tmp_path) -> Path:
    """A fresh copy of the valid oracle submission, to break."""
    return Path(shutil.copytree(oracle, tmp_path / "pred"))


def _evaluate(pred: Path, data: Path, capsys) -> tuple[int, str]:
    out = pred.parent / "results.json"
    rc = main(["evaluate", str(pred), "--data", str(data), "--out", str(out), "--workers", "1"])
    err = capsys.readouterr().err
    assert not out.exists(), "a refused submission wrote results"
    return rc, err


def _refused(pred: Path, data: Path, capsys, file: str, *texts: str) -> str:
    """Evaluate, and check: non-zero exit, no results, each text on one line naming `file`."""
    rc, err = _evaluate(pred, data, capsys)
    assert rc != 0, err
    for text in texts:
        assert any(f"{file}:" in line and text in line for line in err.splitlines()), f"{file}: {text!r} not in\n{err}"
    assert "no score" in err and "Traceback" not in err
    return err


def _arrays(path: Path) -> dict:
    with h5py.File(path, "r") as f:
        return {"mask": f["mask"][()], "motion": f["motion"][()], "num_slots": f.attrs["num_slots"]}


def _outside_copy(pred: Path) -> Path:
    """The valid prediction for TARGET, moved next to (outside) the predictions directory."""
    outside = pred.parent / "borrowed.h5"
    shutil.copy(pred / TARGET, outside)
    return outside


def _rewrite(path: Path, build) -> None:
    """Replace `path` by a fresh file holding the valid root attributes (num_slots, the sequence and layout it
    states) and what `build(f, arrays)` writes."""
    arrays = _arrays(path)
    with h5py.File(path, "r") as f:
        attrs = dict(f.attrs)
    path.unlink()
    with h5py.File(path, "w") as f:
        f.attrs.update(attrs)
        build(f, arrays)


# -- cases handled before: missing, extra, shapes, dtypes, data, damaged files, escaping symlinks --

def test_missing_file(pred, data, capsys):
    (pred / TARGET).unlink()
    _refused(pred, data, capsys, TARGET, "missing prediction file")


def test_extra_file(pred, data, capsys):
    shutil.copy(pred / TARGET, pred / "seq_0042.h5")
    _refused(pred, data, capsys, "seq_0042.h5", "extra file")


def test_wrong_shape(pred, data, capsys):
    _rewrite(pred / TARGET, lambda f, a: (f.create_dataset("mask", data=a["mask"][..., :47]),
                                          f.create_dataset("motion", data=a["motion"])))
    _refused(pred, data, capsys, TARGET, "mask: shape (2, 128, 128, 47), expected (2, 128, 128, 48)")


def test_wrong_dtype(pred, data, capsys):
    _rewrite(pred / TARGET, lambda f, a: (f.create_dataset("mask", data=a["mask"]),
                                          f.create_dataset("motion", data=a["motion"].astype(np.float64))))
    _refused(pred, data, capsys, TARGET, "motion: dtype float64")


def test_huge_declared_shape_is_refused_before_reading(pred, data, capsys):
    # 786 GB declared, nothing written: reading it would exhaust memory
    _rewrite(pred / TARGET, lambda f, a: (f.create_dataset("mask", shape=(10**6, 128, 128, 48), dtype=np.uint8,
                                                           chunks=(1, 128, 128, 48)),
                                          f.create_dataset("motion", data=a["motion"])))
    _refused(pred, data, capsys, TARGET, "mask: shape (1000000, 128, 128, 48)")


def test_nan_motion(pred, data, capsys):
    with h5py.File(pred / TARGET, "r+") as f:
        f["motion"][1, 2, 3, 4, 5] = np.inf
    _refused(pred, data, capsys, TARGET, "motion[1]: NaN or inf")


def test_slot_above_num_slots(pred, data, capsys):
    with h5py.File(pred / TARGET, "r+") as f:
        f["mask"][0, 0, 0, 0] = 200
    _refused(pred, data, capsys, TARGET, "slot id 200 > num_slots")


def test_truncated_file(pred, data, capsys):
    raw = (pred / TARGET).read_bytes()
    (pred / TARGET).write_bytes(raw[: len(raw) // 3])
    _refused(pred, data, capsys, TARGET, "unreadable")


def test_garbage_file(pred, data, capsys):
    (pred / TARGET).write_bytes(np.random.default_rng(0).bytes(4096))
    _refused(pred, data, capsys, TARGET, "unreadable HDF5 file")


def test_symlink_escaping_the_directory(pred, data, capsys):
    outside = _outside_copy(pred)
    (pred / TARGET).unlink()
    os.symlink(outside, pred / TARGET)
    _refused(pred, data, capsys, TARGET, "resolves outside the predictions directory")


def test_dangling_symlink(pred, data, capsys):
    (pred / TARGET).unlink()
    os.symlink("nowhere.h5", pred / TARGET)
    _refused(pred, data, capsys, TARGET, "dangling")


@pytest.mark.parametrize("file", [TARGET, "meta.json"])
def test_symlink_to_a_sibling_is_refused(pred, data, capsys, file):
    """seq_0001.h5 -> seq_0000.h5 would submit one sequence's predictions for two: a predictions directory holds
    regular files only, wherever a link leads."""
    sibling = "seq_0001.h5" if file == TARGET else "meta-kept.json"
    if file == TARGET:
        (pred / TARGET).unlink()
    else:
        (pred / file).rename(pred / sibling)
    os.symlink(sibling, pred / file)
    _refused(pred, data, capsys, file, f"is a symlink to '{sibling}' in the predictions directory",
             "regular files only: copy the file in place of the link")


# -- links and storage outside the file: a borrowed ground truth must not score --

@pytest.mark.parametrize("absolute", [False, True], ids=["relative", "absolute"])
def test_external_links(pred, data, capsys, absolute):
    outside = _outside_copy(pred)
    target = str(outside) if absolute else f"../{outside.name}"
    _rewrite(pred / TARGET, lambda f, a: (f.__setitem__("mask", h5py.ExternalLink(target, "/mask")),
                                          f.__setitem__("motion", h5py.ExternalLink(target, "/motion"))))
    _refused(pred, data, capsys, TARGET, "'mask' is an external link to", "'motion' is an external link to",
             outside.name)


def test_soft_link(pred, data, capsys):
    def build(f, a):
        f.create_dataset("motion", data=a["motion"])
        f.create_dataset("stash", data=a["mask"])
        f["mask"] = h5py.SoftLink("/stash")
    _rewrite(pred / TARGET, build)
    _refused(pred, data, capsys, TARGET, "'mask' is a soft link to '/stash'", "unexpected root member(s) 'stash'")


def test_hard_link_twice(pred, data, capsys):
    with h5py.File(pred / TARGET, "r+") as f:
        f["mask_again"] = f["mask"]
    _refused(pred, data, capsys, TARGET, "'mask' is linked 2 times", "unexpected root member(s) 'mask_again'")


@pytest.mark.parametrize("missing", [False, True], ids=["source", "missing-source"])
def test_virtual_dataset(pred, data, capsys, missing):
    outside = _outside_copy(pred)
    source = str(outside.with_name("gone.h5") if missing else outside)

    def build(f, a):
        layout = h5py.VirtualLayout(shape=a["mask"].shape, dtype=np.uint8)
        layout[...] = h5py.VirtualSource(source, "mask", shape=a["mask"].shape)
        f.create_virtual_dataset("mask", layout, fillvalue=0)
        f.create_dataset("motion", data=a["motion"])
    _rewrite(pred / TARGET, build)
    _refused(pred, data, capsys, TARGET, "mask: a virtual dataset", Path(source).name)


def test_external_raw_storage(pred, data, capsys):
    raw = pred.parent / "motion.raw"

    def build(f, a):
        a["motion"].tofile(raw)
        f.create_dataset("mask", data=a["mask"])
        f.create_dataset("motion", shape=a["motion"].shape, dtype=a["motion"].dtype,
                         external=[(str(raw), 0, a["motion"].nbytes)])
    _rewrite(pred / TARGET, build)
    _refused(pred, data, capsys, TARGET, "motion: stored in external raw file", "motion.raw")


def test_filter_needing_a_plugin(pred, data, capsys):
    """An optional, unregistered filter (HDF5 skips it when writing): refused all the same."""
    def build(f, a):
        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        dcpl.set_chunk((1, 128, 128, 48))
        dcpl.set_filter(32123, h5py.h5z.FLAG_OPTIONAL, ())
        space = h5py.h5s.create_simple(a["mask"].shape)
        h5py.Dataset(h5py.h5d.create(f.id, b"mask", h5py.h5t.NATIVE_UINT8, space, dcpl=dcpl))[...] = a["mask"]
        f.create_dataset("motion", data=a["motion"])
    _rewrite(pred / TARGET, build)
    _refused(pred, data, capsys, TARGET, "mask: compressed with HDF5 filter 32123", "needs a plugin")


def test_mandatory_unknown_filter(pred, data, capsys):
    """lzf relabelled as filter 32123 in the file's bytes: HDF5 cannot decode it; one line, no traceback."""
    _rewrite(pred / TARGET, lambda f, a: (f.create_dataset("mask", data=a["mask"], compression="lzf"),
                                          f.create_dataset("motion", data=a["motion"])))
    raw = bytearray((pred / TARGET).read_bytes())
    at = raw.find(b"lzf\x00")
    assert raw[at - 8: at - 4] == b"\x00\x7d\x08\x00"  # filter id 32000 (lzf), name length 8
    raw[at - 8: at - 6], raw[at: at + 3] = (32123).to_bytes(2, "little"), b"xyz"
    (pred / TARGET).write_bytes(bytes(raw))
    _refused(pred, data, capsys, TARGET, "mask: compressed with HDF5 filter 32123 ('xyz')")


@pytest.mark.parametrize("kind", ["dataset", "group"])
def test_extra_root_member(pred, data, capsys, kind):
    with h5py.File(pred / TARGET, "r+") as f:
        if kind == "group":
            f.create_group("extra").create_dataset("mask", data=np.zeros(3))
        else:
            f["extra"] = np.zeros(3)
    _refused(pred, data, capsys, TARGET, "unexpected root member(s) 'extra'")


def test_group_in_place_of_a_dataset(pred, data, capsys):
    _rewrite(pred / TARGET, lambda f, a: (f.create_group("mask").create_dataset("data", data=a["mask"]),
                                          f.create_dataset("motion", data=a["motion"])))
    _refused(pred, data, capsys, TARGET, "'mask' is a group, expected a dataset")


# -- files that are not regular files: never opened, never hang --

def test_directory_named_like_a_prediction(pred, data, capsys):
    (pred / TARGET).unlink()
    (pred / TARGET).mkdir()
    _refused(pred, data, capsys, TARGET, "is a directory, not a regular file")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
def test_fifos_never_hang(pred, data):
    """A FIFO opened for reading blocks forever: run the CLI in a subprocess so a regression fails."""
    (pred / TARGET).unlink()
    os.mkfifo(pred / TARGET)
    (pred / "meta.json").unlink()
    os.mkfifo(pred / "meta.json")
    out = pred.parent / "results.json"
    done = subprocess.run([sys.executable, "-m", "dsr_bench.cli", "evaluate", str(pred), "--data", str(data),
                           "--out", str(out), "--workers", "1"], check=False, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 1 and not out.exists()
    lines = done.stderr.splitlines()
    for file in (TARGET, "meta.json"):
        fifo = "is a FIFO (named pipe), not a regular file"
        assert any(f"{file}:" in line and fifo in line for line in lines), done.stderr


# -- num_slots: a scalar integer in 1..254 --

@pytest.mark.parametrize("value, text", [
    ("4", "got a string"), (np.array([4, 4]), "got an array of shape (2,)"), (4.7, "got the float 4.7"),
    (4.0, "got the float 4.0"), (True, "got a boolean"), (0, "got 0"), (255, "got 255"), (None, "it is missing"),
], ids=["string", "array", "4.7", "4.0", "bool", "0", "255", "missing"])
def test_num_slots(pred, data, capsys, value, text):
    with h5py.File(pred / TARGET, "r+") as f:
        del f.attrs["num_slots"]
        if value is not None:
            f.attrs["num_slots"] = value
    _refused(pred, data, capsys, TARGET, f"attribute num_slots must be a scalar integer in 1..254, {text}")


def test_num_slots_of_any_integer_type_is_accepted(pred, data, tmp_path):
    with h5py.File(pred / TARGET, "r+") as f:
        f.attrs["num_slots"] = np.uint8(f.attrs["num_slots"])
    out = tmp_path / "results.json"
    assert main(["evaluate", str(pred), "--data", str(data), "--out", str(out), "--workers", "1"]) == 0


# -- meta.json: a regular file, at most 1 MiB, a JSON object whose known keys have their types --

def test_meta_directory(pred, data, capsys):
    (pred / "meta.json").unlink()
    (pred / "meta.json").mkdir()
    _refused(pred, data, capsys, "meta.json", "is a directory, not a regular file")


@pytest.mark.parametrize("text, problem", [
    ("[1, 2]", "must hold a JSON object, not list"),
    ("{not json", "not valid JSON"),
    ("[" * 100_000 + "]" * 100_000, "not valid JSON"),
    (json.dumps({"name": "x", "padding": "x" * (1 << 20)}), "more than the 1048576 allowed"),
], ids=["list", "syntax", "deep", "huge"])
def test_meta_not_an_object(pred, data, capsys, text, problem):
    (pred / "meta.json").write_text(text)
    _refused(pred, data, capsys, "meta.json", problem)


def test_meta_wrong_key_types(pred, data, capsys):
    (pred / "meta.json").write_text(json.dumps({"name": 3, "description": ["a"], "code_url": None, "hardware": {},
                                                "parameters": [1], "seconds_per_step": "fast"}))
    _refused(pred, data, capsys, "meta.json", "'name' must be a string, got int", "'description' must be a string",
             "'code_url' must be a string", "'hardware' must be a string", "'parameters' must be an object, got list",
             "'seconds_per_step' must be a number, got str")
    (pred / "meta.json").write_text(json.dumps({"seconds_per_step": True}))
    _refused(pred, data, capsys, "meta.json", "'seconds_per_step' must be a number, got bool")


def test_meta_symlink_escaping(pred, data, capsys):
    outside = pred.parent / "meta_outside.json"
    (pred / "meta.json").rename(outside)
    os.symlink(outside, pred / "meta.json")
    _refused(pred, data, capsys, "meta.json", "resolves outside the predictions directory")


def test_every_file_is_reported_at_once(pred, data, capsys):
    with h5py.File(pred / TARGET, "r+") as f:
        f.attrs["num_slots"] = "4"
    with h5py.File(pred / "seq_0001.h5", "r+") as f:
        f["extra"] = np.zeros(3)
    (pred / "meta.json").write_text("[]")
    err = _refused(pred, data, capsys, TARGET, "num_slots")
    assert "seq_0001.h5: unexpected root member(s) 'extra'" in err and "meta.json: must hold a JSON object" in err
    assert "3 problems in" in err


# -- the split's pin: scored, with one warning line --

@pytest.fixture(scope="module")
def pinned_data(tmp_path_factory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("pinned") / "data", num_sequences=1, num_steps=2,
                                   split="procedural-novel-mini")


def _pin(monkeypatch, digest):
    spec = SPLITS["procedural-novel-mini"]
    # "": not pinned
    monkeypatch.setitem(SPLITS, spec.name, Split(**{**spec.__dict__, "pinned_checksum": digest or ""}))


def test_pin_mismatch_warns_once_and_still_scores(pinned_data, tmp_path, monkeypatch, capsys):
    _pin(monkeypatch, "c" * 64)
    pred = tmp_path / "pred"
    assert main(["predict", "--model", "oracle", "--data", str(pinned_data), "--out", str(pred)]) == 0
    out = tmp_path / "results.json"
    capsys.readouterr()
    assert main(["evaluate", str(pred), "--data", str(pinned_data), "--out", str(out), "--workers", "1"]) == 0
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "warning" not in err.replace(warnings[0], ""), err
    for text in (str(pinned_data), "'procedural-novel-mini'", "cccccccccccc", "not this toolkit's pin",
                 "dsr-bench generate --split procedural-novel-mini", f"dsr-bench validate {pinned_data}"):
        assert text in warnings[0], text
    results = json.loads(out.read_text())
    assert results["pinned"] is False and results["metrics"]["iou_ordered"] == 1.0


def test_pin_match_and_unpinned_splits(pinned_data, data, monkeypatch):
    manifest = load_manifest(pinned_data)
    actual = split_digest(manifest, "procedural-novel-mini")
    _pin(monkeypatch, actual)
    assert pin_warning(manifest, "procedural-novel-mini") is None
    _pin(monkeypatch, None)
    assert pin_warning(manifest, "procedural-novel-mini") is None
    _pin(monkeypatch, "0" * 64)
    assert "not this toolkit's pin 000000000000" in pin_warning(manifest, "procedural-novel-mini")
    assert pin_warning(load_manifest(data), "test") is None  # not a named split


def test_results_record_whether_pinned(pinned_data, tmp_path, monkeypatch, capsys):
    from dsr_bench.scoring.evaluate import evaluate

    pred = tmp_path / "pred"
    assert main(["predict", "--model", "oracle", "--data", str(pinned_data), "--out", str(pred)]) == 0
    pin_split(monkeypatch, pinned_data, "procedural-novel-mini")  # the checksum and the scored digests
    evaluation = evaluate(pred, pinned_data, workers=1)
    assert evaluation.results["pinned"] is True and evaluation.warnings == []
    monkeypatch.undo()
    _pin(monkeypatch, split_digest(load_manifest(pinned_data), "procedural-novel-mini"))  # a checksum alone
    evaluation = evaluate(pred, pinned_data, workers=1)
    assert evaluation.results["pinned"] is False and "cannot be verified" in evaluation.warnings[0]
    _pin(monkeypatch, None)
    assert evaluate(pred, pinned_data, workers=1).results["pinned"] is False


# -- 2D-only submissions (motion_2d alone): mask and motion come together, the same integrity checks --

@pytest.mark.parametrize("keep", ["mask", "motion"])
def test_mask_and_motion_come_together(pred, data, capsys, keep):
    other = "motion" if keep == "mask" else "mask"
    _rewrite(pred / TARGET, lambda f, a: f.create_dataset(keep, data=a[keep]))
    _refused(pred, data, capsys, TARGET, f"'{keep}' without '{other}': mask and motion come together")


def test_no_dataset_at_all(pred, data, capsys):
    _rewrite(pred / TARGET, lambda f, a: None)
    _refused(pred, data, capsys, TARGET, "missing datasets: 'mask' and 'motion' (3D), or 'motion_2d' alone (2D-only)")


def _only_2d(pred: Path, build) -> None:
    """Every file of `pred` rewritten as a valid 2D-only prediction (the sequence and flow components it states
    kept), TARGET by `build(f, motion_2d)` instead."""
    for path in sorted(pred.glob("*.h5")):
        with h5py.File(path, "r") as f:
            flow = f["motion_2d"][()]
            attrs = {k: f.attrs[k] for k in ("sequence", "flow_components") if k in f.attrs}
        path.unlink()
        with h5py.File(path, "w") as f:
            f.attrs.update(attrs)
            (build if path.name == TARGET else lambda f, m: f.create_dataset("motion_2d", data=m))(f, flow)


def test_2d_only_submission_passes_the_same_checks(pred, data, capsys, tmp_path):
    _only_2d(pred, lambda f, m: f.create_dataset("motion_2d", data=m))
    out = tmp_path / "ok.json"
    assert main(["evaluate", str(pred), "--data", str(data), "--out", str(out), "--workers", "1"]) == 0
    assert json.loads(out.read_text())["metrics"] == {"motion_2d": 0.0}


@pytest.mark.parametrize("case, texts", [
    ("shape", ("motion_2d: shape (2, 240, 320, 2), expected (2, 240, 320, 3)",)),
    ("dtype", ("motion_2d: dtype float64",)),
    ("nan", ("motion_2d[1]: NaN or inf",)),
    ("num_slots", ("attribute num_slots must be a scalar integer in 1..254, got 0",)),
    ("extra", ("unexpected root member(s) 'extra'",)),
    ("soft-link", ("'motion_2d' is a soft link",)),
])
def test_malformed_2d_only_file(pred, data, capsys, case, texts):
    def build(f, m):
        if case == "shape":
            f.create_dataset("motion_2d", data=m[..., :2])
        elif case == "dtype":
            f.create_dataset("motion_2d", data=m.astype(np.float64))
        elif case == "nan":
            m = m.copy()
            m[1, 5, 5, 0] = np.nan
            f.create_dataset("motion_2d", data=m)
        elif case == "soft-link":
            f.create_dataset("flow", data=m)
            f["motion_2d"] = h5py.SoftLink("/flow")
        else:
            f.create_dataset("motion_2d", data=m)
            if case == "num_slots":  # not needed without mask, but checked when present
                f.attrs["num_slots"] = 0
            else:
                f["extra"] = np.zeros(3)
    _only_2d(pred, build)
    _refused(pred, data, capsys, TARGET, *texts)


def test_2d_only_file_cannot_borrow_the_ground_truth_through_a_virtual_dataset(pred, data, capsys):
    """motion_2d read from the sequence's own cameras/front/scene_flow_2d would score 0: refused before reading."""
    source = str(data / TARGET)

    def build(f, m):
        layout = h5py.VirtualLayout(shape=m.shape, dtype=np.float32)
        layout[...] = h5py.VirtualSource(source, "cameras/front/scene_flow_2d", shape=m.shape)
        f.create_virtual_dataset("motion_2d", layout, fillvalue=0)
    _only_2d(pred, build)
    _refused(pred, data, capsys, TARGET, "motion_2d: a virtual dataset", TARGET)


# -- forged folders: another sequence's file, extra entries, y and x swapped (issue 41) --

@pytest.mark.parametrize("how", ["copy", "hard-link"])
def test_another_sequences_predictions_under_this_ones_name(pred, data, capsys, how):
    """seq_0001.h5 holding seq_0000's predictions, byte for byte: the file states the sequence it predicts."""
    (pred / "seq_0001.h5").unlink()
    (shutil.copyfile if how == "copy" else os.link)(pred / TARGET, pred / "seq_0001.h5")
    _refused(pred, data, capsys, "seq_0001.h5", "attribute sequence is 'seq_0000', but the file is seq_0001.h5",
             "another sequence's predictions under this one's name")


LAYOUT = "(volumes (T, Y, X, Z) = world y, world x, z)"


@pytest.mark.parametrize("key, value, text", [
    ("sequence", None, "attribute sequence must name the sequence this file predicts ('seq_0000'), it is missing"),
    ("sequence", "seq_0000.h5", "attribute sequence is 'seq_0000.h5', but the file is seq_0000.h5"),
    ("sequence", np.array(["seq_0000"] * 2, dtype=h5py.string_dtype()), "predicts ('seq_0000'), got an array of "
                                                                         "shape (2,)"),
    ("axis_order", None, f"attribute axis_order must be 'y,x,z' {LAYOUT}, it is missing"),
    ("axis_order", "x,y,z", f"attribute axis_order must be 'y,x,z' {LAYOUT}, got 'x,y,z'"),
    ("axis_order", 3, f"attribute axis_order must be 'y,x,z' {LAYOUT}, got type int64"),
    ("flow_components", None, "attribute flow_components must be 'dy,dx,dz' (motion components (dy, dx, dz)), it is "
                              "missing"),
    ("flow_components", "dx,dy,dz", "attribute flow_components must be 'dy,dx,dz' (motion components (dy, dx, dz)), "
                                    "got 'dx,dy,dz'"),
], ids=["sequence-missing", "sequence-wrong", "sequence-array", "axis_order-missing", "axis_order-x,y,z",
        "axis_order-int", "flow_components-missing", "flow_components-dx,dy,dz"])
def test_the_sequence_and_layout_a_file_states(pred, data, capsys, key, value, text):
    with h5py.File(pred / TARGET, "r+") as f:
        if key in f.attrs:
            del f.attrs[key]
        if value is not None:
            f.attrs[key] = value
    _refused(pred, data, capsys, TARGET, text)


def test_the_stated_attributes_of_any_string_type_are_accepted(pred, data, tmp_path):
    """Fixed-length byte strings (as MATLAB or h5py's np.bytes_ write them) state the same as variable-length ones."""
    with h5py.File(pred / TARGET, "r+") as f:
        for key in ("sequence", "axis_order", "flow_components"):
            f.attrs[key] = np.bytes_(f.attrs[key].encode())
    out = tmp_path / "results.json"
    assert main(["evaluate", str(pred), "--data", str(data), "--out", str(out), "--workers", "1"]) == 0


def test_write_predictions_states_the_sequence_and_layout(tmp_path):
    from dsr_bench.scoring.predictions import write_predictions

    steps = 1
    mask, motion = np.zeros((steps, 128, 128, 48), np.uint8), np.zeros((steps, 3, 128, 128, 48), np.float16)
    with h5py.File(write_predictions(tmp_path / "seq_0007.h5", mask, motion, 4), "r") as f:
        assert (f.attrs["sequence"], f.attrs["axis_order"], f.attrs["flow_components"]) == ("seq_0007", "y,x,z",
                                                                                            "dy,dx,dz")
    flow = np.zeros((steps, 240, 320, 3), np.float16)
    with h5py.File(write_predictions(tmp_path / "seq_0008.h5", motion_2d=flow), "r") as f:  # 2D-only: no volumes
        assert dict(f.attrs) == {"format": "dsr-bench-predictions", "sequence": "seq_0008",
                                 "flow_components": "dy,dx,dz"}


@pytest.mark.parametrize("entry, kind, text", [
    ("notes.txt", "file", "extra file: a predictions directory holds one SEQUENCE.h5 per sequence of the split and "
                          "meta.json, nothing else; move it out of the directory"),
    ("seq_0000.npz", "file", "extra file: a predictions directory holds one SEQUENCE.h5"),
    ("results", "directory", "extra directory: a predictions directory holds one SEQUENCE.h5"),
    (".seq_0001.h5.tmp-host-123-ab12", "file", "extra file: the temporary of a write still running or interrupted"),
], ids=["text", "npz", "directory", "temporary"])
def test_extra_entries_are_refused(pred, data, capsys, entry, kind, text):
    """Strict, as a submission format is: nothing in the directory is silently left unscored."""
    if kind == "directory":
        (pred / entry).mkdir()
    else:
        (pred / entry).write_text("x")
    _refused(pred, data, capsys, entry, text)


def test_the_slurm_logs_folder_is_allowed(pred, data, tmp_path):
    """`evaluate --slurm` keeps its logs in PRED_DIR/slurm-logs by default: a later evaluation accepts it."""
    (pred / "slurm-logs").mkdir()
    (pred / "slurm-logs" / "0_0_log.out").write_text("")
    out = tmp_path / "results.json"
    assert main(["evaluate", str(pred), "--data", str(data), "--out", str(out), "--workers", "1"]) == 0


def _swap_y_and_x(path: Path) -> None:
    """`path`'s mask and motion stored with y and x swapped (volumes (X, Y, Z), motion (dx, dy, dz)): the same
    shapes, as X == Y; the attributes it states are kept."""
    _rewrite(path, lambda f, a: (f.create_dataset("mask", data=a["mask"].transpose(0, 2, 1, 3)),
                                 f.create_dataset("motion", data=a["motion"].transpose(0, 1, 3, 2, 4)[:, [1, 0, 2]])))


@pytest.mark.parametrize("model", ["oracle", "static"])
def test_volumes_with_y_and_x_swapped_are_refused(pred, data, capsys, model):
    """The masks lie on the observed surface (tsdf < 0) as stored, not swapped; swapped, the other way round."""
    if model != "oracle":
        shutil.rmtree(pred)
        assert main(["predict", "--model", model, "--data", str(data), "--out", str(pred)]) == 0
    _swap_y_and_x(pred / TARGET)
    _refused(pred, data, capsys, TARGET, "of its voxels lie on the observed surface (tsdf < 0) with y and x swapped",
             "the volumes look transposed; store mask and motion as (T, Y, X, Z)")


@pytest.mark.parametrize("model", MODEL_NAMES)
def test_the_toolkits_own_predictions_are_never_refused(data, tmp_path, capsys, model):
    """Every model of the registry (the references; the learned ones with their shipped weights) passes every check,
    the layout's included."""
    pred = tmp_path / model
    assert main(["predict", "--model", model, "--data", str(data), "--out", str(pred)]) == 0
    out = tmp_path / "results.json"
    rc = main(["evaluate", str(pred), "--data", str(data), "--out", str(out), "--workers", "1"])
    assert rc == 0 and out.exists(), capsys.readouterr().err
