"""Chunk layouts cannot exhaust the evaluator's memory: HDF5 keeps about 6.6 kB for every chunk a read touches,
written or not, so a 1.4 kB file declaring mask in (1, 1, 1, 6) chunks took a read of the mask to 8 GB. The header
check (`check_prediction_header`) refuses more than MAX_STEP_CHUNKS chunks a step, a chunk larger than its dataset
and a stacked compressor, before any array data is read; every layout the toolkit writes and the usual ones a
user writes (h5py's automatic chunking, one step a chunk, contiguous, one chunk for the whole array) pass.
`bench/bench_chunk_memory.py` measures the peak memory of each."""

import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest

from dsr_bench.cli import main
from dsr_bench.constants import GRID_SHAPE, IMAGE_SHAPE
from dsr_bench.scoring import predictions
from dsr_bench.scoring.predictions import (MAX_STEP_CHUNKS, check_prediction_header, prediction_attrs,
                                           write_predictions)
from dsr_bench.testing import write_synthetic_dataset

STEPS = 2
TARGET = "seq_0000.h5"
SHAPES = {"mask": GRID_SHAPE, "motion": (3,) + GRID_SHAPE, "motion_2d": IMAGE_SHAPE + (3,)}
DTYPES = {"mask": np.uint8, "motion": np.float16, "motion_2d": np.float16}
#: the issue's layouts: (dataset, chunks, chunks a step)
FORGED = [("mask", (1, 1, 1, 6), 128 * 128 * 8), ("motion_2d", (1, 1, 1, 1), 240 * 320 * 3)]
#: exactly MAX_STEP_CHUNKS chunks a step: 32 x 32 columns of the grid, 16 x 64 patches of the image
AT_LIMIT = {"mask": (1, 4, 4, 48), "motion": (1, 3, 4, 4, 48), "motion_2d": (1, 15, 5, 3)}


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_synthetic_dataset(tmp_path_factory.mktemp("chunks") / "data", num_sequences=1, num_steps=STEPS)


@pytest.fixture(scope="module")
def oracle(data, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("oracle") / "pred"
    assert main(["predict", "--model", "oracle", "--data", str(data), "--out", str(out)]) == 0
    return out


def _declare(path: Path, steps: int, chunks: dict, arrays: dict | None = None, **options) -> Path:
    """A prediction file with mask, motion and motion_2d of `steps` steps, each in chunks[name] (h5py's `chunks`
    argument; absent: one step a chunk), holding `arrays` or, without them, no data at all (chunks never written)."""
    with h5py.File(path, "w") as f:
        f.attrs["num_slots"] = 3 if arrays is None else arrays["num_slots"]
        f.attrs.update(prediction_attrs(path.stem))  # the sequence and layout a prediction file states
        for name, shape in SHAPES.items():
            layout = chunks.get(name, (1,) + shape)
            if arrays is None:
                f.create_dataset(name, shape=(steps,) + shape, dtype=DTYPES[name], chunks=layout, **options)
            else:
                f.create_dataset(name, data=arrays[name], chunks=layout, **options)
    return path


def _arrays(path: Path) -> dict:
    with h5py.File(path, "r") as f:
        return {name: f[name][()] for name in SHAPES} | {"num_slots": int(f.attrs["num_slots"])}


def _evaluate(pred: Path, data: Path, capsys) -> tuple[int, list[str], Path]:
    """Exit code, the lines of stderr naming TARGET, and where the results would be."""
    out = pred.parent / "results.json"
    rc = main(["evaluate", str(pred), "--data", str(data), "--out", str(out), "--workers", "1"])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, [line for line in err.splitlines() if f"{TARGET}:" in line], out


def _forged(oracle: Path, tmp_path: Path, name: str, chunks: tuple) -> Path:
    """A copy of the oracle's submission whose TARGET declares `name` in `chunks`, holding no array data but one
    garbage chunk of `name`: reading it would be reported as unreadable, so a refusal that names the chunk count
    alone shows nothing was read."""
    pred = tmp_path / "pred"
    pred.mkdir()
    for path in oracle.iterdir():
        (pred / path.name).write_bytes(path.read_bytes())
    _declare(pred / TARGET, STEPS, {name: chunks}, compression="gzip")
    with h5py.File(pred / TARGET, "r+") as f:
        f[name].id.write_direct_chunk((0,) * len(chunks), b"not a deflate stream")
    return pred


@pytest.mark.parametrize("name, chunks, per_step", FORGED)
def test_forged_layouts_are_refused_by_evaluate_without_reading_data(oracle, data, tmp_path, capsys,
                                                                     name, chunks, per_step):
    pred = _forged(oracle, tmp_path, name, chunks)
    assert (pred / TARGET).stat().st_size < 64_000  # the header alone: no data is needed to forge it
    rc, lines, out = _evaluate(pred, data, capsys)
    assert rc != 0 and not out.exists()
    assert len(lines) == 1, lines  # one line: the chunk count, not an unreadable chunk
    line = lines[0]
    for text in (f"{name}: chunks {chunks}", f"{per_step} chunks", f"({per_step * STEPS} in all)",
                 f"the {MAX_STEP_CHUNKS} allowed", "write it with write_predictions, or in chunks of one step"):
        assert text in line, (text, line)


@pytest.mark.parametrize("name, chunks, per_step", FORGED)
def test_forged_layouts_are_refused_by_the_library_check(oracle, tmp_path, name, chunks, per_step):
    pred = _forged(oracle, tmp_path, name, chunks)
    with h5py.File(pred / TARGET, "r") as f:
        problems = check_prediction_header(f, STEPS)
    assert problems == [f"{name}: chunks {chunks} split each step into {per_step} chunks ({per_step * STEPS} in all), "
                        f"more than the {MAX_STEP_CHUNKS} allowed (HDF5 keeps about 6.6 kB per chunk a read "
                        "touches); write it with write_predictions, or in chunks of one step"]


@pytest.mark.parametrize("compression", [None, "gzip"])
def test_a_file_at_the_limit_is_scored_like_the_oracle(oracle, data, tmp_path, capsys, compression):
    """MAX_STEP_CHUNKS chunks a step in every dataset (uncompressed: read through HDF5, not the raw reader)."""
    for name, chunks in AT_LIMIT.items():
        assert math.prod(-(-s // c) for s, c in zip(SHAPES[name], chunks[1:])) == MAX_STEP_CHUNKS
    pred = tmp_path / "pred"
    pred.mkdir()
    (pred / "meta.json").write_bytes((oracle / "meta.json").read_bytes())
    _declare(pred / TARGET, STEPS, AT_LIMIT, _arrays(oracle / TARGET), compression=compression)
    rc, lines, out = _evaluate(pred, data, capsys)
    assert rc == 0 and lines == [] and out.exists()
    metrics = json.loads(out.read_text())["metrics"]
    assert metrics["iou_unordered"] == 1.0 and metrics["motion_full"] == 0.0 and metrics["motion_2d"] == 0.0


def test_the_limit_is_on_the_chunks_of_a_step(tmp_path, monkeypatch):
    """At the limit passes, one chunk a step over it is refused (the limit lowered to just below the layout's)."""
    path = _declare(tmp_path / "a.h5", STEPS, AT_LIMIT)
    with h5py.File(path, "r") as f:
        assert check_prediction_header(f, STEPS) == []
        monkeypatch.setattr(predictions, "MAX_STEP_CHUNKS", MAX_STEP_CHUNKS - 1)
        problems = check_prediction_header(f, STEPS)
    assert [p.split(":")[0] for p in problems] == ["mask", "motion", "motion_2d"]
    assert all(f"into {MAX_STEP_CHUNKS} chunks" in p and f"the {MAX_STEP_CHUNKS - 1} allowed" in p for p in problems)


def test_the_toolkits_own_files_pass(oracle, tmp_path):
    """What write_predictions writes (one step a chunk, gzip), for one step and for ten."""
    for steps in (1, 10):
        path = write_predictions(tmp_path / f"{steps}.h5", np.zeros((steps,) + SHAPES["mask"], np.uint8),
                                 np.zeros((steps,) + SHAPES["motion"], np.float16), 3,
                                 np.zeros((steps,) + SHAPES["motion_2d"], np.float16))
        with h5py.File(path, "r") as f:
            assert check_prediction_header(f, steps) == []
    with h5py.File(oracle / TARGET, "r") as f:
        assert check_prediction_header(f, STEPS) == []


@pytest.mark.parametrize("steps", [1, 10, 100])
@pytest.mark.parametrize("layout", ["h5py-auto", "contiguous", "one-chunk", "tiles", "rows", "z-slices"])
def test_reasonable_layouts_pass(tmp_path, steps, layout):
    """What a user plausibly writes passes, for short and long sequences (declared: the check reads no data)."""
    chunks = {"h5py-auto": {n: True for n in SHAPES},
              "contiguous": {n: None for n in SHAPES},
              "one-chunk": {n: (steps,) + s for n, s in SHAPES.items()},
              "tiles": {"mask": (1, 16, 16, 48), "motion": (1, 3, 16, 16, 48), "motion_2d": (1, 60, 80, 3)},
              "rows": {"mask": (1, 1, 128, 48), "motion": (1, 1, 1, 128, 48), "motion_2d": (1, 1, 320, 3)},
              "z-slices": {"mask": (1, 128, 128, 1), "motion": (1, 1, 128, 128, 1), "motion_2d": (1, 240, 320, 1)},
              }[layout]
    path = _declare(tmp_path / "p.h5", steps, chunks, **({} if layout == "contiguous" else {"compression": "gzip"}))
    with h5py.File(path, "r") as f:
        assert check_prediction_header(f, steps) == []


def test_a_chunk_larger_than_its_dataset_is_refused(tmp_path):
    """A resizable dataset may declare chunks beyond its shape; HDF5 inflates a chunk whole, so a 3 MB file
    with one (1000, 128, 128, 48) chunk of zeros made one step's read take 790 MB."""
    path = tmp_path / "big.h5"
    _declare(path, STEPS, {})
    with h5py.File(path, "r+") as f:
        del f["mask"]
        f.create_dataset("mask", shape=(STEPS,) + GRID_SHAPE, maxshape=(None,) + GRID_SHAPE, dtype=np.uint8,
                         chunks=(1000,) + GRID_SHAPE, compression="gzip")
    with h5py.File(path, "r") as f:
        problems = check_prediction_header(f, STEPS)
    size = math.prod(GRID_SHAPE)
    assert problems == [f"mask: chunks {(1000,) + GRID_SHAPE} hold {1000 * size} bytes each, more than the whole "
                        f"dataset {(STEPS,) + GRID_SHAPE} ({STEPS * size} bytes; HDF5 inflates a chunk whole); "
                        "write it with write_predictions, or in chunks of one step"]


@pytest.mark.parametrize("second, text", [("deflate", "filter gzip more than once (filters gzip -> gzip)"),
                                          ("lzf", "gzip and lzf (filters gzip -> lzf)")])
def test_stacked_compressors_are_refused(tmp_path, second, text):
    """gzip of gzip: a 7 kB file whose one chunk inflates to 1 GB (1000 x 1000); one compressor at most."""
    from h5py import h5d, h5p, h5s, h5t

    path = _declare(tmp_path / "stacked.h5", STEPS, {})
    with h5py.File(path, "r+") as f:
        del f["mask"]
        dcpl = h5p.create(h5p.DATASET_CREATE)
        dcpl.set_chunk((1,) + GRID_SHAPE)
        dcpl.set_deflate(1)
        if second == "deflate":
            dcpl.set_deflate(1)
        else:
            dcpl.set_filter(32000, 0, ())
        h5d.create(f.id, b"mask", h5t.NATIVE_UINT8, h5s.create_simple((STEPS,) + GRID_SHAPE), dcpl=dcpl)
    with h5py.File(path, "r") as f:
        problems = check_prediction_header(f, STEPS)
    assert problems == [f"mask: compressed with {text}; one compressor at most, each filter once: "
                        "write it with write_predictions"]


@pytest.mark.parametrize("chunks", [(1,) + GRID_SHAPE, (STEPS,) + GRID_SHAPE])  # the fast reader's, and HDF5's own
def test_a_gzip_bomb_is_unreadable_not_inflated(oracle, data, tmp_path, capsys, chunks):
    """A chunk that inflates far beyond its size (a kilobyte to 200 MB) is refused before HDF5's decoder inflates it
    whole: one problem line, no score, nothing written."""
    import resource
    import zlib

    pred = tmp_path / "pred"
    pred.mkdir()
    for path in oracle.iterdir():
        (pred / path.name).write_bytes(path.read_bytes())
    arrays = _arrays(oracle / TARGET)
    _declare(pred / TARGET, STEPS, {"mask": chunks}, arrays, compression="gzip")
    with h5py.File(pred / TARGET, "r+") as f:
        f["mask"].id.write_direct_chunk((0,) * 4, zlib.compress(bytes(200_000_000), 9))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    rc, lines, out = _evaluate(pred, data, capsys)
    assert rc == 1 and len(lines) == 1 and "does not inflate to its" in lines[0] and not out.exists()
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 150_000  # kB: never the 200 MB
