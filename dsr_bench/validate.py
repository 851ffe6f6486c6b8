"""`dsr-bench validate`: check a dataset directory and report every problem at once.

Checks the manifest against the files (missing, extra, checksums), every file against the schema
(format, version, attributes, shapes, dtypes, value ranges) and, unless disabled, the ground truth
against itself: flow recomputed from poses and amodal masks, flow zero off objects, the TSDF's sign
against the front depth image, and content digests.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dsr_bench.constants import GRID_SHAPE, NUM_DIRECTIONS, TSDF_TRUNCATION

FLOW_TOLERANCE = 1e-3  # voxels
TSDF_SIGN_AGREEMENT = 0.95


@dataclass(frozen=True)
class Problem:
    """One problem found: where (a sequence name, a file, or 'dataset') and what."""

    where: str
    message: str


def _check_ranges(seq, name: str) -> list[str]:
    problems = []
    n = seq.num_objects
    tsdf = seq.read("tsdf")
    if not np.all(np.isfinite(tsdf)) or tsdf.min() < -1 or tsdf.max() > 1:
        problems.append("tsdf: values outside [-1, 1] or not finite")
    mask = seq.read("mask_3d")
    if mask.max() > n:
        problems.append(f"mask_3d: instance id {int(mask.max())} > num_objects {n}")
    flow = seq.read("scene_flow_3d")
    if not np.all(np.isfinite(flow)):
        problems.append("scene_flow_3d: NaN or inf")
    poses = seq.read("object_poses")
    if not np.all(np.isfinite(poses)):
        problems.append("object_poses: NaN or inf")
    elif not np.allclose(np.linalg.norm(poses[..., 3:], axis=-1), 1.0, atol=1e-4):
        problems.append("object_poses: quaternions are not unit length")
    action = seq.read("action")
    if action.size and (action[:, 0].min() < 0 or action[:, 0].max() >= NUM_DIRECTIONS
                        or action[:, 1:].min() < 0 or action[:, 1:].max() >= GRID_SHAPE[0]):
        problems.append("action: direction outside 0..7 or cell outside 0..127")
    if "visible_fraction" in seq:
        vis = seq.read("visible_fraction")
        if np.any(vis < 0) or np.any(vis > 1):
            problems.append("visible_fraction: values outside [0, 1]")
    return problems


def _check_ground_truth(seq) -> list[str]:
    from dsr_bench.geometry import voxel_centers
    from dsr_bench.groundtruth import rigid_scene_flow_3d

    problems = []
    poses = seq.read("object_poses")
    # the official release's flow is a difference of rounded voxel coordinates: within a voxel of ours
    tolerance = 1.0 + FLOW_TOLERANCE if seq.attrs.get("source") == "official-import" else FLOW_TOLERANCE
    for t in range(seq.num_steps):
        mask = seq.read("mask_3d", t)
        flow = seq.read("scene_flow_3d", t)
        expected = rigid_scene_flow_3d(mask, poses[t], poses[t + 1])
        err = np.abs(flow - expected).max()
        if err > tolerance:
            problems.append(f"scene_flow_3d[{t}]: differs from the rigid motion of the stored poses by {err:.3g} voxels")
    if "cameras/front/depth" in seq:
        cam = seq.camera("front")
        centres = voxel_centers()
        for t in range(seq.num_steps + 1):
            tsdf = seq.read("tsdf", t)
            depth = seq.read("cameras/front/depth", t)
            neg = centres[tsdf < 0]
            if len(neg) == 0:
                continue
            uv, z = cam.project(neg)
            u = np.clip(np.rint(uv[:, 0]).astype(int), 0, cam.width - 1)
            v = np.clip(np.rint(uv[:, 1]).astype(int), 0, cam.height - 1)
            d = depth[v, u]
            behind = z - d
            # at the stored image's resolution: a pixel spans ~3 mm, so allow that much slack
            agree = np.mean((d > 0) & (behind > -0.006) & (behind < TSDF_TRUNCATION + 0.012))
            if agree < TSDF_SIGN_AGREEMENT:
                problems.append(f"tsdf[{t}]: only {agree:.0%} of negative voxels lie behind the depth image's surface")
    return problems


def validate_sequence(path: str | Path, check_gt: bool = True, expected_digest: str | None = None) -> list[str]:
    """Every problem of one sequence file (empty if none)."""
    from dsr_bench.manifest import sequence_content_digest
    from dsr_bench.schema import FIELDS, REQUIRED_ATTRS, check_array, dataset_path, resolve_shape
    from dsr_bench.sequence import SequenceReader

    try:
        seq = SequenceReader(path)
    except Exception as exc:
        return [f"unreadable: {exc}"]
    problems: list[str] = []
    try:
        problems += [f"missing attribute {a!r}" for a in REQUIRED_ATTRS if a not in seq.attrs]
        for field in FIELDS.values():
            cams = list(seq.cameras) if field.camera else [None]
            for cam in cams:
                name = dataset_path(field, cam)
                if name not in seq:
                    if field.required:
                        problems.append(f"missing dataset {name!r}")
                    continue
                image = (seq.cameras[cam]["height"], seq.cameras[cam]["width"]) if cam else None
                shape = resolve_shape(field, seq.num_steps, seq.num_objects, image) if cam else resolve_shape(
                    field, seq.num_steps, seq.num_objects)
                problems += check_array(field, seq.dataset(name), shape, name)
        if problems:
            return problems
        problems += _check_ranges(seq, seq.name)
        if check_gt and not problems:
            problems += _check_ground_truth(seq)
        stored = seq.attrs.get("content_sha256")
        if check_gt or expected_digest is not None:
            actual = sequence_content_digest(path)
            if stored is not None and actual != stored:
                problems.append("content digest does not match the arrays (file modified after writing)")
            if expected_digest is not None and actual != expected_digest:
                problems.append("content digest differs from the manifest's")
    except Exception as exc:  # truncated chunks and the like surface on read
        problems.append(f"unreadable data: {type(exc).__name__}: {exc}")
    finally:
        seq.close()
    return problems


def _validate_one(args) -> tuple[str, list[str]]:
    path, check_gt, digest = args
    return Path(path).stem, validate_sequence(path, check_gt, digest)


def validate_dataset(data_dir: str | Path, check_gt: bool = True, workers: int = 1) -> tuple[list[Problem], int]:
    """(every problem found, number of sequence files checked) for a dataset directory."""
    from dsr_bench.errors import UserError
    from dsr_bench.manifest import MANIFEST_NAME, file_sha256, load_manifest

    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise UserError(f"dataset directory not found: {data_dir}")
    problems: list[Problem] = []
    files = {p.stem: p for p in sorted(data_dir.glob("seq_*.h5"))}
    manifest = None
    try:
        manifest = load_manifest(data_dir)
    except UserError as exc:
        problems.append(Problem(MANIFEST_NAME, str(exc)))
    digests: dict[str, str] = {}
    if manifest is not None:
        listed = {s["name"]: s for s in manifest["sequences"]}
        for name in sorted(set(listed) - set(files)):
            problems.append(Problem(name, "listed in the manifest but the file is missing"))
        for name in sorted(set(files) - set(listed)):
            problems.append(Problem(name, "file present but not in the manifest (run `dsr-bench manifest DIR`)"))
        for name in sorted(set(files) & set(listed)):
            if file_sha256(files[name]) != listed[name]["sha256"]:
                problems.append(Problem(name, "SHA-256 of the file differs from the manifest"))
            digests[name] = listed[name]["content_sha256"]
        for split, info in manifest.get("splits", {}).items():
            path = data_dir / info["file"]
            if not path.is_file():
                problems.append(Problem(info["file"], f"split file of {split!r} is missing"))
                continue
            names = [line.strip() for line in path.read_text().splitlines() if line.strip()]
            if names != info["names"]:
                problems.append(Problem(info["file"], "split file differs from the manifest"))
            problems += [Problem(info["file"], f"names {n!r}, which has no file") for n in names if n not in files]
    jobs = [(str(p), check_gt, digests.get(name)) for name, p in files.items()]
    if workers > 1 and len(jobs) > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers) as pool:
            results = list(pool.map(_validate_one, jobs))
    else:
        results = [_validate_one(j) for j in jobs]
    for name, found in results:
        problems += [Problem(name, m) for m in found]
    if not files and manifest is None:
        problems.append(Problem("dataset", f"no seq_*.h5 files in {data_dir}"))
    return problems, len(files)
