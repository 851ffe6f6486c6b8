"""Forged inputs of the annotator: every file `dsr-bench annotate` and `dsr-bench import-capture` read is treated as
an adversary's. Each forged case is refused in one line (UserError; the CLI exits 2) and nothing is written.

- The journal (annotator/journal.py): a journal copied from another capture's work directory (same generation), a
  whole work directory moved onto another capture of the same name and size, records with a NaN / infinite / string
  pose, an unknown status or kind, a "before" this state does not hold, an empty or headerless journal, one that is a
  directory or a link, garbage and deeply nested JSON; journals written before the binding (accepted beside their own
  unbound state.json of the same generation, else refused).
- import-capture (annotator/importer.py, inputs.py, realsense.py): rig numbers that are true or strings, image sizes
  of 10^9, meshes / board images / frames / the rig file / the push log / bags outside SRC (`..`, absolute, links),
  a 12000 x 12000 depth PNG (refused from its header: the test traces the allocations), typed board, push and
  step-time fields, an output made immutable with `chattr +i`; RGBA colour images (alpha never dropped silently),
  PNGs cut short or with a bad CRC (PIL decodes a PNG missing its last 20 bytes without error), a dropped step whose
  push is gone from the log too (the counts agree), and capture and object names that are paths ('..', '/').

The import corpus is a tiny synthetic folder (2 steps, 48 x 64 black images, a 5 cm box, given extrinsics at the
benchmark's camera placement): untouched, it imports (the baseline), so each refusal is the forgery's.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest

from dsr_bench.errors import UserError

SHAPE = (48, 64)


def _tree(root: Path) -> dict[str, bytes | None]:
    """Every path under `root` (hidden ones too) with its bytes (None for a directory or a link)."""
    out: dict[str, bytes | None] = {}
    for p in sorted(root.rglob("*")):
        out[str(p.relative_to(root))] = None if p.is_symlink() or p.is_dir() else p.read_bytes()
    return out


def _one_line_refusal(capsys, argv: list[str], expected: str) -> str:
    from dsr_bench.cli import main

    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expected in err, err
    return err


# --- import-capture ------------------------------------------------------------------------------------------------


def _write_png(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(array).save(path)


def _rig_folder(folder: Path) -> Path:
    """A 2-step PNG folder that imports: black images, no depth, a 5 cm box, extrinsics given for both cameras."""
    import trimesh

    from dsr_bench.geometry import make_camera

    folder.mkdir(parents=True)
    (folder / "meshes").mkdir()
    trimesh.creation.box(extents=(0.05, 0.05, 0.05)).export(folder / "meshes" / "box.ply")
    cameras = {}
    for name in ("front", "back"):
        cam = make_camera(name, *SHAPE)
        k = np.asarray(cam.intrinsics, float)
        cameras[name] = {"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2], "width": SHAPE[1],
                         "height": SHAPE[0], "depth_scale": 0.001, "extrinsics": np.asarray(cam.extrinsics).tolist()}
        for step in (0, 1):
            _write_png(folder / f"{name}_color_{step}.png", np.zeros(SHAPE + (3,), np.uint8))
            _write_png(folder / f"{name}_depth_{step}.png", np.zeros(SHAPE, np.uint16))
    rig = {"name": "forged", "cameras": cameras, "objects": [{"name": "box", "mesh": "meshes/box.ply"}]}
    (folder / "rig.json").write_text(json.dumps(rig))
    (folder / "pushes.json").write_text(json.dumps({"pushes": [{"start": [0.4, 0.0], "direction": [1.0, 0.0]}]}))
    return folder


def _huge_png(path: Path, side: int = 12000) -> None:
    """A real side x side 16-bit greyscale PNG of zeros (a few hundred kB on disk, 2 x side^2 bytes decoded),
    written row by row."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")

    packer = zlib.compressobj(9)
    rows = b"\0" * (1 + 2 * side) * 100
    idat = b"".join(packer.compress(rows) for _ in range(side // 100)) + packer.flush()
    ihdr = side.to_bytes(4, "big") * 2 + bytes([16, 0, 0, 0, 0])
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b""))


@pytest.fixture(scope="module")
def rig_folder(tmp_path_factory) -> Path:
    return _rig_folder(tmp_path_factory.mktemp("forged_rig") / "src")


@pytest.fixture(scope="module")
def huge_png(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("huge") / "huge_depth.png"
    _huge_png(path)
    return path


def _rig(folder: Path, edit) -> None:
    spec = json.loads((folder / "rig.json").read_text())
    edit(spec)
    (folder / "rig.json").write_text(json.dumps(spec))


def _camera(key, value, camera="front"):
    return lambda spec: spec["cameras"][camera].__setitem__(key, value)


def _outside(folder: Path) -> Path:
    """A file beside SRC (outside it): a copy of SRC's mesh."""
    target = folder.parent / "outside.ply"
    shutil.copy(folder / "meshes" / "box.ply", target)
    return target


def _mesh_up(folder):
    _outside(folder)
    _rig(folder, lambda s: s["objects"][0].__setitem__("mesh", "../outside.ply"))


def _mesh_absolute(folder):
    target = _outside(folder)
    _rig(folder, lambda s: s["objects"][0].__setitem__("mesh", str(target)))


def _mesh_link(folder):
    (folder / "meshes" / "link.ply").symlink_to(_outside(folder))
    _rig(folder, lambda s: s["objects"][0].__setitem__("mesh", "meshes/link.ply"))


def _mesh_loop(folder):
    (folder / "meshes" / "a.ply").symlink_to(folder / "meshes" / "b.ply")
    (folder / "meshes" / "b.ply").symlink_to(folder / "meshes" / "a.ply")
    _rig(folder, lambda s: s["objects"][0].__setitem__("mesh", "meshes/a.ply"))


def _board_images(images):
    board = {"squares": [7, 5], "square_length": 0.06, "marker_length": 0.045, "dictionary": "DICT_4X4_50",
             "offset": [0.29, 0.15, 0.0], "images": images}
    return lambda spec: spec.__setitem__("board", board)


def _board_up(folder):
    shutil.copy(folder / "front_color_0.png", folder.parent / "board.png")
    _rig(folder, _board_images({"front": "../board.png"}))


def _board_link(folder):
    shutil.copy(folder / "front_color_0.png", folder.parent / "board.png")
    (folder / "board.png").symlink_to(folder.parent / "board.png")
    _rig(folder, _board_images({"front": {"color": "board.png"}}))


def _linked_out(name: str, outside: str | None = None):
    """A forgery: SRC's file `name` moved out of SRC (as `outside`) and linked back into it."""
    def forge(folder):
        shutil.move(folder / name, folder.parent / (outside or name))
        (folder / name).symlink_to(folder.parent / (outside or name))
    return forge


_frame_link, _rig_link = _linked_out("front_color_1.png", "frame.png"), _linked_out("rig.json")
_pushes_link = _linked_out("pushes.json")


def _pushes_string(folder):
    (folder / "pushes.json").write_text(json.dumps({"pushes": [{"start": ["0.4", 0.0], "direction": [1.0, 0.0]}]}))


def _board_squares(folder):
    def edit(spec):
        _board_images(None)(spec)
        spec["board"]["squares"] = ["7", 5]
        del spec["cameras"]["back"]["extrinsics"]  # calibrated from the board: the board is read
    _rig(folder, edit)


def _png_lies(folder):  # a JPEG (or anything) named .png
    (folder / "front_depth_1.png").write_bytes(b"\xff\xd8\xff\xe0" + b"\0" * 64)


def _rgba(folder):  # alpha would be dropped silently
    rgba = np.zeros(SHAPE + (4,), np.uint8)
    rgba[..., 3] = 40
    _write_png(folder / "front_color_1.png", rgba)


def _cut(name: str, size: int):
    """A forgery: SRC's PNG `name` with its last `size` bytes cut off (12: IEND; 20: also the last IDAT's zlib
    checksum and CRC, which PIL decodes without error)."""
    def forge(folder):
        data = (folder / name).read_bytes()
        (folder / name).write_bytes(data[:-size])
    return forge


def _bad_crc(folder):
    data = bytearray((folder / "back_color_0.png").read_bytes())
    data[-14] ^= 0x01  # the last byte of the IDAT chunk's CRC
    (folder / "back_color_0.png").write_bytes(bytes(data))


def _steps_0123(folder, drop: int | None, between: list | None, pushes: int = 3) -> None:
    """SRC with steps 0..3 (step 2, 3 copies of step 0), step `drop`'s images of every camera deleted, and a push log
    of `pushes` pushes, each with its "between" from `between` if given."""
    for name in ("front", "back"):
        for step in (2, 3):
            for kind in ("color", "depth"):
                shutil.copy(folder / f"{name}_{kind}_0.png", folder / f"{name}_{kind}_{step}.png")
        if drop is not None:
            for kind in ("color", "depth"):
                (folder / f"{name}_{kind}_{drop}.png").unlink()
    entries = [{"start": [0.4, 0.0], "direction": [1.0, 0.0]} for _ in range(pushes)]
    for entry, pair in zip(entries, between or []):
        entry["between"] = pair
    (folder / "pushes.json").write_text(json.dumps({"pushes": entries}))


def _mesh_named_dotdot(folder):  # no 'name': the mesh's stem is the object's name
    shutil.copy(folder / "meshes" / "box.ply", folder / "meshes" / "...ply")
    _rig(folder, lambda s: s.__setitem__("objects", [{"mesh": "meshes/...ply"}]))


IMPORT_CORPUS = [
    (lambda f: _rig(f, _camera("fx", True)), "camera 'front' 'fx' must be a finite positive number (a JSON number, "
                                             "not true)"),
    (lambda f: _rig(f, _camera("fx", "912")), "camera 'front' 'fx' must be a finite positive number (a JSON number, "
                                              'not "912")'),
    (lambda f: _rig(f, _camera("depth_scale", [0.001])), "camera 'front' 'depth_scale' must be a finite positive"),
    (lambda f: _rig(f, _camera("width", 10 ** 9)), "camera 'front' 'width' must be a whole number of pixels 1..4096, "
                                                   "got 1000000000"),
    (lambda f: _rig(f, _camera("height", 10 ** 9, "back")), "camera 'back' 'height' must be a whole number of pixels"),
    (lambda f: _rig(f, _camera("width", 64.0)), "'width' must be a whole number of pixels"),
    (lambda f: _rig(f, _camera("distortion", ["0.1", 0, 0, 0, 0])), "distortion must be OpenCV's 5 coefficients"),
    (lambda f: _rig(f, lambda s: s["cameras"]["back"]["extrinsics"][0].__setitem__(0, "1")),
     "camera 'back' extrinsics must be a 4x4 matrix of numbers"),
    (lambda f: _rig(f, lambda s: s.__setitem__("name", {"a": 1})), "'name' must be a string"),
    (lambda f: _rig(f, lambda s: s["objects"][0].__setitem__("identity", "ycb")), "'identity' an object"),
    (_mesh_up, "object 1 mesh '../outside.ply' is not inside"),
    (_mesh_absolute, "outside.ply' is not inside"),
    (_mesh_link, "object 1 mesh 'meshes/link.ply' leads outside"),
    (_mesh_loop, "object 1 mesh"),
    (_board_up, "board image 'color' of camera 'front' '../board.png' is not inside"),
    (_board_link, "board image 'color' of camera 'front' 'board.png' leads outside"),
    (_frame_link, "image 'front_color_1.png' leads outside"),
    (_rig_link, "the rig file 'rig.json' leads outside"),
    (_pushes_link, "the push log 'pushes.json' leads outside"),
    (_pushes_string, "push 0 start must be 2 finite numbers"),
    (_board_squares, "board squares must be 2 integers"),
    (_png_lies, "front_depth_1.png: not a PNG file"),
    (_rgba, "front_color_1.png: an 8-bit RGBA PNG (with an alpha channel), where colour images are 8-bit RGB; the "
            "importer does not drop alpha for you: save it as RGB"),
    (_cut("front_color_1.png", 12), "front_color_1.png: truncated PNG (it ends at byte"),
    (_cut("front_color_1.png", 20), "front_color_1.png: truncated PNG (its 'IDAT' chunk at byte 33 runs past the end"),
    (_cut("back_depth_1.png", 16), "back_depth_1.png: truncated PNG (its 'IDAT' chunk at byte 33 runs past the end"),
    (_bad_crc, "back_color_0.png: corrupt PNG (its 'IDAT' chunk at byte 33 fails its CRC)"),
    # a dropped step whose push is dropped too: 3 steps, 2 pushes, the counts agree
    (lambda f: _steps_0123(f, 2, None, 2), "step 2 missing (the image numbers jump from 1 to 3: no front_color_2.png; "
                                           "a dropped frame"),
    (lambda f: _steps_0123(f, 2, None, 3), "step 2 missing"),  # the frame alone: named before the push count
    (lambda f: _steps_0123(f, 2, [[0, 1], [1, 2]], 2), "push 1 is logged between steps 1 and 2, but "),
    (lambda f: _steps_0123(f, 2, [[0, 1], [2, 3]], 2), "has no images of step 2 (no front_color_2.png: a dropped "
                                                       "frame)"),
    (lambda f: _steps_0123(f, None, [[0, 1], [2, 3]], 2), "push 1 is logged between steps 2 and 3, but the images go "
                                                          "from step 1 to 2, and no push between them is logged"),
    (lambda f: _steps_0123(f, None, [[0, 1], [1, "2"]], 3), 'push 1 "between" must be [N, M], the step numbers'),
    (lambda f: _steps_0123(f, None, [[0, 1]], 3), 'push 1 "between" must be [N, M]'),  # for every push or none
    (lambda f: _rig(f, lambda s: s.__setitem__("name", "../../evil")), "rig.json: 'name' (the capture's) "
                                                                       '"../../evil" is not a plain name: it holds'),
    (lambda f: _rig(f, lambda s: s.__setitem__("name", "..")), "'name' (the capture's) \"..\" is not a plain name: "
                                                               "'..' is a path"),
    (lambda f: _rig(f, lambda s: s["objects"][0].__setitem__("name", "../../box")), 'object 1 name "../../box" is not '
                                                                                   "a plain name"),
    (lambda f: _rig(f, lambda s: s["objects"][0].__setitem__("name", "/etc/box")), 'object 1 name "/etc/box"'),
    (lambda f: _rig(f, lambda s: s["objects"][0].__setitem__("name", "box\nline")),
     'object 1 name "box\\nline" is not a plain name: it holds control'),
    (_mesh_named_dotdot, "object 1 name \"..\" is not a plain name"),
]


def test_the_untouched_folder_imports(rig_folder, tmp_path, capsys):
    """The baseline of the import corpus: every refusal below is its forgery's."""
    from dsr_bench.cli import main
    from dsr_bench.dataset.capture import load_capture

    assert main(["import-capture", str(rig_folder), "--out", str(tmp_path / "cap")]) == 0
    assert load_capture(tmp_path / "cap").num_objects == 1


@pytest.mark.parametrize("forge, expected", IMPORT_CORPUS, ids=[f"import{k}" for k in range(len(IMPORT_CORPUS))])
def test_forged_import_inputs_are_refused_in_one_line(rig_folder, tmp_path, capsys, forge, expected):
    src = tmp_path / "src"
    shutil.copytree(rig_folder, src)
    forge(src)
    before = _tree(tmp_path)
    out = tmp_path / "out"
    _one_line_refusal(capsys, ["import-capture", str(src), "--out", str(out)], expected)
    assert _tree(tmp_path) == before  # nothing written: no capture, no temporary beside it


@pytest.mark.parametrize("args, expected", [
    (["--name", "../../evil"], '--name: the capture name "../../evil" is not a plain name: it holds'),
    (["--name", ".."], '--name: the capture name ".." is not a plain name'),
    (["--name", ""], '--name: the capture name "" is not a plain name: it is empty'),
])
def test_capture_names_that_are_paths_are_refused(rig_folder, tmp_path, capsys, args, expected):
    """--name, like the rig file's 'name' and the objects' (IMPORT_CORPUS), becomes part of output paths: one plain
    name or a one-line refusal, nothing written."""
    before = _tree(tmp_path)
    _one_line_refusal(capsys, ["import-capture", str(rig_folder), "--out", str(tmp_path / "out"), *args], expected)
    assert _tree(tmp_path) == before


def test_an_out_that_names_no_directory_of_its_own_is_refused(rig_folder, tmp_path, capsys):
    """--out DIR/.. with --overwrite would replace DIR's parent with the capture: refused before any work."""
    (tmp_path / "dir").mkdir()
    before = _tree(tmp_path)
    _one_line_refusal(capsys, ["import-capture", str(rig_folder), "--out", f"{tmp_path}/dir/..", "--overwrite"],
                      f"--out {tmp_path}/dir/..: names no capture directory of its own (it ends in '..')")
    assert _tree(tmp_path) == before


def test_frame_numbers_import_when_the_log_says_between_which_steps_each_push_lies(rig_folder, tmp_path, capsys):
    """Step numbers with gaps (frame numbers) import when every push gives its "between": [N, M]; without it a gap
    is a dropped step (IMPORT_CORPUS)."""
    from dsr_bench.cli import main
    from dsr_bench.dataset.capture import load_capture

    src = tmp_path / "src"
    shutil.copytree(rig_folder, src)
    for path in sorted(src.glob("*_[01].png")):
        frame = {"0": 1043, "1": 1187}[path.stem[-1]]
        path.rename(src / f"{path.stem[:-1]}{frame}.png")
    push = {"start": [0.4, 0.0], "direction": [1.0, 0.0]}
    (src / "pushes.json").write_text(json.dumps({"pushes": [push]}))
    _one_line_refusal(capsys, ["import-capture", str(src), "--out", str(tmp_path / "cap")],
                      "step 1044 and 142 more missing (the image numbers jump from 1043 to 1187")
    (src / "pushes.json").write_text(json.dumps({"pushes": [{**push, "between": [1043, 1187]}]}))
    assert main(["import-capture", str(src), "--out", str(tmp_path / "cap")]) == 0
    capture = load_capture(tmp_path / "cap")
    assert capture.num_steps == 1 and capture.source["step_numbers"] == [1043, 1187]
    assert capture.actions.tolist() == [[0, 64, 39]]


def test_a_huge_png_is_refused_from_its_header_before_it_is_decoded(rig_folder, huge_png, tmp_path, capsys):
    """A 12000 x 12000 16-bit depth PNG (288 MB decoded) is refused from its header: the import's allocations stay
    far below one decoded copy."""
    src = tmp_path / "src"
    shutil.copytree(rig_folder, src)
    shutil.copy(huge_png, src / "front_depth_0.png")
    before = _tree(tmp_path)
    tracemalloc.start()
    try:
        _one_line_refusal(capsys, ["import-capture", str(src), "--out", str(tmp_path / "out")],
                          "front_depth_0.png: expected a 16-bit single-channel depth (uint16 units of depth_scale) PNG "
                          "of 64x48 (the rig file's 'front' width x height), got shape (12000, 12000) uint16")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 32 * 2 ** 20, peak
    assert _tree(tmp_path) == before


def _bag_folder(rig_folder: Path, folder: Path) -> Path:
    """A bag-form folder whose checks before the bags are opened pass: front.bag (never opened by these cases),
    rig.json (objects), steps.json, pushes.json."""
    folder.mkdir()
    shutil.copytree(rig_folder / "meshes", folder / "meshes")
    shutil.copy(rig_folder / "pushes.json", folder / "pushes.json")
    (folder / "front.bag").write_bytes(b"#ROSBAG V2.0\n")
    (folder / "rig.json").write_text(json.dumps({"objects": [{"name": "box", "mesh": "meshes/box.ply"}]}))
    (folder / "steps.json").write_text(json.dumps({"step_times": [1.0, 2.0]}))
    return folder


def _steps(value):
    return lambda f: (f / "steps.json").write_text(json.dumps({"step_times": value}))


_bag_link, _steps_link = _linked_out("front.bag"), _linked_out("steps.json")


def _bag_extrinsics(folder):
    spec = json.loads((folder / "rig.json").read_text())
    spec["cameras"] = {"front": {"extrinsics": [["1", 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}}
    (folder / "rig.json").write_text(json.dumps(spec))


BAG_CORPUS = [
    (_steps(["1.0", "2.0"]), "step_times must be a list of times (s)"),
    (_steps([True, 2.0]), "step_times must be a list of times (s)"),
    (_bag_link, "recording 'front.bag' leads outside"),
    (_steps_link, "the steps file 'steps.json' leads outside"),
    (_bag_extrinsics, "camera 'front' extrinsics must be a 4x4 matrix of numbers"),
]


@pytest.mark.parametrize("forge, expected", BAG_CORPUS, ids=[f"bag{k}" for k in range(len(BAG_CORPUS))])
def test_forged_bag_folder_inputs_are_refused_in_one_line(rig_folder, tmp_path, capsys, forge, expected):
    src = _bag_folder(rig_folder, tmp_path / "src")
    forge(src)
    before = _tree(tmp_path)
    _one_line_refusal(capsys, ["import-capture", str(src), "--out", str(tmp_path / "out")], expected)
    assert _tree(tmp_path) == before


def _chattr(flag: str, path: Path) -> bool:
    if shutil.which("chattr") is None:
        return False
    return subprocess.run(["chattr", flag, str(path)], capture_output=True).returncode == 0


def test_an_immutable_output_is_refused_before_any_work(rig_folder, tmp_path, capsys):
    """`chattr +i` (root ignores permission bits): a new capture in an immutable directory, an existing immutable
    capture with --overwrite, and annotate --export into an immutable directory are refused in one line naming the
    option, before the inputs are read (a forged rig file is not reached)."""
    src = tmp_path / "src"
    shutil.copytree(rig_folder, src)
    _rig(src, _camera("fx", True))  # would be refused later: the output is checked first
    dest = tmp_path / "dest"
    (dest / "cap").mkdir(parents=True)
    (dest / "cap" / "capture.json").write_text("{}")
    if not _chattr("+i", dest / "cap"):
        pytest.skip("chattr +i is not available here")
    try:
        if not _chattr("+i", dest):
            pytest.skip("chattr +i is not available here")
        before = _tree(tmp_path)
        _one_line_refusal(capsys, ["import-capture", str(src), "--out", str(dest / "new")],
                          f"--out {dest / 'new'}: cannot create files in {dest}")
        _one_line_refusal(capsys, ["import-capture", str(src), "--out", str(dest / "cap"), "--overwrite"],
                          f"--out {dest / 'cap'}: cannot create files in it")
        _one_line_refusal(capsys, ["annotate", "no_such_capture", "--export", str(dest / "out.h5")],
                          f"--export {dest / 'out.h5'}: cannot create files in {dest}")
        assert _tree(tmp_path) == before
    finally:
        _chattr("-i", dest)
        _chattr("-i", dest / "cap")


# --- the annotation journal ----------------------------------------------------------------------------------------


def _annotate(capture: Path, work: Path, truth) -> None:
    """4 journal records on a fresh state.json (generation 1): 3 picks and a nudge."""
    from dsr_bench.annotator.session import Session
    from helpers import place_from_truth

    session = Session.open(capture, work)
    place_from_truth(session, truth, snap=False)
    session.nudge(0, translation=(0.002, 0.0, 0.0))


@pytest.fixture(scope="module")
def annotated(capture_dir, truth, tmp_path_factory) -> dict[str, Path]:
    """A work directory with 4 records on generation 1 ("work"), and another capture of the same name, size and scene
    (a copy) annotated the same way in its own work directory ("other", "other_work")."""
    root = tmp_path_factory.mktemp("annotated")
    other = root / "other" / capture_dir.name
    shutil.copytree(capture_dir, other, ignore=shutil.ignore_patterns("annotation"))
    _annotate(capture_dir, root / "work", truth)
    _annotate(other, root / "other_work", truth)
    return {"work": root / "work", "other": other, "other_work": root / "other_work"}


def _records(work: Path) -> tuple[list[str], list[dict]]:
    lines = (work / "journal.jsonl").read_text().splitlines()
    return lines[:1], [json.loads(line) for line in lines[1:]]


def _rewrite(work: Path, edit) -> None:
    header, records = _records(work)
    edit(records)
    (work / "journal.jsonl").write_text("\n".join(header + [json.dumps(r) for r in records]) + "\n")


def _after_pose(record: int, value):
    def edit(records):
        records[record - 1]["op"]["cells"][0][3]["pose"][0] = value
    return lambda work, ctx: _rewrite(work, edit)


def _field(record: int, key: str, value):
    return lambda work, ctx: _rewrite(work, lambda r: r[record - 1].__setitem__(key, value))


def _foreign_journal(work, ctx):  # another capture's journal, also generation 1, over a fresh state.json
    shutil.rmtree(work)
    from dsr_bench.annotator.session import Session

    Session.open(ctx["capture"], work)
    shutil.copy(ctx["other_work"] / "journal.jsonl", work / "journal.jsonl")


def _forged_before(work, ctx):  # record 2 claims to start from a snapped pose
    def edit(records):
        cell = records[1]["op"]["cells"][0]
        cell[2] = dict(cell[3], status="snapped")
    _rewrite(work, edit)


def _empty(work, ctx):
    (work / "journal.jsonl").write_bytes(b"")


def _headerless(work, ctx):
    lines = (work / "journal.jsonl").read_text().splitlines(keepends=True)
    (work / "journal.jsonl").write_text("".join(lines[1:]))


def _directory(work, ctx):
    (work / "journal.jsonl").unlink()
    (work / "journal.jsonl").mkdir()


def _link(work, ctx):
    (work / "journal.jsonl").rename(work.parent / "journal.jsonl")
    (work / "journal.jsonl").symlink_to(work.parent / "journal.jsonl")


def _state_directory(work, ctx):
    (work / "state.json").unlink()
    (work / "state.json").mkdir()


def _garbage(work, ctx):
    lines = (work / "journal.jsonl").read_text().splitlines(keepends=True)
    (work / "journal.jsonl").write_text("".join(lines[:1] + ["{not json\n"] + lines[1:]))


def _nested(work, ctx):
    with open(work / "journal.jsonl", "a") as f:
        f.write("[" * 100000 + "]" * 100000 + "\n")


def _unbound(work, state: bool = True, journal: bool = True, generation: int | None = None) -> None:
    """Files as the annotator wrote them before the binding: state.json without capture_sha256 / folded, a header
    with only format and generation."""
    if state:
        d = json.loads((work / "state.json").read_text())
        for key in ("capture_sha256", "folded", "snapshot"):
            d.pop(key)
        (work / "state.json").write_text(json.dumps(d))
    if journal:
        lines = (work / "journal.jsonl").read_text().splitlines(keepends=True)
        header = json.loads(lines[0])
        header = {"format": header["format"], "generation": header["generation"] if generation is None else generation}
        (work / "journal.jsonl").write_text(json.dumps(header) + "\n" + "".join(lines[1:]))


JOURNAL_CORPUS = [
    (_foreign_journal, "journal.jsonl: written on top of another state.json (generation 1; this one is generation 1)"),
    (_after_pose(4, float("nan")), "record 4 of 4 (line 5): step 0 object 1 after pose [nan, "),
    (_after_pose(1, float("inf")), "record 1 of 4 (line 2): step 0 object 1 after pose [inf, "),
    (_after_pose(2, "0.5"), "record 2 of 4 (line 3): step 0 object 2 after pose must be null or 7 numbers"),
    (lambda w, c: _rewrite(w, lambda r: r[0]["op"]["cells"][0][3].__setitem__("status", "bogus")),
     "record 1 of 4 (line 2): step 0 object 1 after: unknown status 'bogus'"),
    (lambda w, c: _rewrite(w, lambda r: r[0]["op"]["cells"][0][3].__setitem__("pose", None)),
     "record 1 of 4 (line 2): step 0 object 1 after: status 'initialised' with no pose"),
    (_forged_before, "record 2 of 4 (line 3): its pick of step 0 object 2 starts from a snapped pose this state does "
                     "not hold"),
    (_field(3, "kind", "teleport"), "record 3 of 4 (line 4): unknown record kind 'teleport'"),
    (_field(2, "step", 7), "record 2 of 4 (line 3): step 7 or selected object 0 is not in this capture's steps"),
    (_field(2, "selected", True), "record 2 of 4 (line 3): step 0 or selected object True is not"),
    (_field(1, "counts", {"pick": -1}), "record 1 of 4 (line 2): counts must map action kinds"),
    (lambda w, c: _rewrite(w, lambda r: r[0]["op"].__setitem__("cursor", [0, 9])),
     "record 1 of 4 (line 2): an operation outside this capture's steps and objects"),
    (_garbage, "record 1 of 5 (line 2): unreadable JSON"),
    (_nested, "record 5 of 5 (line 6): unreadable JSON"),
    (_empty, "journal.jsonl: empty, but state.json (generation 1) is followed by its journal"),
    (_headerless, "journal.jsonl: has no journal header (not an annotation journal)"),
    (_directory, "journal.jsonl is a directory, not the annotation's journal"),
    (_link, "journal.jsonl is a link, not the annotation's journal"),
    (_state_directory, "state.json is a directory, not the annotation's state"),
    (lambda w, c: _unbound(w, state=False), "journal.jsonl: carries no binding to its state.json"),
    (lambda w, c: _unbound(w, journal=False), "journal.jsonl: written on top of another state.json"),
    (lambda w, c: _unbound(w, generation=2), "journal.jsonl: generation 2 does not go with state.json's 1, and neither "
                                             "file says which capture"),
]


@pytest.mark.parametrize("forge, expected", JOURNAL_CORPUS, ids=[f"journal{k}" for k in range(len(JOURNAL_CORPUS))])
def test_forged_journals_are_refused_in_one_line(capture_dir, annotated, tmp_path, capsys, forge, expected):
    from dsr_bench.annotator.session import Session

    work = tmp_path / "work"
    shutil.copytree(annotated["work"], work, symlinks=True)
    forge(work, {"capture": capture_dir, **annotated})
    before = _tree(tmp_path)
    with pytest.raises(UserError) as caught:
        Session.open(capture_dir, work)
    assert expected in str(caught.value) and "\n" not in str(caught.value), str(caught.value)
    out = tmp_path / "out.h5"
    _one_line_refusal(capsys, ["annotate", str(capture_dir), "--work", str(work), "--export", str(out),
                               "--allow-unchecked"], expected)
    assert _tree(tmp_path) == before  # nothing written: no export, no fresh journal, state.json untouched


def test_a_work_directory_moved_onto_another_capture_of_the_same_name_is_refused(annotated, tmp_path, capsys):
    """The whole work directory (state.json and its own journal) of one capture, opened on another capture of the
    same name, steps and objects whose content differs (one colour pixel): refused, naming the capture."""
    from PIL import Image

    from dsr_bench.annotator.session import Session

    other = tmp_path / "captures" / annotated["other"].name
    shutil.copytree(annotated["other"], other)
    path = other / "steps" / "001" / "front_color.png"
    image = np.asarray(Image.open(path)).copy()
    image[0, 0, 0] ^= 1
    Image.fromarray(image).save(path)
    work = tmp_path / "work"
    shutil.copytree(annotated["work"], work)
    before = _tree(tmp_path)
    with pytest.raises(UserError, match="state.json was made on another capture's content than .*give another --work"):
        Session.open(other, work)
    _one_line_refusal(capsys, ["annotate", str(other), "--work", str(work), "--status"],
                      "was made on another capture's content")
    assert _tree(tmp_path) == before


def test_the_untouched_journal_and_an_unbound_pair_resume(capture_dir, annotated, tmp_path):
    """The baseline of the journal corpus (the untouched copy resumes with its 4 records), and files written before
    the binding: an unbound state.json with its unbound journal of the same generation resumes (each record checked
    against the state it applies to) and both come out bound; a torn last record is still dropped with a note."""
    from dsr_bench.annotator.journal import read_saved
    from dsr_bench.annotator.session import Session
    from dsr_bench.dataset.capture import load_capture

    work = tmp_path / "work"
    shutil.copytree(annotated["work"], work)
    expected = read_saved(work, load_capture(capture_dir))
    assert expected.replayed == 4 and expected.bound and expected.journal_current
    _unbound(work)
    old = read_saved(work)
    assert not old.bound and old.replayed == 4 and old.state.to_dict() == expected.state.to_dict()
    session = Session.open(capture_dir, work)
    assert session.state.to_dict() == expected.state.to_dict()
    header = json.loads((work / "journal.jsonl").read_text().splitlines()[0])
    state = json.loads((work / "state.json").read_text())
    assert header["capture_sha256"] == state["capture_sha256"] and len(header["state_sha256"]) == 64
    session.select(2)
    with open(work / "journal.jsonl", "a") as f:
        f.write('{"kind": "select", "step"')  # cut short by a crash
    resumed = Session.open(capture_dir, work)
    assert resumed.selected == 2 and len(resumed.notes) == 1 and "cut short" in resumed.notes[0]


@pytest.mark.parametrize("content, expected", [
    ({"objects": {"1": [[1, 0, 0, "0.4"], [0, 1, 0, 0], [0, 0, 1, 0.02], [0, 0, 0, 1]]}},
     "object '1': a pose must be 4 rows of 4 finite numbers"),
    ({"objects": {"1": {"mesh": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "cloud": [[0.5, 0, 0], ["nan", 0, 0], [0, 1, 0]]}}},
     "object '1': mesh and cloud must be lists of [x, y, z] points (finite numbers"),
    ({"objects": {"1": {"mesh": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "cloud": [[0.5, 0, 0], [True, 0, 0], [0, 1, 0]]}}},
     "object '1': mesh and cloud must be lists of [x, y, z] points"),
])
def test_forged_place_files_are_refused_in_one_line(capture_dir, tmp_path, capsys, content, expected):
    """--place POSES.json: numbers are JSON numbers (a string or true is refused, not converted), picks finite."""
    (tmp_path / "place.json").write_text(json.dumps(content))
    _one_line_refusal(capsys, ["annotate", str(capture_dir), "--work", str(tmp_path / "work"), "--place",
                               str(tmp_path / "place.json")], expected)
