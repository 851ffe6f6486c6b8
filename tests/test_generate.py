"""`dsr-bench generate` end to end: physics and policy sanity, ground-truth consistency,
determinism across workers and shards, resume after kill -9, and bad inputs."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pybullet")

from dsr_bench.cli import main  # noqa: E402
from dsr_bench.constants import TSDF_TRUNCATION  # noqa: E402
from dsr_bench.geometry import pose_to_matrix, world_to_pixel  # noqa: E402
from dsr_bench.dataset.sequence import SequenceReader  # noqa: E402

SMALL = ["--objects", "procedural", "--steps", "3", "--objects-per-scene", "3", "--seed", "5"]


def _generate(out: Path, *extra: str, n: int = 2) -> int:
    return main(["generate", *SMALL, "-n", str(n), "--out", str(out), *extra])


def _digests(directory: Path) -> dict[str, str]:
    out = {}
    for path in sorted(directory.glob("seq_*.h5")):
        with SequenceReader(path) as seq:
            out[path.stem] = seq.attrs["content_sha256"]
    return out


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("gen") / "data"
    assert _generate(out, "--cameras", "front,back") == 0
    return out


def test_layout_manifest_and_split(dataset):
    from dsr_bench.dataset.manifest import load_manifest

    assert sorted(p.name for p in dataset.glob("seq_*.h5")) == ["seq_0000.h5", "seq_0001.h5"]
    assert (dataset / "splits" / "all.txt").read_text().split() == ["seq_0000", "seq_0001"]
    manifest = load_manifest(dataset)
    assert [s["name"] for s in manifest["sequences"]] == ["seq_0000", "seq_0001"]
    assert not list(dataset.glob(".*tmp*"))


def test_shapes_ranges_and_attributes(dataset):
    with SequenceReader(dataset / "seq_0000.h5") as seq:
        assert seq.num_steps == 3 and seq.num_objects == 3
        assert seq.read("tsdf").shape == (4, 128, 128, 48)
        assert seq.read("scene_flow_3d").shape == (3, 3, 128, 128, 48)
        assert seq.read("cameras/back/depth").shape == (4, 240, 320)
        mask = seq.read("mask_3d")
        assert set(np.unique(mask)) == {0, 1, 2, 3}  # every object is in the grid at every step
        tsdf = seq.read("tsdf")
        assert tsdf.min() >= -1 and tsdf.max() <= 1 and (tsdf < 0).any()
        assert np.all(seq.read("visible_fraction")[0] >= 0.4)
        poses = seq.read("object_poses")
        assert np.allclose(np.linalg.norm(poses[..., 3:], axis=-1), 1, atol=1e-6)
        args = seq.attrs["generator_args"]
        assert args["objects"] == "procedural" and args["base_seed"] == 5 and args["index"] == 0
        assert seq.attrs["pybullet_version"] > 0 and len(seq.objects) == 3
        # the stored action is the grid cell of the tool's start
        assert np.array_equal(world_to_pixel(seq.read("push_start")[:, :2]), seq.read("action")[:, 1:])


def test_chosen_object_moves_and_others_mostly_stay(dataset):
    moved_chosen, moved_other = [], []
    for path in sorted(dataset.glob("seq_*.h5")):
        with SequenceReader(path) as seq:
            poses, chosen = seq.read("object_poses"), seq.read("policy/chosen_object")
        for t, k in enumerate(chosen):
            shift = np.linalg.norm(poses[t + 1, :, :2] - poses[t, :, :2], axis=1)
            moved_chosen.append(shift[k])
            moved_other.extend(np.delete(shift, k))
    assert np.median(moved_chosen) > 0.02  # a 15 cm push moves what it hits by centimetres
    assert np.median(moved_other) < 0.005 and np.mean(moved_other) < np.mean(moved_chosen) / 3


def _splat(points: np.ndarray, shape) -> np.ndarray:
    """Trilinear splat of unit weights at continuous voxel positions (M, 3) onto a grid."""
    import itertools

    base = np.floor(points).astype(int)
    frac = points - base
    acc = np.zeros(shape)
    for corner in itertools.product((0, 1), repeat=3):
        idx = base + np.array(corner)
        w = np.prod(np.where(np.array(corner) == 1, frac, 1 - frac), axis=1)
        ok = np.all((idx >= 0) & (idx < shape), axis=1)
        np.add.at(acc, tuple(idx[ok].T), w[ok])
    return acc


def test_flow_warps_mask_onto_next_mask(dataset):
    """Warping each object's amodal voxels at t by the flow (trilinear splat, occupied where the
    splatted weight reaches 0.5) lands on its voxels at t+1: IoU > 0.9 for solid objects; for every
    object, thin walls included (there a sub-voxel shift changes which centres fall inside), each
    warped voxel lies within one voxel of the next mask and back."""
    from scipy import ndimage

    with SequenceReader(dataset / "seq_0000.h5") as seq:
        masks, flows, poses = seq.read("mask_3d"), seq.read("scene_flow_3d"), seq.read("object_poses")
    checked, solid_checked = 0, 0
    ball = ndimage.generate_binary_structure(3, 3)
    for t in range(flows.shape[0]):
        for obj in range(1, poses.shape[1] + 1):
            src = np.argwhere(masks[t] == obj)
            warped = _splat(src + flows[t][:, src[:, 0], src[:, 1], src[:, 2]].T, masks.shape[1:]) >= 0.5
            target = masks[t + 1] == obj
            assert (warped & ndimage.binary_dilation(target, ball)).sum() >= 0.99 * warped.sum(), (t, obj)
            assert (target & ndimage.binary_dilation(warped, ball)).sum() >= 0.99 * target.sum(), (t, obj)
            if ndimage.binary_erosion(masks[t] == obj, ball).sum() >= 0.3 * len(src):  # a solid core
                iou = (warped & target).sum() / (warped | target).sum()
                assert iou > 0.9, (t, obj, iou)
                solid_checked += 1
            checked += 1
    assert checked == flows.shape[0] * poses.shape[1] and solid_checked > 0


def test_tsdf_sign_agrees_with_depth(dataset):
    with SequenceReader(dataset / "seq_0001.h5") as seq:
        tsdf, depth, cam = seq.read("tsdf", 2), seq.read("cameras/front/depth", 2), seq.camera("front")
    from dsr_bench.geometry import voxel_points

    centres = voxel_points()
    uv, z = cam.project(centres[tsdf < 0])
    u = np.clip(np.rint(uv[:, 0]).astype(int), 0, cam.width - 1)
    v = np.clip(np.rint(uv[:, 1]).astype(int), 0, cam.height - 1)
    behind = z - depth[v, u]
    # negative TSDF = just behind the observed surface (within the truncation, up to pixel size: the
    # voxels of the z = 0 layer lie on the table, whose depth at this image's 2.7 mm pixels changes by
    # up to ~8 mm across a pixel where the view grazes it)
    assert np.mean((behind > -0.008) & (behind < TSDF_TRUNCATION + 0.008)) > 0.95
    uv, z = cam.project(centres[(tsdf > 0) & (tsdf < 1)])
    u = np.clip(np.rint(uv[:, 0]).astype(int), 0, cam.width - 1)
    v = np.clip(np.rint(uv[:, 1]).astype(int), 0, cam.height - 1)
    assert np.mean(z < depth[v, u] + 0.004) > 0.95  # positive band in front of the surface


def _winding_number(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Generalised winding number of closed surfaces at points (van Oosterom-Strackee solid angles);
    a union of overlapping closed parts gives >= 1 inside and 0 outside."""
    total = np.zeros(len(points))
    tri = vertices[faces]
    for chunk in np.array_split(np.arange(len(points)), max(1, len(points) // 256)):
        a, b, c = (tri[None, :, i] - points[chunk, None] for i in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", b, c) * la \
            + np.einsum("pfi,pfi->pf", c, a) * lb
        total[chunk] = (2 * np.arctan2(det, den)).sum(-1) / (4 * np.pi)
    return total


def test_mask_is_the_solid_at_the_pose(dataset):
    """mask_3d labels a voxel with object k exactly when k's solid at its pose meets the voxel-sized cube
    around the voxel's sample point (checked on the cube's 4 x 4 x 4 sub-samples with winding numbers)."""
    from dsr_bench.constants import MASK_SUBSAMPLES, VOXEL_SIZE
    from dsr_bench.geometry import voxel_to_world

    rng = np.random.default_rng(0)
    k4 = MASK_SUBSAMPLES
    sub = ((np.arange(k4) + 0.5) / k4 - 0.5) * VOXEL_SIZE
    offsets = np.stack(np.meshgrid(sub, sub, sub, indexing="ij"), -1).reshape(-1, 3)
    with SequenceReader(dataset / "seq_0000.h5") as seq:
        mask, poses = seq.read("mask_3d", 1), seq.read("object_poses", 1)
        for k in range(seq.num_objects):
            vertices, faces = seq.mesh(k)
            m = pose_to_matrix(poses[k])
            world = vertices.astype(np.float64) @ m[:3, :3].T + m[:3, 3]
            labelled = np.argwhere(mask == k + 1)
            lo, hi = labelled.min(0) - 2, labelled.max(0) + 3
            box = np.argwhere(np.ones(tuple(hi - lo), bool)) + lo
            box = box[np.all((box >= 0) & (box < mask.shape), axis=1)]
            label = mask[tuple(box.T)]
            for chosen, expect in ((box[label == k + 1], True), (box[label == 0], False)):
                chosen = chosen[rng.choice(len(chosen), min(len(chosen), 150), replace=False)]
                points = (voxel_to_world(chosen)[:, None, :] + offsets).reshape(-1, 3)
                meets = (_winding_number(points, world, faces) > 0.5).reshape(len(chosen), -1).any(1)
                assert np.mean(meets == expect) > 0.99, (k, expect, np.mean(meets == expect))


def test_deterministic_across_workers_and_shards(dataset, tmp_path):
    assert _generate(tmp_path / "w2", "--workers", "2", "--cameras", "front,back") == 0
    reference = _digests(dataset)
    assert _digests(tmp_path / "w2") == reference
    shard_dir = tmp_path / "sharded"
    assert _generate(shard_dir, "--shard", "1/2", "--cameras", "front,back") == 0
    assert not (shard_dir / "manifest.json").exists()  # shard 0 still missing
    assert _generate(shard_dir, "--shard", "0/2", "--cameras", "front,back") == 0
    assert _digests(shard_dir) == reference and (shard_dir / "manifest.json").exists()


@pytest.mark.skipif(os.uname().machine not in ("x86_64", "AMD64"), reason="OPENBLAS_CORETYPE names x86-64 kernels")
def test_identical_whatever_blas_kernel_the_cpu_selects(dataset, tmp_path):
    """Pinned splits must reproduce on any x86-64 CPU: OpenBLAS picks its kernels (and summation order) per
    CPU, so the ground truth may not go through BLAS. Force an SSE-era and an AVX2 kernel set and compare."""
    reference = _digests(dataset)
    for coretype in ("Nehalem", "Haswell"):
        out = tmp_path / coretype
        cmd = [sys.executable, "-m", "dsr_bench.cli", "generate", *SMALL, "-n", "2", "--out", str(out), "--cameras",
               "front,back"]
        env = {**os.environ, "OPENBLAS_CORETYPE": coretype}
        subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        assert _digests(out) == reference, f"content differs with OPENBLAS_CORETYPE={coretype}"


def test_resume_after_kill_9(tmp_path):
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "dsr_bench.cli", "generate", *SMALL, "-n", "3", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and not (out / "seq_0000.h5").exists():
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert (out / "seq_0000.h5").exists()
    first = (out / "seq_0000.h5").stat().st_mtime_ns
    assert not (out / "seq_0002.h5").exists() and not (out / "manifest.json").exists()
    assert _generate(out, n=3) == 0
    assert (out / "seq_0000.h5").stat().st_mtime_ns == first  # skipped, not regenerated
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []
    fresh = tmp_path / "fresh"
    assert _generate(fresh, n=3) == 0
    assert _digests(out) == _digests(fresh)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--objects", "teapots", "-n", "1"], "teapots"),
        (["--objects", "procedural", "-n", "1", "--shard", "2/2"], "--shard"),
        (["--objects", "procedural", "-n", "1", "--objects-per-scene", "9"], "--objects-per-scene"),
        (["--objects", "procedural", "-n", "0"], "--num-sequences"),
        (["--objects", "procedural", "-n", "1", "--policy", "greedy"], "--policy"),
        (["--objects", "procedural", "-n", "1", "--cameras", "side"], "--cameras"),
        (["--split", "no-such-split"], "unknown split"),
        (["--split", "procedural-mini", "--objects", "cube"], "--split procedural-mini fixes --objects"),
    ],
)
def test_bad_inputs_fail_with_one_line_and_write_nothing(tmp_path, capsys, args, message):
    out = tmp_path / "never"
    assert main(["generate", *args, "--out", str(out)]) != 0
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_missing_external_meshes_name_flag_and_variable(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("DSR_BENCH_SHAPENET", raising=False)
    out = tmp_path / "never"
    assert main(["generate", "--objects", "shapenet", "-n", "1", "--out", str(out),
                 "--object-root", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err
    assert "--object-root" in err and "DSR_BENCH_SHAPENET" in err
    assert not out.exists()


def test_existing_directory_from_other_arguments_is_refused(dataset, tmp_path, capsys):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    assert main(["generate", "--objects", "procedural", "--steps", "2", "-n", "2", "--out", str(copy)]) == 2
    assert "different arguments" in capsys.readouterr().err


def test_plan_from_arguments_fills_a_split_or_the_defaults(tmp_path):
    from dsr_bench.constants import DEFAULT_OBJECTS_PER_SCENE, DEFAULT_STEPS
    from dsr_bench.dataset.splits import get_split
    from dsr_bench.errors import UserError
    from dsr_bench.generators.run import plan_from_arguments

    spec = get_split("procedural-mini")
    plan = plan_from_arguments(split="procedural-mini", workers=2, shard="1/3", cameras="front, back")
    assert plan.out == Path("data") / "procedural-mini" and plan.split == "procedural-mini"
    assert (plan.num_sequences, plan.seed, plan.shard, plan.workers) == (spec.num_sequences, spec.base_seed, (1, 3), 2)
    assert (plan.config.objects, plan.config.steps, plan.config.objects_per_scene, plan.config.policy) == (
        spec.objects, spec.steps, spec.objects_per_scene, spec.policy)
    assert plan.config.cameras == ("front", "back")
    plan = plan_from_arguments(objects="cube", num_sequences=3, out=tmp_path, object_root=tmp_path)
    assert (plan.split, plan.seed, plan.shard, plan.config.policy) == ("all", 0, (0, 1), "heuristic")
    assert (plan.config.steps, plan.config.objects_per_scene) == (DEFAULT_STEPS, DEFAULT_OBJECTS_PER_SCENE)
    assert plan.config.object_root == str(tmp_path) and plan.config.cameras == ("front",)
    with pytest.raises(UserError, match="--split procedural-mini fixes --seed, --policy"):
        plan_from_arguments(split="procedural-mini", seed=1, policy="random")
    with pytest.raises(UserError, match="^missing --out DIR: give it, or a named --split instead$"):
        plan_from_arguments(objects="cube", num_sequences=3)
    with pytest.raises(UserError, match="^missing --objects SET and --out DIR: give them, or a named --split"):
        plan_from_arguments(num_sequences=3)


def test_generate_names_what_is_missing_and_where_shapenet_comes_from(monkeypatch, capsys):
    """`generate --objects shapenet` alone names the two options it lacks, not the one given, and says at once
    that ShapeNet needs --object-root and where to get it; with the variable set or the root given it does not."""
    from dsr_bench.cli import main

    monkeypatch.delenv("DSR_BENCH_SHAPENET", raising=False)
    assert main(["generate", "--objects", "shapenet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: missing --num-sequences N and --out DIR: give them, or a named --split instead; "
                          "--objects shapenet also needs --object-root PATH (or $DSR_BENCH_SHAPENET), your copy of "
                          "ShapeNetCore v2 (https://shapenet.org") and err.count("\n") == 1
    monkeypatch.setenv("DSR_BENCH_SHAPENET", "/somewhere")
    assert main(["generate", "--objects", "shapenet", "-n", "2"]) == 2
    assert capsys.readouterr().err == "error: missing --out DIR: give it, or a named --split instead\n"


def test_needs_writing_skips_same_arguments_and_refuses_others(tmp_path):
    from dsr_bench.errors import UserError
    from dsr_bench.generators.run import needs_writing

    path = tmp_path / "out"
    recorded = {"seed": 1}
    assert needs_writing(path, {"seed": 1}, lambda p: recorded, "different") is True  # absent
    path.write_text("x")
    assert needs_writing(path, {"seed": 1}, lambda p: recorded, "different") is False  # same: skip
    with pytest.raises(UserError, match="^different$"):
        needs_writing(path, {"seed": 2}, lambda p: recorded, "different")
    assert needs_writing(path, {"seed": 2}, lambda p: 1 / 0, "different", overwrite=True) is True  # never read
