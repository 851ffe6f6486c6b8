"""`dsr-bench validate`: check a dataset directory and report every problem at once.

Checks the manifest against the files (missing, extra, checksums, split files and checksums), every
file against the schema (format, version, attributes, shapes, dtypes, value ranges) and, unless
disabled, the ground truth against itself: flow recomputed from poses and amodal masks, flow zero
off objects, amodal masks at t + 1 against the masks at t moved by the flow, the TSDF's sign against
the front depth image, and content digests. A damaged file is a problem, never a crash.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dsr_bench.constants import GRID_SHAPE, NUM_DIRECTIONS, TSDF_TRUNCATION

#: Largest allowed difference (voxels) between stored flow and the rigid motion of the stored poses.
FLOW_TOLERANCE = 1e-3
#: The official release's flow is a difference of rounded voxel coordinates: within a voxel of ours.
OFFICIAL_FLOW_TOLERANCE = 1.0 + FLOW_TOLERANCE
#: Least fraction of negative TSDF voxels that must lie behind the depth image's surface (edges disagree).
TSDF_SIGN_AGREEMENT = 0.95
#: Least IoU between an object's amodal voxels at t + 1 and its voxels at t moved by the flow.
MASK_WARP_IOU = 0.9


def action_problems(actions: np.ndarray, shape: tuple[int, int] = GRID_SHAPE[:2]) -> list[str]:
    """What is wrong with actions (T, 3) [direction, row, col] on a (Y, X) action map (none: [])."""
    a = np.asarray(actions)
    if a.ndim != 2 or a.shape[1] != 3 or not np.issubdtype(a.dtype, np.integer):
        return [f"action: {a.dtype} array of shape {a.shape}, expected (T, 3) integers [direction, row, col]"]
    out = []
    if a.size and (a[:, 0].min() < 0 or a[:, 0].max() >= NUM_DIRECTIONS):
        out.append(f"action: direction outside 0..{NUM_DIRECTIONS - 1} (values {a[:, 0].min()}..{a[:, 0].max()})")
    if a.size and (a[:, 1:].min() < 0 or a[:, 1].max() >= shape[0] or a[:, 2].max() >= shape[1]):
        out.append(f"action: row/col outside 0..{shape[0] - 1}" if shape[0] == shape[1]
                   else f"action: row/col outside the {shape[0]} x {shape[1]} map")
    return out


@dataclass(frozen=True)
class Problem:
    """One problem found: where (a sequence name, a file, or 'dataset') and what."""

    where: str
    message: str


def schema_markdown_table() -> str:
    """The sequence schema (`dsr_bench.schema.SEQUENCE_SCHEMA`) as a markdown table for docs/format.md."""
    from dsr_bench.schema import SEQUENCE_SCHEMA

    rows = ["| dataset | shape | dtype | units | required | meaning |", "|---|---|---|---|---|---|"]
    for f in SEQUENCE_SCHEMA:
        name = f"cameras/<cam>/{f.name}" if f.camera else f.name
        required = "yes" if f.required else "no"
        rows.append(f"| `{name}` | ({', '.join(f.shape)}) | {f.dtype} | {f.units} | {required} | {f.description} |")
    return "\n".join(rows) + "\n"


# --- per-file checks ---------------------------------------------------------------------------------
def _guard(problems: list[str], label: str, check: Callable[[], list[str]]) -> None:
    """Run one check; a read error (truncated chunk, bad data) becomes a problem, not a crash."""
    try:
        problems += check()
    except Exception as exc:  # noqa: BLE001 - anything a damaged file raises
        problems.append(f"{label}: unreadable data ({type(exc).__name__}: {exc})")


def _finite(name: str, a: np.ndarray) -> list[str]:
    return [] if np.all(np.isfinite(a)) else [f"{name}: {int(np.sum(~np.isfinite(a)))} values are NaN or inf"]


def _range_checks(seq, ok: set[str]) -> dict[str, Callable[[], list[str]]]:
    """Value-range checks of the fields whose shape and dtype are right."""
    n = seq.num_objects

    def tsdf():
        a = seq.read("tsdf")
        out = _finite("tsdf", a)
        if not out and (a.min() < -1 or a.max() > 1):
            out.append(f"tsdf: values in [{a.min():.3g}, {a.max():.3g}], expected [-1, 1]")
        return out

    def mask_3d():
        m = int(seq.read("mask_3d").max())
        return [f"mask_3d: instance id {m} > num_objects {n}"] if m > n else []

    def camera_mask(name):
        def check():
            m = int(seq.read(name).max())
            return [f"{name}: instance id {m} > num_objects {n}"] if m > n else []
        return check

    def poses():
        a = seq.read("object_poses")
        out = _finite("object_poses", a)
        if not out:
            norm = np.linalg.norm(a[..., 3:], axis=-1)
            if not np.allclose(norm, 1.0, atol=1e-4):
                out.append(f"object_poses: quaternion norms in [{norm.min():.4g}, {norm.max():.4g}], expected 1")
        return out

    def action():
        return action_problems(seq.read("action"))

    def visible():
        a = seq.read("visible_fraction")
        out = _finite("visible_fraction", a)
        if not out and (a.min() < 0 or a.max() > 1):
            out.append(f"visible_fraction: values in [{a.min():.3g}, {a.max():.3g}], expected [0, 1]")
        return out

    checks = {"tsdf": tsdf, "mask_3d": mask_3d, "object_poses": poses, "action": action,
              "visible_fraction": visible}
    for name in ("scene_flow_3d", "push_start", "push_end", "heightmap"):
        checks[name] = (lambda name=name: _finite(name, seq.read(name)))
    for cam in seq.cameras:
        checks[f"cameras/{cam}/mask"] = camera_mask(f"cameras/{cam}/mask")
        flow2d = f"cameras/{cam}/scene_flow_2d"
        checks[flow2d] = (lambda name=flow2d: _finite(name, seq.read(name)))
    return {name: check for name, check in checks.items() if name in ok}


def _check_flow(seq) -> list[str]:
    """Stored flow against the rigid motion of the stored poses, and zero off objects."""
    from dsr_bench.groundtruth import rigid_scene_flow_3d

    problems = []
    poses = seq.read("object_poses")
    official = seq.attrs.get("source") == "official-import"
    tolerance = OFFICIAL_FLOW_TOLERANCE if official else FLOW_TOLERANCE
    for t in range(seq.num_steps):
        mask = seq.read("mask_3d", t)
        flow = seq.read("scene_flow_3d", t)
        outside = np.count_nonzero(np.any(flow[:, mask == 0] != 0, axis=0))
        if outside:
            problems.append(f"scene_flow_3d[{t}]: {outside} voxels outside every object have non-zero flow")
        err = float(np.abs(flow - rigid_scene_flow_3d(mask, poses[t], poses[t + 1])).max())
        if err > tolerance:
            problems.append(f"scene_flow_3d[{t}]: differs from the rigid motion of the stored poses by "
                            f"{err:.3g} voxels (tolerance {tolerance:g})")
    return problems


def mask_warp_iou(mask_t: np.ndarray, flow_t: np.ndarray, mask_next: np.ndarray, obj: int) -> float | None:
    """Voxel-tolerant IoU of object `obj`'s voxels at t + 1 with its voxels at t moved by the flow.

    mask_t, mask_next: (Y, X, Z) ids; flow_t: (3, Y, X, Z) voxels (dy, dx, dz). Moved voxel centres
    are rounded to voxels (those leaving the grid are dropped). A voxel of either set matches if the
    other set has a voxel within one voxel (26-neighbourhood): rounding a rotated solid's voxels
    leaves holes and doubles that a plain IoU would count (it drops to ~0.6 for valid 30-degree
    turns). Returns (matched voxels of both sets) / (voxels of both sets), or None if both are empty.
    """
    from scipy import ndimage

    src = np.argwhere(mask_t == obj)
    moved = np.rint(src + flow_t[:, src[:, 0], src[:, 1], src[:, 2]].T).astype(np.int64)
    moved = moved[np.all((moved >= 0) & (moved < np.array(mask_t.shape)), axis=1)]
    target = np.argwhere(mask_next == obj)
    if len(moved) == 0 and len(target) == 0:
        return None
    if len(moved) == 0 or len(target) == 0:
        return 0.0
    both = np.concatenate([moved, target])
    lo = both.min(0) - 1
    shape = tuple(both.max(0) - lo + 2)
    warped, truth = np.zeros(shape, bool), np.zeros(shape, bool)
    warped[tuple((moved - lo).T)] = True
    truth[tuple((target - lo).T)] = True
    cube = np.ones((3, 3, 3), bool)
    matched = np.count_nonzero(warped & ndimage.binary_dilation(truth, cube))
    matched += np.count_nonzero(truth & ndimage.binary_dilation(warped, cube))
    return matched / (np.count_nonzero(warped) + np.count_nonzero(truth))


def _check_mask_warp(seq) -> list[str]:
    problems = []
    for t in range(seq.num_steps):
        mask_t, flow_t, mask_next = seq.read("mask_3d", t), seq.read("scene_flow_3d", t), seq.read("mask_3d", t + 1)
        for obj in range(1, seq.num_objects + 1):
            iou = mask_warp_iou(mask_t, flow_t, mask_next, obj)
            if iou is not None and iou < MASK_WARP_IOU:
                problems.append(f"mask_3d[{t + 1}]: object {obj} overlaps its voxels at {t} moved by the flow "
                                f"with IoU {iou:.2f} (within a voxel) < {MASK_WARP_IOU}")
    return problems


def _check_tsdf_sign(seq, camera: str = "front") -> list[str]:
    """Voxels with tsdf < 0 must lie behind the depth image's surface, within the truncation."""
    from dsr_bench.geometry import voxel_centers

    problems = []
    cam = seq.camera(camera)
    centres = voxel_centers()
    for t in range(seq.num_steps + 1):
        tsdf = seq.read("tsdf", t)
        depth = seq.read(f"cameras/{camera}/depth", t)
        neg = centres[tsdf < 0]
        if len(neg) == 0:
            continue
        uv, z = cam.project(neg)
        # at the stored image's resolution a pixel spans ~3 mm, so a voxel agrees when any of the four pixels
        # around its projection has a surface in front of it (edges of objects alias otherwise), with 6 mm slack
        u0, v0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = np.zeros(len(neg), dtype=bool)
        for du in (0, 1):
            for dv in (0, 1):
                d = depth[np.clip(v0 + dv, 0, cam.height - 1), np.clip(u0 + du, 0, cam.width - 1)]
                behind = z - d
                ok |= (d > 0) & (behind > -0.006) & (behind < TSDF_TRUNCATION + 0.012)
        agree = float(np.mean(ok))
        if agree < TSDF_SIGN_AGREEMENT:
            problems.append(f"tsdf[{t}]: only {agree:.0%} of negative voxels lie behind the {camera} depth "
                            f"image's surface (expected >= {TSDF_SIGN_AGREEMENT:.0%})")
    return problems


def _open(path: str | Path):
    """(reader, None) or (None, the problem) for a sequence file."""
    from dsr_bench.sequence import SequenceFormatError, SequenceReader

    try:
        return SequenceReader(path), None
    except SequenceFormatError as exc:
        return None, str(exc).replace(f"{path}: ", "")
    except KeyError as exc:
        return None, f"missing root attribute {exc}"
    except Exception as exc:  # noqa: BLE001 - truncated or garbage files
        return None, f"unreadable: {type(exc).__name__}: {exc}"


def schema_problems(seq) -> tuple[list[str], set[str]]:
    """Structural problems of an open sequence (missing datasets, shapes, dtypes) and the names of
    the datasets that passed. Shared by `validate` and the viewer."""
    from dsr_bench.schema import FIELDS, check_array, dataset_path, resolve_shape

    problems: list[str] = []
    ok: set[str] = set()
    for field in FIELDS.values():
        for cam in (list(seq.cameras) if field.camera else [None]):
            name = dataset_path(field, cam)
            if name not in seq:
                if field.required:
                    problems.append(f"missing dataset {name!r}")
                continue
            try:
                image = (int(seq.cameras[cam]["height"]), int(seq.cameras[cam]["width"])) if cam else None
                shape = (resolve_shape(field, seq.num_steps, seq.num_objects, image) if image
                         else resolve_shape(field, seq.num_steps, seq.num_objects))
                found = check_array(field, seq.dataset(name), shape, name)
            except Exception as exc:  # noqa: BLE001 - malformed camera attributes, unreadable dataset
                found = [f"{name}: cannot check ({type(exc).__name__}: {exc})"]
            problems += found
            if not found:
                ok.add(name)
    return problems, ok


def validate_sequence(path: str | Path, check_gt: bool = True, expected_digest: str | None = None) -> list[str]:
    """Every problem of one sequence file (empty if none).

    Schema (attributes, every dataset's shape and dtype), value ranges, and with `check_gt` the
    ground-truth consistency and the content digest; `expected_digest` (the manifest's) is compared too.
    """
    from dsr_bench.manifest import sequence_content_digest
    from dsr_bench.schema import REQUIRED_ATTRS

    seq, problem = _open(path)
    if seq is None:
        return [problem]
    problems: list[str] = []
    try:
        problems += [f"missing attribute {a!r}" for a in REQUIRED_ATTRS if a not in seq.attrs]
        found, ok = schema_problems(seq)
        problems += found
        range_problems: list[str] = []
        for name, check in _range_checks(seq, ok).items():
            _guard(range_problems, name, check)
        problems += range_problems
        if check_gt:
            gt_ready = not range_problems and {"mask_3d", "scene_flow_3d", "object_poses"} <= ok
            if gt_ready:
                _guard(problems, "scene_flow_3d", lambda: _check_flow(seq))
                _guard(problems, "mask_3d", lambda: _check_mask_warp(seq))
            if not range_problems and "tsdf" in ok and "cameras/front/depth" in ok:
                _guard(problems, "tsdf", lambda: _check_tsdf_sign(seq))
        if check_gt or expected_digest is not None:
            stored = seq.attrs.get("content_sha256")
            try:
                actual = sequence_content_digest(path)
            except Exception as exc:  # noqa: BLE001
                problems.append(f"content digest: unreadable data ({type(exc).__name__}: {exc})")
            else:
                if stored is not None and actual != stored:
                    problems.append("content digest does not match the arrays (file modified after writing)")
                if expected_digest is not None and actual != expected_digest:
                    problems.append("content digest differs from the manifest's")
    finally:
        seq.close()
    return problems


def _validate_one(args: tuple[str, bool, str | None]) -> tuple[str, list[str]]:
    path, check_gt, digest = args
    return Path(path).stem, validate_sequence(path, check_gt, digest)


# --- the dataset -------------------------------------------------------------------------------------
def _check_manifest(data_dir: Path, manifest: dict, files: dict[str, Path]) -> tuple[list[Problem], dict[str, str]]:
    """Manifest against the files and split files; returns (problems, manifest digests by name)."""
    from dsr_bench.errors import UserError
    from dsr_bench.manifest import file_sha256, split_digest

    problems: list[Problem] = []
    listed = {s["name"]: s for s in manifest["sequences"]}
    for name in sorted(set(listed) - set(files)):
        problems.append(Problem(name, "listed in the manifest but the file is missing"))
    for name in sorted(set(files) - set(listed)):
        problems.append(Problem(name, "file present but not in the manifest (run `dsr-bench manifest DIR`)"))
    digests: dict[str, str] = {}
    for name in sorted(set(files) & set(listed)):
        if file_sha256(files[name]) != listed[name]["sha256"]:
            problems.append(Problem(name, "SHA-256 of the file differs from the manifest"))
        digests[name] = listed[name]["content_sha256"]
    splits = manifest.get("splits", {})
    for split, info in sorted(splits.items()):
        path = data_dir / info["file"]
        if not path.is_file():
            problems.append(Problem(info["file"], f"split file of {split!r} is missing"))
            continue
        names = [line.strip() for line in path.read_text().splitlines() if line.strip()]
        if names != info["names"]:
            problems.append(Problem(info["file"], "split file differs from the manifest"))
        problems += [Problem(info["file"], f"names {n!r}, which has no file") for n in names if n not in files]
        try:
            if split_digest(manifest, split) != info["content_sha256"]:
                problems.append(Problem(info["file"], f"split checksum of {split!r} in the manifest does not match "
                                                      "its sequences' content digests"))
        except UserError as exc:
            problems.append(Problem(info["file"], str(exc)))
    for path in sorted((data_dir / "splits").glob("*.txt")):
        if path.stem not in splits:
            problems.append(Problem(f"splits/{path.name}",
                                    "split file not in the manifest (run `dsr-bench manifest DIR`)"))
    return problems + _check_pinned(manifest), digests


def _check_pinned(manifest: dict) -> list[Problem]:
    """A named benchmark split must reproduce the toolkit's pinned digests, sequence by sequence."""
    from dsr_bench.errors import UserError
    from dsr_bench.manifest import split_digest
    from dsr_bench.splits import pinned_digests

    problems = []
    digests = {s["name"]: s["content_sha256"] for s in manifest["sequences"]}
    for split, pin in pinned_digests().items():
        if split not in manifest.get("splits", {}):
            continue
        try:
            if split_digest(manifest, split) == pin["checksum"]:
                continue
        except UserError:
            continue  # reported by the manifest checks
        differing = [n for n, d in pin["sequences"].items() if digests.get(n) != d]
        problems.append(Problem(f"splits/{split}.txt", f"differs from the toolkit's pinned {split} in "
                                f"{len(differing)} sequences (e.g. {', '.join(differing[:3])}); regenerate it with "
                                f"`dsr-bench generate --split {split}` on this toolkit version"))
    return problems


def validate_dataset(data_dir: str | Path, check_gt: bool = True, workers: int = 1) -> tuple[list[Problem], int]:
    """(every problem found, number of sequence files checked) for a dataset directory."""
    from dsr_bench.errors import UserError
    from dsr_bench.manifest import MANIFEST_NAME, load_manifest

    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise UserError(f"dataset directory not found: {data_dir}")
    if workers < 1:
        raise UserError(f"--workers {workers}: must be at least 1")
    problems: list[Problem] = []
    files = {p.stem: p for p in sorted(data_dir.glob("seq_*.h5"))}
    digests: dict[str, str] = {}
    try:
        manifest = load_manifest(data_dir)
    except UserError as exc:
        problems.append(Problem(MANIFEST_NAME, str(exc)))
    else:
        found, digests = _check_manifest(data_dir, manifest, files)
        problems += found
    jobs = [(str(p), check_gt, digests.get(name)) for name, p in files.items()]
    if workers > 1 and len(jobs) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp.get_context("spawn")) as pool:
            results = list(pool.map(_validate_one, jobs))
    else:
        results = [_validate_one(j) for j in jobs]
    for name, found in results:
        problems += [Problem(name, m) for m in found]
    if not files:
        problems.append(Problem("dataset", f"no seq_*.h5 files in {data_dir}"))
    return problems, len(files)
