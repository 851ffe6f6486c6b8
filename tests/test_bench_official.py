"""The side-by-side benchmarks' own side and argument handling (bench/official.py and the benches
that use it), against a FAKE checkout of the authors' repository made here: no timing is asserted."""

from __future__ import annotations

import stat
import sys
from pathlib import Path

import numpy as np
import pytest

from dsr_bench.errors import UserError

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import official  # noqa: E402

# Written from the description in the notes (official-release.md, "Running the authors' code beside
# ours"), not from their code: logit_pred [B, K, S1, S2, S3] with the LAST channel empty,
# mask_gt_argmax [B, S1, S2, S3] with 0 = empty; I / max(U, 1) between the K-1 predicted object
# channels and GT objects 1..K-1, best permutation, mean over slots; ordered: one permutation for the
# whole sequence. A module-level import of a module that does not exist stands for their model
# (which needs cupy): the extraction must skip it.
FAKE_TEST_PY = '''
import itertools

import numpy as np
import torch

from model import ModelDSR  # needs cupy in the real repository; absent here

SLOT_EPS = 1


def _iou_table(logit_pred, mask_gt_argmax):
    B, K = logit_pred.size()[:2]
    pred = torch.argmax(logit_pred, dim=1)
    table = np.zeros([B, K - 1, K - 1])
    for b in range(B):
        for i in range(K - 1):
            p = pred[b] == i
            for j in range(K - 1):
                g = mask_gt_argmax[b] == j + 1
                inter = torch.sum(p & g).item()
                union = torch.sum(p | g).item()
                table[b, i, j] = inter / max(union, SLOT_EPS)
    return table


def calc_iou_unordered(logit_pred, mask_gt_argmax):
    table = _iou_table(logit_pred, mask_gt_argmax)
    K = table.shape[1]
    return np.array([max(np.mean([t[i, p[i]] for i in range(K)]) for p in itertools.permutations(range(K)))
                     for t in table])


def calc_iou_ordered(logit_pred_list, mask_gt_argmax_list):
    tables = np.stack([_iou_table(l, g) for l, g in zip(logit_pred_list, mask_gt_argmax_list)])
    L, B, K = tables.shape[:3]
    return np.array([max(np.mean([tables[l, b, i, p[i]] for l in range(L) for i in range(K)])
                         for p in itertools.permutations(range(K))) for b in range(B)])


model = ModelDSR()

if __name__ == "__main__":
    raise SystemExit("the test script of the fake checkout")
'''

# Writes one tiny file and sleeps 0.1 s; fails unless run from the repository root (assets/).
FAKE_DATA_GENERATION = '''
import argparse, os, time
parser = argparse.ArgumentParser()
for name in ("--data_path", "--object_type", "--train_num", "--test_num", "--max_path_length"):
    parser.add_argument(name)
args = parser.parse_args()
if not os.path.isdir("assets"):
    raise SystemExit("assets/ not found: run from the repository root")
os.makedirs(args.data_path, exist_ok=True)
with open(os.path.join(args.data_path, "0_0.hdf5"), "wb") as f:
    f.write(b"x")
time.sleep(0.1)
'''


@pytest.fixture
def fake_repo(tmp_path) -> Path:
    repo = tmp_path / "dsr"
    (repo / "assets").mkdir(parents=True)
    (repo / "test.py").write_text(FAKE_TEST_PY)
    (repo / "data_generation.py").write_text(FAKE_DATA_GENERATION)
    return repo


# --- check_official_repo / load_official_functions -------------------------------------------------

def test_a_path_that_is_not_a_checkout_fails_with_one_line_naming_the_missing_file(tmp_path, fake_repo):
    with pytest.raises(UserError) as err:
        official.check_official_repo(tmp_path / "nowhere")
    assert "not a directory" in str(err.value) and "\n" not in str(err.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError) as err:
        official.check_official_repo(tmp_path / "empty", ("data_generation.py", "test.py"))
    message = str(err.value)
    assert "data_generation.py" in message and "test.py" in message and "\n" not in message
    assert official.check_official_repo(fake_repo, ("data_generation.py", "test.py")) == fake_repo.resolve()


def test_the_benches_report_a_bad_checkout_as_one_line_and_exit_2(tmp_path, capsys):
    import bench_evaluate

    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit) as exit_:
        official.run_main(bench_evaluate.main, ["--data", str(tmp_path), "--official-repo", str(tmp_path / "empty")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "test.py missing" in err and "\n" not in err


def test_load_official_functions_skips_imports_the_functions_do_not_need(fake_repo):
    pytest.importorskip("torch")
    functions = official.load_official_functions(fake_repo)
    assert set(functions) == {"calc_iou_unordered", "calc_iou_ordered"} and all(map(callable, functions.values()))
    with pytest.raises(UserError, match="defines no function calc_iou_3d"):
        official.load_official_functions(fake_repo, ("calc_iou_unordered", "calc_iou_3d"))
    (fake_repo / "test.py").write_text("from model import helper\n\n"
                                       "def calc_iou_unordered(a, b):\n    return helper(a)\n")
    with pytest.raises(UserError, match="need a module"):
        official.load_official_functions(fake_repo, ("calc_iou_unordered",))


@pytest.mark.parametrize("num_objects", [4, 3, 2])
def test_the_authors_functions_as_described_give_our_official_iou(fake_repo, num_objects):
    """Pins the notes' description of their inputs (and bench_evaluate's way of building them)
    against dsr_bench.scoring.metrics' official-definition IoU."""
    pytest.importorskip("torch")
    import bench_evaluate

    from dsr_bench.scoring.metrics import official_iou, overlap, sequence_scores

    functions = official.load_official_functions(fake_repo)
    rng = np.random.default_rng(num_objects)
    gt = rng.integers(0, num_objects + 1, (3, 8, 8, 4)).astype(np.uint8)
    pred = np.where(rng.random(gt.shape) < 0.6, (gt + rng.integers(0, 4)) % 5, rng.integers(0, 5, gt.shape))
    pred = pred.astype(np.uint8)
    logits, gts = bench_evaluate.official_inputs(pred, gt, num_slots=4)
    assert logits[0].shape == (1, 5, 8, 8, 4) and gts[0].shape == (1, 8, 8, 4)
    assert (logits[0][0, -1].numpy() == (pred[0] == 0)).all()  # the last channel holds the empty voxels
    for t in range(3):
        ours = official_iou(overlap(pred[t], gt[t], 4, num_objects))
        assert np.isclose(functions["calc_iou_unordered"](logits[t], gts[t])[0], ours)
    scores = sequence_scores(pred, gt, 4, num_objects)
    assert np.allclose([functions["calc_iou_unordered"](lg, g)[0] for lg, g in zip(logits, gts)],
                       scores["iou_unordered_official"])
    assert np.isclose(functions["calc_iou_ordered"](logits, gts)[0], scores["iou_ordered_official"].mean())


# --- alternate / report -----------------------------------------------------------------------------

def test_alternate_runs_the_sides_in_turn():
    calls = []

    def side(name, seconds):
        def run():
            calls.append(name)
            return seconds
        return run

    timings = official.alternate({"A": side("A", 2.0), "B": side("B", None), "C": side("C", 1.0)}, 3)
    assert calls == ["A", "B", "C"] * 3
    assert timings["A"] == [2.0] * 3 and timings["C"] == [1.0] * 3  # the side's own measure is kept
    assert len(timings["B"]) == 3 and all(t >= 0 for t in timings["B"])  # None: timed as a whole
    with pytest.raises(UserError, match="--repeats 0"):
        official.alternate({"A": side("A", 1.0)}, 0)


def test_report_prints_medians_and_the_ratio_of_medians():
    lines = []
    out = official.report({"theirs": [10.0, 40.0, 12.0], "ours": [1.0, 2.0, 9.0]}, [("theirs", "ours")], per=2,
                          out=lines.append)
    assert out["theirs"] == 6.0 and out["ours"] == 1.0 and out["theirs / ours"] == 6.0
    assert any("theirs / ours: 6.0x" in line for line in lines)


# --- official_env (a fake interpreter stands in for python and pip) ---------------------------------

FAKE_PYTHON = '''#!/bin/sh
echo "$*" >> "{calls}"
if [ "$1" = "-c" ]; then echo {version}; exit 0; fi
if [ "$1" = "-m" ] && [ "$2" = "venv" ]; then mkdir -p "$3/bin"; cp "$0" "$3/bin/python"; exit 0; fi
if [ "$1" = "-m" ] && [ "$2" = "pip" ]; then
  case "$*" in *numpy==1.23.5*) if [ -n "{fail}" ]; then
    echo "ERROR: No matching distribution found for numpy==1.23.5"; exit 1; fi;; esac
  exit 0
fi
exit 3
'''


def _fake_python(tmp_path, version="3 11", fail=""):
    path = tmp_path / f"python-{version.replace(' ', '.')}{'-failing' if fail else ''}"
    calls = tmp_path / "calls.txt"
    path.write_text(FAKE_PYTHON.format(calls=calls, version=version, fail=fail))
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return path, calls


def test_official_env_is_built_once_and_reused(tmp_path, fake_repo):
    python, calls = _fake_python(tmp_path)
    scratch = tmp_path / "cache"
    env_python = official.official_env(fake_repo, scratch, python, log=lambda _: None)
    assert env_python == scratch.resolve() / "venv-py3.11" / "bin" / "python" and env_python.exists()
    installs = [line for line in calls.read_text().splitlines() if "install" in line and "numpy==1.23.5" in line]
    assert len(installs) == 1 and all(r in installs[0] for r in official.OFFICIAL_REQUIREMENTS)
    assert official.official_env(fake_repo, scratch, python, log=lambda _: None) == env_python
    assert len([line for line in calls.read_text().splitlines() if "numpy==1.23.5" in line]) == 1  # cached


def test_official_env_reports_a_failing_pip_and_the_way_out(tmp_path, fake_repo):
    python, _ = _fake_python(tmp_path, fail="yes")
    with pytest.raises(UserError) as err:
        official.official_env(fake_repo, tmp_path / "cache", python, log=lambda _: None)
    message = str(err.value)
    assert "No matching distribution found for numpy==1.23.5" in message and "--official-python" in message
    assert "\n" not in message and not (tmp_path / "cache" / "venv-py3.11").exists()  # no half-built env kept


def test_official_env_refuses_a_python_without_wheels_and_a_place_inside_our_venv(tmp_path, fake_repo):
    python, _ = _fake_python(tmp_path, version="3 12")
    with pytest.raises(UserError, match="Python 3.12.*--official-python"):
        official.official_env(fake_repo, tmp_path / "cache", python)
    with pytest.raises(UserError, match="inside the toolkit's environment"):
        official.official_env(fake_repo, Path(sys.prefix) / "official-env", sys.executable)


# --- bench_evaluate ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory) -> Path:
    from dsr_bench.testing import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("bench") / "data", num_sequences=2, num_steps=2)


def test_bench_evaluate_compares_with_the_authors_functions_end_to_end(tiny_dataset, fake_repo, capsys):
    pytest.importorskip("torch")
    pytest.importorskip("scipy")
    import bench_evaluate

    out = bench_evaluate.main(["--data", str(tiny_dataset), "--repeats", "2", "--official-repo", str(fake_repo)])
    text = capsys.readouterr().out
    assert set(out["timings"]) == {bench_evaluate.READ, bench_evaluate.OURS, bench_evaluate.OURS_1,
                                   bench_evaluate.THEIRS}
    assert all(len(v) == 2 for v in out["timings"].values())
    assert out["difference"]["unordered"] < 1e-9 and out["difference"]["ordered"] < 1e-9
    assert f"{bench_evaluate.THEIRS} / {bench_evaluate.OURS}:" in text and "max |difference|" in text
    assert "WARNING" not in text and "no comparison" not in text


def test_bench_evaluate_without_a_checkout_times_only_our_side(tiny_dataset, capsys):
    pytest.importorskip("scipy")
    import bench_evaluate

    out = bench_evaluate.main(["--data", str(tiny_dataset), "--repeats", "1"])
    text = capsys.readouterr().out
    assert set(out["timings"]) == {bench_evaluate.READ, bench_evaluate.OURS, bench_evaluate.OURS_1}
    assert "no comparison with the authors' code was made" in text and "authors'" not in text.split("no comparison")[0]


# --- bench_generate_official ------------------------------------------------------------------------

def test_the_generate_commands_are_the_documented_ones(tmp_path):
    import bench_generate_official as bench

    out = tmp_path / "out"
    ours = bench.our_command(out, 7, 10)
    assert Path(ours[0]).name == "dsr-bench"
    assert ours[1:] == ["generate", "--objects", "cube", "-n", "1", "--workers", "1", "--seed", "7", "--out", str(out)]
    assert bench.our_command(out, 7, 3)[-2:] == ["--steps", "3"]
    assert bench.our_command(out, 7, 10, sleep_at_rest=True)[-1] == "--sleep-at-rest"
    assert bench.official_command(Path("py"), out, 10) == ["py", "data_generation.py", "--data_path", str(out),
                                                           "--object_type", "cube", "--train_num", "1",
                                                           "--test_num", "0"]


def _quick_ours(seeds, asleep=None):
    def command(out, seed, steps, sleep_at_rest=False):
        (seeds if not sleep_at_rest or asleep is None else asleep).append(seed)
        return [sys.executable, "-c", "import pathlib, sys; p = pathlib.Path(sys.argv[1]); p.mkdir(parents=True); "
                "(p / 'seq_0000.h5').write_bytes(b'x')", str(out)]
    return command


def test_bench_generate_alternates_the_authors_generator_with_ours(fake_repo, monkeypatch, capsys):
    import bench_generate_official as bench

    seeds, asleep = [], []
    monkeypatch.setattr(bench, "our_command", _quick_ours(seeds, asleep))
    out = bench.main(["--official-repo", str(fake_repo), "--no-venv", "--official-python", sys.executable,
                      "--repeats", "2", "--seed", "5"])
    text = capsys.readouterr().out
    sides = [bench.THEIRS, bench.OURS, bench.OURS_ASLEEP]
    assert list(out["timings"]) == sides and all(len(v) == 2 for v in out["timings"].values())
    assert seeds == [5, 6] and asleep == [5, 6]  # a new sequence per run, the same seeds with the option
    assert f"{bench.THEIRS} / {bench.OURS}:" in text and f"{bench.THEIRS} / {bench.OURS_ASLEEP}:" in text
    assert list(out["cpu"]) == sides and all(len(v) == 2 for v in out["cpu"].values())
    assert all(v >= 0 for values in out["cpu"].values() for v in values)  # each run's process CPU seconds
    assert f"CPU {bench.THEIRS} / {bench.OURS}" in out["figures"] and "process CPU seconds" in text
    row = [line for line in text.splitlines() if line.startswith("| 2")]
    assert len(row) == 1 and row[0].count("|") == 17 and "alternated" in row[0] and "load" in row[0]
    mb = out["figures"]["MB per step"]  # every file each run wrote, over its 10 steps: ours wrote one byte
    assert mb[bench.OURS] == pytest.approx(1 / 10 / 1e6) and mb[bench.THEIRS] > 0
    assert f"bytes per step, {bench.THEIRS} / {bench.OURS}:" in text


def test_bench_generate_without_a_checkout_runs_only_ours(monkeypatch, capsys):
    import bench_generate_official as bench

    monkeypatch.setattr(bench, "our_command", _quick_ours([]))
    out = bench.main(["--repeats", "1"])
    assert list(out["timings"]) == [bench.OURS, bench.OURS_ASLEEP]
    assert "no comparison with the authors' code was made" in capsys.readouterr().out


def test_bench_generate_reports_a_failing_or_silent_official_run_in_one_line(fake_repo, tmp_path, monkeypatch):
    import tempfile

    import bench_generate_official as bench

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # the logs of a failed run are kept: keep them here
    monkeypatch.setattr(bench, "our_command", _quick_ours([]))
    args = ["--official-repo", str(fake_repo), "--no-venv", "--official-python", sys.executable, "--repeats", "1"]
    (fake_repo / "assets").rmdir()  # not run from a root holding assets/: their script fails
    with pytest.raises(UserError) as err:
        bench.main(args)
    assert "exited 1" in str(err.value) and "assets/ not found" in str(err.value) and "\n" not in str(err.value)
    (fake_repo / "assets").mkdir()
    (fake_repo / "data_generation.py").write_text("pass\n")
    with pytest.raises(UserError, match="wrote nothing"):
        bench.main(args)


# --- bench_storage -----------------------------------------------------------------------------------

def test_bench_storage_restores_bit_for_bit_and_reports_where_the_bytes_go(tmp_path, capsys):
    """bench_storage re-writes a schema-2-style dataset (points stored) through today's writer, checks every array
    bit for bit (or stops), and reports bytes per step by array and whole files; points equal to depth's
    back-projection are left out (derived), so the re-stored files are smaller."""
    import h5py

    import bench_storage
    from dsr_bench.dataset.sequence import SequenceReader, derive_points
    from dsr_bench.testing import write_synthetic_dataset

    data = write_synthetic_dataset(tmp_path / "data", num_sequences=2, num_steps=2)
    for path in sorted(data.glob("seq_*.h5")):  # as the generator writes them: points follow from depth exactly
        with SequenceReader(path) as seq:
            points = derive_points(seq.read("cameras/front/depth"), seq.camera("front"))
        with h5py.File(path, "r+") as f:
            f["cameras/front/points"][...] = points
    out = bench_storage.main([str(data), "--num-sequences", "2", "--repeats", "1"])
    text = capsys.readouterr().out
    assert "arrays re-stored bit for bit" in text and "(derived on reading)" in text
    assert "cameras/front/points" in out["bytes"]["as stored"]
    assert "cameras/front/points" not in out["bytes"]["current layout"]
    assert out["mb_per_step"]["current layout"] < out["mb_per_step"]["as stored"]
    assert set(out["read_seconds_per_step"]) == {"as stored", "current layout"}


def test_bench_storage_runs_on_a_freshly_generated_schema_3_dataset(generated_dataset, capsys):
    """Today's generator stores no camera points (schema 3 derives them from depth): bench_storage re-stores such
    files from every array as read, derived ones included, bit for bit, in the same bytes (issue 33: it refused
    with "missing dataset 'cameras/front/points'")."""
    import h5py

    import bench_storage
    from dsr_bench.dataset.sequence import DERIVED_ATTR

    first = sorted(generated_dataset.glob("seq_*.h5"))[0]
    with h5py.File(first, "r") as f:
        assert "points" not in f["cameras/front"] and "cameras/front/points" in f.attrs[DERIVED_ATTR]
    out = bench_storage.main([str(generated_dataset), "--num-sequences", "2", "--repeats", "1"])
    text = capsys.readouterr().out
    assert "2 sequences" in text and "arrays re-stored bit for bit" in text
    assert out["bytes"]["as stored"] == out["bytes"]["current layout"]  # already today's layout
    assert "cameras/front/points" not in out["bytes"]["as stored"]
    assert out["mb_per_step"]["current layout"] == pytest.approx(out["mb_per_step"]["as stored"], rel=0.01)


def test_bench_table_layer_reads_the_free_voxels_of_the_bottom_layer(tmp_path, capsys):
    """The table layer's figure (DATASHEET) is the z = 0 layer at the voxels no object occupies, on both sides."""
    import h5py

    import bench_table_layer
    from dsr_bench.testing import write_synthetic_dataset

    tsdf = np.ones((4, 4, 3), np.float32)
    tsdf[:, :, 0] = -0.5
    tsdf[0, 0, 0] = 0.25  # under an object: left out
    mask = np.zeros((4, 4, 3), np.uint8)
    mask[0, 0, 0] = 1
    assert bench_table_layer.table_layer(tsdf, mask).tolist() == [-0.5] * 15
    reference = tmp_path / "reference.h5"
    with h5py.File(reference, "w") as f:
        for name in ("seq_0000", "seq_0001"):
            f[f"{name}/tsdf_step0"], f[f"{name}/mask_3d_step0"] = tsdf, mask
        f["seq_0002/positions"] = np.zeros(3)  # a sequence without step-0 volumes: not counted
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=1)
    out = bench_table_layer.main([str(data), "--reference", str(reference)])
    assert out["theirs"] == {"median_per_scene": [-0.5, -0.5], "median": -0.5, "negative_share": 1.0}
    assert len(out["ours"]["median_per_scene"]) == 1 and "theirs z = 0 layer" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="no such file"):
        bench_table_layer.main([str(data), "--reference", str(tmp_path / "missing.h5")])


def test_bench_evaluate_times_a_baseline_checkout_beside_this_one(tmp_path, capsys):
    """--baseline-repo: a bad path is one line; a checkout (here this one) is timed beside this one, alternated, and
    the difference printed."""
    import bench_evaluate

    from dsr_bench.testing import write_synthetic_dataset

    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit) as exit_:
        official.run_main(bench_evaluate.main, ["--data", str(tmp_path), "--baseline-repo", str(tmp_path / "empty")])
    err = capsys.readouterr().err.strip()
    assert exit_.value.code == 2 and "not a dsr-bench checkout" in err and "\n" not in err
    data = write_synthetic_dataset(tmp_path / "data", num_sequences=1, num_steps=1)
    repo = Path(__file__).resolve().parents[1]
    out = bench_evaluate.main(["--data", str(data), "--model", "oracle", "--repeats", "1", "--workers", "1",
                               "--baseline-repo", str(repo)])
    printed = capsys.readouterr().out
    assert len(out["timings"][bench_evaluate.BASELINE]) == 1 and out["timings"][bench_evaluate.HERE][0] > 0
    assert "this checkout's evaluate over the baseline's:" in printed
