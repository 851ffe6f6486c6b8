"""`dsr-bench import-capture`: a folder of a real rig's PNGs -> a capture directory (`dsr_bench.dataset.capture`).

The folder (docs/annotator.md, "Real captures in"):

    SRC/rig.json                 cameras (intrinsics, distortion, depth scale, optional extrinsics), board, objects
    SRC/front_color_<N>.png      (H, W, 3) 8-bit RGB (not RGBA), one per step N (any zero padding: 0, 000017, ...)
    SRC/front_depth_<N>.png      (H, W) 16-bit depth in depth units, aligned to the colour image (same pixels, same
    SRC/back_color_<N>.png       intrinsics: the RealSense's "align depth to colour"), 0 = no depth
    SRC/back_depth_<N>.png
    SRC/pushes.json              the robot's log of the T pushes (annotator.pushes), or --pushes

Steps are the numbers N sorted numerically and renumbered 0..T; every camera needs colour and depth at the same
N, and the numbers run without a gap (a gap is a dropped step, which the push count cannot show when its push was
dropped too), unless the push log gives each push's "between": [N, M] (then N may be frame numbers, checked against
it). Images with distortion coefficients are undistorted (colour bilinear, depth nearest: a depth is never mixed
with its neighbours) onto the same fx, fy, cx, cy. Extrinsics come from the rig file or from the ChArUco board
(`annotator.calibrate`); the front camera must see the whole grid. Everything is checked before anything is
written, and the capture is written atomically (`write_capture`). The output is checked to be writable first, and
every input before it is used (`annotator.inputs`): JSON values of the right type and range, PNG sizes from their
headers, PNGs whole (chunk CRCs, IEND), paths that stay inside SRC, capture and object names that are plain names.

A folder of RealSense recordings instead (front.bag or front.db3, back.bag or back.db3) is the other form
(`annotator.realsense`): `import_capture` dispatches on the folder's content; what both forms share (the rig file,
the board calibration, undistortion) is `annotator.rig`.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from dsr_bench.annotator.inputs import (MAX_IMAGE_SIDE, finite, image_side, inside, json_text, numbers, plain_name,
                                        png_intact, png_shape, resolved_inside)
from dsr_bench.annotator.rig import (PUSHES_FILE, calibrate_cameras, capture_name, check_out, default_file, load_rig,
                                     read_objects, rig_error, undistort, undistort_maps)
from dsr_bench.constants import CAMERAS, MODEL_CAMERA
from dsr_bench.dataset.capture import CaptureCamera, parse_camera, write_capture
from dsr_bench.errors import UserError

#: Camera names a rig may use: the benchmark's cameras (`dsr_bench.constants.CAMERAS`), `front` (MODEL_CAMERA, the
#: view models see) required, the others (`back`) for annotation only.
CAMERA_NAMES = tuple(CAMERAS)
#: File names of the step images: <camera>_<color|depth>_<N>.png.
IMAGE_PATTERN = re.compile(r"^(?P<camera>[A-Za-z0-9]+)_(?P<kind>color|depth)_(?P<step>\d+)\.png$")


def _number(path: Path, where: str, spec: dict, key: str, positive: bool = True) -> float:
    """A rig file's number: a finite JSON number (not true / false, not a string such as "912"), positive if asked."""
    if key not in spec:
        raise rig_error(path, f"{where} lacks {key!r}")
    value = spec[key]
    if not finite(value) or (positive and value <= 0):
        raise rig_error(path, f"{where} {key!r} must be a finite{' positive' if positive else ''} number (a JSON "
                               f"number, not {json.dumps(value)[:40]})")
    return float(value)


def read_camera(path: Path, name: str, spec) -> tuple[CaptureCamera, np.ndarray | None, bool]:
    """(camera, distortion (5,) k1 k2 p1 p2 k3 or None, whether its extrinsics were given) of one rig camera. A
    camera without extrinsics gets the identity until the board calibrates it."""
    where = f"camera {name!r}"
    if not isinstance(spec, dict):
        raise rig_error(path, f"{where} must be an object with fx, fy, cx, cy, width, height, depth_scale")
    fx, fy = _number(path, where, spec, "fx"), _number(path, where, spec, "fy")
    cx, cy = _number(path, where, spec, "cx", False), _number(path, where, spec, "cy", False)
    for key in ("width", "height"):
        if not image_side(spec.get(key)):
            raise rig_error(path, f"{where} {key!r} must be a whole number of pixels 1..{MAX_IMAGE_SIDE}, got "
                                   f"{json.dumps(spec.get(key))[:40]}")
    width, height = spec["width"], spec["height"]
    scale = _number(path, where, spec, "depth_scale")
    dist = None
    if spec.get("distortion") is not None:
        if not numbers(spec["distortion"], (5,)):
            raise rig_error(path, f"{where} distortion must be OpenCV's 5 coefficients [k1, k2, p1, p2, k3]")
        dist = np.asarray(spec["distortion"], np.float64)
        dist = None if not dist.any() else dist
    given = spec.get("extrinsics") is not None
    if given and not numbers(spec["extrinsics"], (4, 4)):
        raise rig_error(path, f"{where} extrinsics must be a 4x4 matrix of numbers (camera-to-table, metres, "
                               "row-major)")
    full = {"height": int(height), "width": int(width), "intrinsics": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
            "extrinsics": spec["extrinsics"] if given else np.eye(4).tolist(), "depth_scale": scale}
    try:
        camera = parse_camera(path, name, full)
    except UserError as exc:
        raise rig_error(path, str(exc).split(": ", 1)[-1] + " (extrinsics: camera-to-table, metres, row-major)") \
            from None
    return camera, dist, given


def find_steps(src: Path, cameras: list[str]) -> tuple[list[int], dict[tuple[str, str, int], Path]]:
    """The step numbers N (sorted) of SRC's `<camera>_<color|depth>_<N>.png` files and each file by (camera, kind,
    N); UserError naming SRC when a camera or kind lacks a step another has, when fewer than 2 steps are found, or
    when a file names a camera the rig file does not list."""
    found: dict[tuple[str, str], set[int]] = {(c, k): set() for c in cameras for k in ("color", "depth")}
    files: dict[tuple[str, str, int], Path] = {}
    for entry in sorted(src.iterdir()):
        m = IMAGE_PATTERN.match(entry.name)
        if m is None:
            continue
        key = (m["camera"], m["kind"])
        if key not in found:
            raise UserError(f"{src}: {entry.name} names camera {m['camera']!r}, which the rig file does not list; name "
                            f"the images {' or '.join(CAMERA_NAMES)}_<color|depth>_<N>.png as the rig's cameras")
        step = int(m["step"])
        if key + (step,) in files:
            raise UserError(f"{src}: {files[key + (step,)].name} and {entry.name} are both step {step}; keep one")
        resolved_inside(src, entry, "image", src)
        found[key].add(step)
        files[key + (step,)] = entry
    steps = sorted(set().union(*found.values()))
    if len(steps) < 2:
        raise UserError(f"{src}: found {len(steps)} steps of <camera>_color_<N>.png / <camera>_depth_<N>.png images "
                        "(e.g. front_color_000.png); a capture needs at least 2 (one push)")
    for (cam, kind), have in found.items():
        missing = sorted(set(steps) - have)
        if missing:
            listed = ", ".join(f"{cam}_{kind}_{n}.png" for n in missing[:3]) + (" ..." if len(missing) > 3 else "")
            raise UserError(f"{src}: no {listed} (step number{'s' if len(missing) > 1 else ''} "
                            f"{', '.join(map(str, missing[:3]))} exist{'' if len(missing) > 1 else 's'} for another "
                            "camera or kind): every camera needs colour and depth at every step")
    return steps, files


def logged_between(log: Path) -> list[tuple[int, int]] | None:
    """Each push's "between": [N, M] in the push log (the step numbers N of the images before and after it), or None
    when no push gives it or the log cannot be read (`read_pushes` says why); UserError naming the log and the push
    when one gives it and another does not, or when it is not two increasing whole numbers."""
    try:
        data = json.loads(log.read_text())
    except (OSError, ValueError, RecursionError):
        return None
    entries = data.get("pushes") if isinstance(data, dict) else None
    if not isinstance(entries, list) or not any(isinstance(e, dict) and "between" in e for e in entries):
        return None
    out = []
    for i, entry in enumerate(entries):
        value = entry.get("between") if isinstance(entry, dict) else None
        if not (isinstance(value, list) and len(value) == 2 and all(type(v) is int for v in value)
                and 0 <= value[0] < value[1]):
            raise UserError(f"--pushes {log}: push {i} \"between\" must be [N, M], the step numbers (as in "
                            f"<camera>_color_<N>.png) of the images before and after it, N < M, got "
                            f"{json_text(value)}; give it for every push or for none")
        out.append((value[0], value[1]))
    return out


def check_step_numbers(src: Path, steps: list[int], files: dict[tuple[str, str, int], Path],
                       between: list[tuple[int, int]] | None, log: Path) -> None:
    """Refuse a dropped step, which counting cannot show when its push is missing from the log as well (T + 1 steps
    and T pushes still agree, and every later push would be paired with the wrong images). Without "between" in the
    push log the numbers N count steps: they must run without a gap (N0, N0 + 1, ...). With it (the numbers may then
    be frame numbers), push i must be logged between the i-th and (i + 1)-th numbers. UserError naming the missing
    step (or push) and the fix."""
    def image(n: int) -> str:  # the front colour image of step n, zero-padded as its neighbours are
        near = min(steps, key=lambda k: abs(k - n))
        digits = files[(MODEL_CAMERA, "color", near)].stem.rsplit("_", 1)[1]
        width = len(digits) if digits.startswith("0") else 0
        return f"{MODEL_CAMERA}_color_{n:0{width}d}.png"

    if between is None:
        for a, b in zip(steps, steps[1:]):
            if b - a > 1:
                more = f" and {b - a - 2} more" if b - a > 2 else ""
                raise UserError(f"{src}: step {a + 1}{more} missing (the image numbers jump from {a} to {b}: no "
                                f"{image(a + 1)}; a dropped frame, whose push may be gone from the log too); re-export "
                                "it, or, if the numbers are frame numbers rather than steps, log each push's "
                                "\"between\": [N, M] (docs/annotator.md, 'Pushes')")
        return
    have = set(steps)
    for i, pair in enumerate(between):
        expected = (steps[i], steps[i + 1]) if i + 1 < len(steps) else None
        if pair == expected:
            continue
        gone = [n for n in pair if n not in have]
        said = f"--pushes {log}: push {i} is logged between steps {pair[0]} and {pair[1]}"
        if gone:
            raise UserError(f"{said}, but {src} has no images of step {gone[0]} (no {image(gone[0])}: a dropped "
                            "frame); re-export it, or cut the capture and its log before it")
        if expected is not None:
            raise UserError(f"{said}, but the images go from step {expected[0]} to {expected[1]}, and no push between "
                            "them is logged (a dropped push); log it, or cut the capture there")


def read_image(path: Path, camera: CaptureCamera, kind: str) -> np.ndarray:
    """A step image checked against the camera: colour (H, W, 3) uint8 RGB (RGBA refused: alpha is not dropped
    silently), depth (H, W) uint16 units. Its PNG header is checked first (size, bit depth, colour type): an image of
    another size or type is refused before it is decoded (a decoder allocates what the header declares); then that the
    file is whole (`png_intact`: a PNG cut short decodes without error when only its tail is gone)."""
    from PIL import Image

    shape, dtype, depth, colour = png_shape(path)
    if kind == "color" and depth == 8 and colour == 6 and shape[:2] == (camera.height, camera.width):
        raise UserError(f"{path}: an 8-bit RGBA PNG (with an alpha channel), where colour images are 8-bit RGB; the "
                        "importer does not drop alpha for you: save it as RGB (e.g. PIL's .convert('RGB'))")
    ok = depth == 8 and colour == 2 if kind == "color" else depth == 16 and colour == 0
    if not ok or shape[:2] != (camera.height, camera.width):
        _wrong_image(path, camera, kind, shape, dtype)
    png_intact(path)
    try:
        with Image.open(path) as im:
            array = np.asarray(im)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: unreadable image ({exc}); re-export it as PNG") from None
    shape = (camera.height, camera.width, 3) if kind == "color" else (camera.height, camera.width)
    ok = array.shape == shape and (array.dtype == np.uint8 if kind == "color" else array.dtype == np.uint16)
    if not ok:
        _wrong_image(path, camera, kind, array.shape, str(array.dtype))
    return array


def _wrong_image(path: Path, camera: CaptureCamera, kind: str, shape: tuple, dtype: str):
    what = "an 8-bit RGB" if kind == "color" else "a 16-bit single-channel depth (uint16 units of depth_scale)"
    raise UserError(f"{path}: expected {what} PNG of {camera.width}x{camera.height} (the rig file's "
                    f"{camera.name!r} width x height), got shape {tuple(shape)} {dtype}")


def board_images(rig_path: Path, src: Path, spec: dict, names: list[str]) -> dict[str, dict[str, Path]]:
    """The rig file's board "images" per camera ({"color": path, "depth": path}, depth optional), each a file inside
    SRC; {} without a board or images. Checked before any image is read."""
    images = spec["board"].get("images") if isinstance(spec.get("board"), dict) else None
    if not images:
        return {}
    hint = 'give {"color": PATH, "depth": PATH} (depth optional) or a colour image PATH, relative to the folder'
    if not isinstance(images, dict) or any(n not in names for n in images):
        raise rig_error(rig_path, f"board images must map the rig's cameras ({', '.join(names)}) to images; {hint}")
    out = {}
    for n, given in images.items():
        given = given if isinstance(given, dict) else {"color": given}
        if "color" not in given or any(kind not in ("color", "depth") for kind in given):
            raise rig_error(rig_path, f"board images of camera {n!r}: {hint}")
        out[n] = {kind: inside(src, rel, f"board image {kind!r} of camera {n!r}", rig_path)
                  for kind, rel in given.items()}
        for kind, path in out[n].items():
            if not path.is_file():
                raise rig_error(rig_path, f"board image {kind!r}: {given[kind]!r} of camera {n!r} is not a file "
                                           f"under {src}; {hint}")
    return out


def import_capture(src: str | Path, out: str | Path, *, rig: str | Path | None = None,
                   pushes: str | Path | None = None, steps: str | Path | None = None, max_gap_ms: float | None = None,
                   name: str | None = None, overwrite: bool = False) -> tuple[Path, dict]:
    """Import SRC, a folder of step PNGs (`import_png_folder`) or of RealSense bags (`annotator.realsense`), into the
    capture directory `out`; returns (out, calibration report)."""
    src, out = Path(src), Path(out)
    if not src.is_dir():
        raise UserError(f"{src}: no such folder; give the folder of <camera>_color_<N>.png / _depth_<N>.png images or "
                        "of front.bag / back.bag recordings")
    check_out(out, overwrite)
    if name is not None:  # both forms: the name becomes part of output paths and identities
        plain_name(name, "the capture name", "--name")
    from dsr_bench.annotator.realsense import recordings_in

    has_bags = bool(recordings_in(src))  # .bag, .db3, ROS2 bag directories
    has_pngs = any(IMAGE_PATTERN.match(p.name) for p in src.iterdir())
    if has_bags and has_pngs:
        raise UserError(f"{src}: holds both RealSense recordings (.bag, .db3) and <camera>_color_<N>.png images; keep "
                        "one form per folder")
    if has_bags:
        from dsr_bench.annotator.realsense import DEFAULT_MAX_GAP_MS, import_bags

        return import_bags(src, out, rig=rig, pushes=pushes, steps=steps, name=name, overwrite=overwrite,
                           max_gap_ms=DEFAULT_MAX_GAP_MS if max_gap_ms is None else max_gap_ms)
    if steps is not None or max_gap_ms is not None:
        raise UserError(f"{src}: --steps and --max-gap-ms pick frames of .bag recordings; this folder holds none "
                        "(step PNGs are numbered by their names)")
    return import_png_folder(src, out, rig=rig, pushes=pushes, name=name, overwrite=overwrite)


def import_png_folder(src: str | Path, out: str | Path, *, rig: str | Path | None = None,
                      pushes: str | Path | None = None, name: str | None = None, overwrite: bool = False
                      ) -> tuple[Path, dict]:
    """Import SRC (module docstring) into the capture directory `out`; returns (out, calibration report).

    Everything is read and checked first (one-line UserErrors naming the input and the fix), then written at once.
    """
    from dsr_bench.annotator.pushes import read_pushes

    src, out = Path(src), Path(out)
    if not src.is_dir():
        raise UserError(f"{src}: no such folder; give the folder of <camera>_color_<N>.png / _depth_<N>.png images")
    check_out(out, overwrite)
    rig_path, spec = load_rig(src, rig)
    if not isinstance(spec.get("cameras"), dict):
        raise rig_error(rig_path, 'expected {"cameras": {"front": {...}, "back": {...}}, "objects": [...], ...}')
    names = list(spec["cameras"])
    bad = [n for n in names if n not in CAMERA_NAMES]
    if bad or MODEL_CAMERA not in names:
        others = ", ".join(repr(n) for n in CAMERA_NAMES if n != MODEL_CAMERA)
        raise rig_error(rig_path, f"camera names {names} must be {MODEL_CAMERA!r} (the view models see; required) and "
                                  f"{others}: rename {', '.join(map(repr, bad)) or 'one of them'}")
    names = [n for n in CAMERA_NAMES if n in names]
    cameras, distortion, given = {}, {}, {}
    for n in names:
        cameras[n], distortion[n], given[n] = read_camera(rig_path, n, spec["cameras"][n])
    objects = read_objects(rig_path, src, spec.get("objects"))
    board_files = board_images(rig_path, src, spec, names)
    steps, files = find_steps(src, names)
    log = default_file(src, pushes, PUSHES_FILE, "the push log")
    check_step_numbers(src, steps, files, logged_between(log), log)
    actions, pushes_world = read_pushes(log, len(steps) - 1)
    title = capture_name(name, spec, rig_path, out)

    maps = {n: undistort_maps(cameras[n], d) for n, d in distortion.items() if d is not None}  # names' order

    def load(camera: str, kind: str, path: Path) -> np.ndarray:
        image = read_image(path, cameras[camera], kind)
        return undistort(image, maps[camera], kind == "depth") if camera in maps else image

    colors = [{n: load(n, "color", files[(n, "color", s)]) for n in names} for s in steps]
    depths = [{n: load(n, "depth", files[(n, "depth", s)]).astype(np.float64) * cameras[n].depth_scale
               for n in names} for s in steps]

    def board_image(n: str) -> tuple[str, np.ndarray, np.ndarray]:
        if n not in board_files:
            return str(files[(n, "color", steps[0])]), colors[0][n], depths[0][n]
        path = board_files[n]["color"]
        depth = (load(n, "depth", board_files[n]["depth"]).astype(np.float64) * cameras[n].depth_scale
                 if "depth" in board_files[n] else np.zeros((cameras[n].height, cameras[n].width)))
        return str(path), load(n, "color", path), depth

    report = calibrate_cameras(rig_path, spec, cameras, given, board_image)

    source = {"kind": "real", "importer": "annotator.importer", "format": "png-folder", "src": str(src),
              "rig": spec, "step_numbers": steps, "undistorted": sorted(maps), "calibration": report,
              "policy": "recorded"}
    written = write_capture(out, name=title, cameras=cameras, colors=colors,
                            depths=depths, actions=actions, pushes_world=pushes_world, objects=objects,
                            source=source, overwrite=overwrite)
    return written, report
