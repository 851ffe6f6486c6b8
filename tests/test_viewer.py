"""`dsr-bench view --save`: the recording holds the entities, timelines and values we log,
checked with rerun's own tools (`rerun rrd verify`, `rerun rrd print`)."""

import re
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

pytest.importorskip("rerun")

from dsr_bench.cli import main  # noqa: E402


def _rerun() -> str:
    local = Path(sys.executable).parent / "rerun"
    found = str(local) if local.exists() else shutil.which("rerun")
    if found is None:
        pytest.skip("the rerun command-line tool is not installed")
    return found


def _rows_per_entity(rrd: Path) -> Counter:
    out = subprocess.run([_rerun(), "rrd", "print", "-v", str(rrd)], capture_output=True, text=True, check=True).stdout
    rows = Counter()
    for n, entity, columns in re.findall(r"with (\d+) rows .*? - (/\S+) - data columns: \[([^\]]*)\]", out):
        for column in columns.split():
            rows[column.split("@", 1)[1] if "@" in column else column, entity] += 0
        rows[entity] += int(n)
        for column in columns.split():
            rows[column] += int(n)
    return rows


@pytest.fixture(scope="module")
def recording(generated_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("rrd")
    assert main(["predict", "--model", "static", "--data", str(generated_dataset), "--out", str(out / "pred")]) == 0
    rrd = out / "seq_0001.rrd"
    assert main(["view", "seq_0001", "--data", str(generated_dataset), "--predictions", str(out / "pred"),
                 "--save", str(rrd)]) == 0
    return rrd


def test_recording_verifies(recording):
    result = subprocess.run([_rerun(), "rrd", "verify", str(recording)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_entities_and_rows_per_step(recording):
    rows = _rows_per_entity(recording)
    steps = 3  # the fixture's pushes: T + 1 observations
    for entity, expected in [("/world/gt/mask", steps + 1), ("/world/tsdf", steps + 1),
                             ("/world/cameras/front/image/color", steps + 1),
                             ("/world/cameras/front/image/depth", steps + 1), ("/world/gt/flow", steps),
                             ("/world/pred/mask", steps), ("/world/pred/disagree", steps),
                             ("/metrics/iou_unordered", steps), ("/metrics/motion_full", steps),
                             ("/policy/direction_probs", steps)]:
        assert rows[entity] == expected, (entity, rows[entity])
    assert rows["/world/push@Arrows3D:vectors"] == steps
    assert rows["/world/objects/1@Mesh3D:vertex_positions"] == 1  # static mesh, posed per step
    assert rows["/world/objects/1@Transform3D:quaternion"] == steps + 1
    assert rows["/world/cameras/front/image@Pinhole:image_from_camera"] == 1
    assert rows["/world@AnnotationContext:context"] == 1
    assert any(k.startswith("/viewport") for k in rows)  # a blueprint is stored with the recording


def test_timeline_and_values(recording):
    out = subprocess.run([_rerun(), "rrd", "print", "-vvv", str(recording)], capture_output=True, text=True).stdout
    assert "index_name: step" in out and "index_name: observation" in out
    block = out[out.index("/metrics/iou_unordered"):][:6000]
    values = [float(v) for v in re.findall(r"\[(0\.\d+|1(?:\.0)?)\]", block)]
    assert values and all(0 <= v <= 1 for v in values)


def test_errors(generated_dataset, tmp_path, capsys):
    assert main(["view", "seq_0099", "--data", str(generated_dataset), "--save", str(tmp_path / "x.rrd")]) == 2
    assert "no sequence 'seq_0099'" in capsys.readouterr().err
    broken = tmp_path / "broken.h5"
    broken.write_bytes(b"\x89HDF\r\n garbage")
    assert main(["view", str(broken), "--save", str(tmp_path / "y.rrd")]) == 2
    assert "not a readable HDF5 file" in capsys.readouterr().err
    assert not (tmp_path / "y.rrd").exists()
    assert main(["view", "seq_0000", "--data", str(generated_dataset), "--predictions", str(tmp_path / "none"),
                 "--save", str(tmp_path / "z.rrd")]) == 2
