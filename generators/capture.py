"""Simulated two-camera RGB-D captures: the annotator's demo, test fixtures and accuracy yardstick.

simulate (generators.episode, both cameras) -> ideal renders (dsr_bench.render) -> sensor model -> capture
directory (dsr_bench.dataset.capture.write_capture). The sensor model imitates an active-stereo RealSense (D415-like):

- depth comes from a disparity d = f b / z (f the focal length in pixels, b the stereo baseline): matching noise of
  `disparity_sigma` pixels (part white, part spatially correlated), so the depth error grows with z^2; the
  disparity is quantised to `disparity_step` pixels, the depth to the depth unit (`depth_scale`, 1 mm -> uint16);
- pixels are missing where the second imager cannot see them (stereo occlusion band beside foreground edges), in a
  band around depth discontinuities, on dark surfaces (low colour intensity) and as random speckle;
- colour gets Gaussian pixel noise;
- the stored calibration is the true one perturbed by a small rigid motion (1-2 mm, 0.1-0.2 degrees, about the
  camera centre) and slightly wrong intrinsics; the true calibration and poses go to truth.json only.

Everything random is drawn from generators seeded with the capture seed: a capture is a pure function of its
arguments and seed (the episode from `sequence_seed`-style seed, the sensor noise from a separate stream).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from dsr_bench.atomic import clean_temporaries
from dsr_bench.constants import CAMERAS
from dsr_bench.dataset.capture import CaptureCamera, write_capture
from dsr_bench.errors import UserError
from dsr_bench.geometry import Camera, make_camera

#: Image size (height, width) of simulated captures: the RealSense's common 640 x 480 mode.
CAPTURE_IMAGE_SHAPE: tuple[int, int] = (480, 640)
#: Cameras of a simulated capture: every camera of the benchmark (`dsr_bench.constants.CAMERAS`), in its order.
CAPTURE_CAMERAS: tuple[str, ...] = tuple(CAMERAS)
#: Metres per depth unit of the 16-bit depth PNGs (RealSense default).
DEPTH_SCALE: float = 0.001
#: Spawn key of the sensor-noise stream (independent of the episode's stream from the same seed).
_NOISE_STREAM = 0x5E5

#: Rec. 601 luma weights: colour intensity of a pixel, 0..1.
_LUMA = np.array([0.299, 0.587, 0.114])


@dataclass(frozen=True)
class SensorModel:
    """Noise of a simulated RGB-D camera (units in each field's comment); all zero = ideal sensor."""

    baseline: float = 0.055  # m, stereo baseline (D415)
    disparity_sigma: float = 0.08  # px RMS matching error
    correlated_fraction: float = 0.3  # share of the disparity noise variance that is spatially correlated
    correlation_px: float = 3.0  # px, Gaussian correlation length of that share
    disparity_step: float = 1.0 / 32.0  # px, subpixel resolution of the matcher (0 = none)
    stereo_shadow: bool = True  # missing band where the second imager is occluded
    edge_jump: float = 0.01  # m, depth jump to a 4-neighbour that marks a discontinuity
    edge_band_px: int = 1  # px, half-width of the band around discontinuities
    edge_dropout: float = 0.6  # probability a pixel in that band is missing
    dark_start: float = 0.15  # intensity (0..1) below which pixels start to go missing
    dark_full: float = 0.05  # intensity at which the dropout probability reaches dark_dropout
    dark_dropout: float = 0.9  # probability a pixel at or below dark_full is missing
    speckle: float = 0.002  # probability any pixel is missing
    min_range: float = 0.16  # m, no depth nearer (D415 minimum z at 640 x 480)
    max_range: float = 3.0  # m, no depth farther
    color_sigma: float = 2.0  # uint8 levels, Gaussian colour noise
    calib_translation: tuple[float, float] = (0.001, 0.002)  # m, range of the camera-centre error
    calib_rotation_deg: tuple[float, float] = (0.1, 0.2)  # degrees, range of the rotation error
    focal_error: float = 0.002  # relative RMS error of fx and fy
    principal_error: float = 0.5  # px RMS error of cx and cy

    @classmethod
    def ideal(cls) -> "SensorModel":
        """A perfect sensor: depth exact up to the depth unit, nothing missing, exact colour and calibration."""
        return cls(disparity_sigma=0.0, disparity_step=0.0, stereo_shadow=False, edge_dropout=0.0, dark_dropout=0.0,
                   speckle=0.0, min_range=0.0, max_range=np.inf, color_sigma=0.0, calib_translation=(0.0, 0.0),
                   calib_rotation_deg=(0.0, 0.0), focal_error=0.0, principal_error=0.0)


NOISE_MODELS: dict[str, SensorModel] = {"realistic": SensorModel(), "none": SensorModel.ideal()}


def get_sensor_model(name: str) -> SensorModel:
    """The named sensor model ('realistic' or 'none')."""
    if name not in NOISE_MODELS:
        raise UserError(f"--noise {name!r} is not a noise model; choose one of: {', '.join(NOISE_MODELS)}")
    return NOISE_MODELS[name]


# --- depth ---------------------------------------------------------------------------------------------


def depth_discontinuities(depth: np.ndarray, jump: float) -> np.ndarray:
    """Pixels (H, W) bool whose depth differs from a 4-neighbour's by more than `jump` metres (or that border a
    pixel without depth while having one). depth: (H, W) z-depth in metres, 0 = no return."""
    edge = np.zeros(depth.shape, dtype=bool)
    valid = depth > 0
    for axis in (0, 1):
        a = np.swapaxes(depth, 0, axis)
        v = np.swapaxes(valid, 0, axis)
        step = (np.abs(a[1:] - a[:-1]) > jump) | (v[1:] != v[:-1])
        e = np.swapaxes(edge, 0, axis)
        e[1:] |= step
        e[:-1] |= step
    return edge & valid


def stereo_shadow(disparity: np.ndarray, max_shift: int = 32) -> np.ndarray:
    """Pixels (H, W) bool the second imager cannot see (the band left of foreground edges in a RealSense image).

    The depth image is the reference (left) imager's; the second imager sits at +x (to the right), so pixel u of
    disparity d(u) appears at u - d(u) there and is hidden when a nearer pixel u + s (s = 1..max_shift) to its
    right has d(u + s) - d(u) >= s. disparity: (H, W) pixels, 0 = no return."""
    shadow = np.zeros(disparity.shape, dtype=bool)
    for s in range(1, max_shift + 1):
        ahead = disparity[:, s:]
        here = disparity[:, :-s]
        shadow[:, :-s] |= (here > 0) & (ahead - here >= s)
    return shadow


def sensor_depth(depth: np.ndarray, color: np.ndarray, intrinsics: np.ndarray, rng: np.random.Generator,
                 model: SensorModel, depth_scale: float = DEPTH_SCALE) -> np.ndarray:
    """A sensor-like z-depth image (H, W) float32 metres (0 = missing, multiples of depth_scale) from an ideal one.

    depth: (H, W) ideal z-depth in metres (0 = no return); color: (H, W, 3) uint8 ideal colour of the same view
    (dark pixels lose depth); intrinsics: (3, 3) pixels (fx sets the disparity). Draws from `rng` in a fixed order.
    """
    from scipy import ndimage

    depth = np.asarray(depth, dtype=np.float64)
    h, w = depth.shape
    valid = (depth > 0) & (depth >= model.min_range) & (depth <= model.max_range)
    fb = float(intrinsics[0, 0]) * model.baseline
    disparity = np.where(valid, fb / np.where(valid, depth, 1.0), 0.0)
    white = rng.standard_normal((h, w))
    smooth = ndimage.gaussian_filter(rng.standard_normal((h, w)), model.correlation_px, mode="reflect") \
        if model.correlation_px > 0 else np.zeros((h, w))
    smooth /= max(float(smooth.std()), 1e-12)
    noise = np.sqrt(1 - model.correlated_fraction) * white + np.sqrt(model.correlated_fraction) * smooth
    measured = disparity + model.disparity_sigma * noise
    if model.disparity_step > 0:
        measured = np.round(measured / model.disparity_step) * model.disparity_step
    out = np.where(valid & (measured > 0), fb / np.where(measured > 0, measured, 1.0), 0.0)

    missing = ~valid
    if model.stereo_shadow:
        missing |= stereo_shadow(disparity)
    band = depth_discontinuities(depth, model.edge_jump)
    if model.edge_band_px > 1:
        band = ndimage.binary_dilation(band, iterations=model.edge_band_px - 1)
    u_edge, u_dark, u_speckle = rng.random((3, h, w))
    missing |= band & (u_edge < model.edge_dropout)
    intensity = (np.asarray(color, dtype=np.float64) / 255.0) @ _LUMA
    span = max(model.dark_start - model.dark_full, 1e-9)
    p_dark = model.dark_dropout * np.clip((model.dark_start - intensity) / span, 0.0, 1.0)
    missing |= u_dark < p_dark
    missing |= u_speckle < model.speckle
    out = np.where(missing, 0.0, out)
    units = np.clip(np.round(out / depth_scale), 0, np.iinfo(np.uint16).max)
    return (units * depth_scale).astype(np.float32)


def sensor_color(color: np.ndarray, rng: np.random.Generator, model: SensorModel) -> np.ndarray:
    """Colour (H, W, 3) uint8 with Gaussian pixel noise of `model.color_sigma` levels."""
    noisy = np.asarray(color, dtype=np.float64) + model.color_sigma * rng.standard_normal(np.shape(color))
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)


# --- calibration -------------------------------------------------------------------------------------------


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def perturb_calibration(camera: CaptureCamera, rng: np.random.Generator, model: SensorModel) -> CaptureCamera:
    """The camera as a calibration would estimate it: extrinsics moved by a rigid motion about the camera centre
    (translation |t| in model.calib_translation m, rotation in model.calib_rotation_deg degrees, random axes),
    fx, fy scaled by (1 + N(0, focal_error)), cx, cy shifted by N(0, principal_error) px."""
    from scipy.spatial.transform import Rotation

    t = _random_unit(rng) * rng.uniform(*model.calib_translation)
    angle = np.deg2rad(rng.uniform(*model.calib_rotation_deg))
    delta = np.eye(4)
    delta[:3, :3] = Rotation.from_rotvec(_random_unit(rng) * angle).as_matrix()
    extrinsics = np.asarray(camera.extrinsics, dtype=np.float64).copy()
    extrinsics[:3, :3] = extrinsics[:3, :3] @ delta[:3, :3]
    extrinsics[:3, 3] += t
    k = np.asarray(camera.intrinsics, dtype=np.float64).copy()
    k[0, 0] *= 1 + model.focal_error * rng.standard_normal()
    k[1, 1] *= 1 + model.focal_error * rng.standard_normal()
    k[:2, 2] += model.principal_error * rng.standard_normal(2)
    return replace(camera, intrinsics=k, extrinsics=extrinsics)


def calibration_error(stored: CaptureCamera, true: CaptureCamera) -> tuple[float, float]:
    """(camera-centre error m, rotation error degrees) between two calibrations of one camera."""
    from scipy.spatial.transform import Rotation

    dt = float(np.linalg.norm(stored.extrinsics[:3, 3] - true.extrinsics[:3, 3]))
    rel = stored.extrinsics[:3, :3].T @ true.extrinsics[:3, :3]
    return dt, float(np.rad2deg(Rotation.from_matrix(rel).magnitude()))


# --- sequences -----------------------------------------------------------------------------------------------


class _RecordingSet:
    """Wraps an object set and remembers the specs of its last sample (the scene the episode kept)."""

    def __init__(self, object_set) -> None:
        self._set = object_set
        self.name = getattr(object_set, "name", "")
        self.last: list = []

    def sample(self, rng: np.random.Generator, count: int) -> list:
        self.last = list(self._set.sample(rng, count))
        return self.last


def _capture_camera(camera: Camera, depth_scale: float) -> CaptureCamera:
    return CaptureCamera(camera.name, camera.height, camera.width, np.asarray(camera.intrinsics, np.float64),
                         np.asarray(camera.extrinsics, np.float64), depth_scale)


def generate_capture(out: Path, *, name: str, seed: int, objects: str = "procedural", steps: int = 10,
                     objects_per_scene: int = 4, noise: str = "realistic", object_root: str | None = None,
                     image_shape: tuple[int, int] = CAPTURE_IMAGE_SHAPE, object_set=None,
                     overwrite: bool = False) -> Path:
    """Simulate one pushing sequence and write it as a capture directory `out` (see DATASHEET.md).

    The sequence is exactly `generate_episode`'s for (objects, steps, objects_per_scene, heuristic policy, seed);
    images of both cameras are rendered at `image_shape` (H, W) and passed through the named sensor model.
    Raises SceneRejected (generators.episode) when no scene works, UserError on bad arguments.
    """
    from dsr_bench.generators.episode import EpisodeConfig, generate_episode
    from dsr_bench.generators.objects import get_object_set
    from dsr_bench.render import create_renderer

    model = get_sensor_model(noise)
    if object_set is None:
        object_set = get_object_set(objects, object_root)
    recorder = _RecordingSet(object_set)
    # the episode gives poses, actions and pushes only (they do not depend on its cameras); both cameras'
    # images are rendered below at the capture's size, so the episode observes with the front camera alone
    config = EpisodeConfig(objects=objects, steps=steps, objects_per_scene=objects_per_scene, policy="heuristic",
                           cameras=("front",), object_root=object_root)
    episode = generate_episode(config, recorder, seed, name)
    specs = recorder.last
    poses = episode.arrays["object_poses"]
    actions = episode.arrays["action"]
    pushes = np.stack([episode.arrays["push_start"], episode.arrays["push_end"]], axis=1)

    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(_NOISE_STREAM,)))
    renderer = create_renderer(specs, cameras=CAPTURE_CAMERAS, image_shape=image_shape)
    true_cams = {n: _capture_camera(make_camera(n, *image_shape), DEPTH_SCALE) for n in CAPTURE_CAMERAS}
    stored = {n: perturb_calibration(c, rng, model) for n, c in true_cams.items()}
    colors: list[dict[str, np.ndarray]] = []
    depths: list[dict[str, np.ndarray]] = []
    for t in range(len(poses)):
        scene, ids = renderer.scene(poses[t])
        colors.append({})
        depths.append({})
        for cam in CAPTURE_CAMERAS:
            ideal = renderer.render_camera(scene, ids, cam)
            depths[t][cam] = sensor_depth(ideal.depth, ideal.color, true_cams[cam].intrinsics, rng, model)
            colors[t][cam] = sensor_color(ideal.color, rng, model)
    meshes = [(f"{spec.category}_{i}", *spec.mesh(), spec.identity()) for i, spec in enumerate(specs)]
    licensed = objects in ("shapenet", "ycb")
    source = {
        "kind": "simulation", "generator": "generators.capture", "policy": "heuristic",
        **capture_arguments(seed=seed, objects=objects, steps=steps, objects_per_scene=objects_per_scene, noise=noise,
                            image_shape=image_shape),
        "sensor_model": {k: (list(v) if isinstance(v, tuple) else None if v == np.inf else v)
                         for k, v in asdict(model).items()},
        "toolkit_version": episode.attrs["toolkit_version"],
        "scene_attempts": int(episode.scene_attempts),
        "meshes_redistributable": not licensed,
    }
    if licensed:
        source["mesh_licence"] = (f"meshes are copies of the user's own {objects} models; their licence forbids "
                                  "redistribution, so do not share this capture")
    return write_capture(out, name=name, cameras=stored, colors=colors, depths=depths, actions=actions,
                         pushes_world=pushes, objects=meshes, truth_poses=poses, truth_cameras=true_cams,
                         source=source, overwrite=overwrite)


def capture_arguments(*, seed: int, objects: str, steps: int, objects_per_scene: int, noise: str,
                      image_shape: tuple[int, int] = CAPTURE_IMAGE_SHAPE) -> dict:
    """The arguments that define a simulated capture, as recorded in its capture.json `source`."""
    return {"seed": int(seed), "objects": objects, "steps": int(steps), "objects_per_scene": int(objects_per_scene),
            "noise": noise, "image_shape": list(image_shape)}


def recorded_capture_arguments(path: Path) -> dict:
    """The `capture_arguments` an existing capture directory records in its capture.json `source` (a key it
    lacks reads None; an unreadable capture.json reads {}): compared with the expected ones on resumption."""
    import json

    keys = capture_arguments(seed=0, objects="", steps=0, objects_per_scene=0, noise="")
    try:
        source = json.loads((Path(path) / "capture.json").read_text()).get("source", {})
        return {k: source.get(k) for k in keys}
    except (OSError, ValueError, AttributeError):
        return {}


# --- many captures -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CapturePlan:
    """What a `dsr-bench generate-captures` invocation produces: captures OUT/seq_0000 ... of `num` sequences,
    capture i from `sequence_seed(seed, i)`."""

    out: Path
    num: int = 1
    objects: str = "procedural"
    steps: int = 10
    objects_per_scene: int = 4
    seed: int = 0
    noise: str = "realistic"
    object_root: str | None = None
    overwrite: bool = False

    def arguments(self, seed: int) -> dict:
        """The capture_arguments of the capture made from `seed`."""
        return capture_arguments(seed=seed, objects=self.objects, steps=self.steps,
                                 objects_per_scene=self.objects_per_scene, noise=self.noise)


@dataclass
class CaptureJobs:
    """What `prepare_captures` found: the captures to write (name, seed), those already complete, the object set."""

    todo: list[tuple[str, int]]
    skipped: list[str]
    object_set: object


def prepare_captures(plan: CapturePlan) -> CaptureJobs:
    """Check everything (arguments, --out, meshes, existing captures) before any simulation. An existing capture
    made with the same arguments is skipped; one made with other arguments is refused unless `plan.overwrite`
    (`generators.run.needs_writing`). Removes the temporaries of abandoned writers in --out."""
    from dsr_bench.dataset.splits import sequence_name, sequence_seed
    from dsr_bench.generators.objects import get_object_set
    from dsr_bench.generators.run import check_scene_arguments, needs_writing

    check_scene_arguments(plan.num, plan.steps, plan.objects_per_scene)
    get_sensor_model(plan.noise)
    out = Path(plan.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory; give a directory for the captures")
    object_set = get_object_set(plan.objects, plan.object_root)
    todo, skipped = [], []
    for i in range(plan.num):
        name, seed = sequence_name(i), sequence_seed(plan.seed, i)
        if needs_writing(out / name, plan.arguments(seed), recorded_capture_arguments,
                         f"{out / name} exists with other arguments; pass --overwrite to replace it or choose "
                         "another --out", overwrite=plan.overwrite):
            todo.append((name, seed))
        else:
            skipped.append(name)
    if out.is_dir():
        clean_temporaries(out, "seq_*")
    return CaptureJobs(todo, skipped, object_set)


def generate_captures(plan: CapturePlan, jobs: CaptureJobs, started: Callable[[str], None] | None = None,
                      finished: Callable[[str], None] | None = None, workers: int = 1) -> list[Path]:
    """Write the captures `jobs.todo` (from `prepare_captures`), each atomically, in `workers` processes (one:
    here, in order; a capture is a function of its seed alone, so the files are the same either way);
    `started(name)` / `finished(name)` are called around each (with workers, `started` as it is handed out). A
    scene that cannot be set up is a UserError naming the fix."""
    from dsr_bench.parallel import as_finished

    names = [name for name, _ in jobs.todo]
    if workers <= 1 or len(jobs.todo) <= 1:
        written = []
        for name, seed in jobs.todo:
            if started:
                started(name)
            written.append(_write_capture(plan, jobs.object_set, (name, seed)))
            if finished:
                finished(name)
        return written
    from functools import partial

    for name in names:
        if started:
            started(name)
    done: list[object] = [None] * len(names)
    for position, path in as_finished(partial(_write_capture, plan, None), jobs.todo, workers):
        done[position] = path
        if finished:
            finished(names[position])
    return [p for p in done if isinstance(p, Path)]


def _write_capture(plan: CapturePlan, object_set, job: tuple[str, int]) -> Path:
    """One capture of `plan` (name, seed); `object_set` None: loaded here (a worker process)."""
    from dsr_bench.generators.episode import SceneRejected
    from dsr_bench.generators.objects import get_object_set

    name, seed = job
    if object_set is None:
        object_set = get_object_set(plan.objects, plan.object_root)
    try:
        return generate_capture(Path(plan.out) / name, name=name, seed=seed, objects=plan.objects, steps=plan.steps,
                                objects_per_scene=plan.objects_per_scene, noise=plan.noise,
                                object_root=plan.object_root, object_set=object_set, overwrite=True)
    except SceneRejected as exc:
        raise UserError(f"{name}: {exc}; try another --seed or fewer --objects-per-scene") from None
