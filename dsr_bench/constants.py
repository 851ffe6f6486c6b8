"""The benchmark's fixed constants, in one place.

Every other module imports its grid, camera, unit and policy constants from here. Values follow the
official DSR release (see DATASHEET.md, "Conventions"), lengths in metres, angles in radians.
"""

from __future__ import annotations

import numpy as np

# --- The voxel grid --------------------------------------------------------------------------
#: Voxel edge length (m).
VOXEL_SIZE: float = 0.004
#: World bounds of the volume, rows (x, y, z), columns (min, max), metres.
GRID_BOUNDS: np.ndarray = np.array([[0.244, 0.756], [-0.256, 0.256], [0.0, 0.192]])
#: Volume shape in the benchmark's axis order (world y, world x, z).
GRID_SHAPE: tuple[int, int, int] = (128, 128, 48)
#: Where a volume samples voxel (iy, ix, iz), in voxels from bound_min: 0, the voxel's lower corner
#: bound_min + index * VOXEL_SIZE, as the official release's TSDF fusion, masks and flow do (and so
#: the inputs the authors' networks were trained on). TSDF, amodal masks and 3D flow all use it.
VOXEL_SAMPLE_OFFSET: float = 0.0
#: Amodal masks as the official release makes them: a voxel belongs to an object when the object's
#: solid meets the cube of one voxel's edge centred on the voxel's sample point (the official code
#: rounds a dense solid point set to the nearest sample point), tested on this many sub-samples per
#: axis (4: a 1 mm sub-grid).
MASK_SUBSAMPLES: int = 4
#: Human-readable axis order of every volume, the action map and flow components.
AXIS_ORDER: str = "y,x,z"
FLOW_COMPONENTS: str = "dy,dx,dz"
#: Workspace centre on the table (m).
WORKSPACE_CENTER: tuple[float, float] = (0.5, 0.0)
#: TSDF truncation distance: 5 voxels (m).
TSDF_TRUNCATION: float = 5 * VOXEL_SIZE
#: voxel^2 -> cm^2 (0.4 cm voxels), the official factor for motion MSE.
VOXEL2_TO_CM2: float = 0.16
#: The metrics' visible surface: voxels with TSDF_SURFACE_LOW < tsdf < 0 (and an object, above z = 0).
TSDF_SURFACE_LOW: float = -0.99

# --- Actions ---------------------------------------------------------------------------------
NUM_DIRECTIONS: int = 8
#: Push primitive heights and length (m).
PUSH_APPROACH_HEIGHT: float = 0.15
PUSH_HEIGHT: float = 0.005
PUSH_LENGTH: float = 0.15
#: The simulated pusher: the official generator's thin stick, a cylinder (m). The arm carries its lower
#: end 2.5 mm above the tool tip it commands to PUSH_HEIGHT, and ends the push phase about 14.6 cm along
#: the commanded PUSH_LENGTH (generators/arm.py).
PUSHER_RADIUS: float = 0.003
PUSHER_LENGTH: float = 0.14
#: The real rig's pusher: a cylinder tool (m), for the annotator's contact checks.
RIG_PUSHER_RADIUS: float = 0.01
#: Start-point search of the official code (m, pixels, count).
START_BACKOFF: float = 0.04
START_STEP: float = 0.01
START_MAX_STEPS: int = 5
START_FREE_RADIUS_PX: int = 5
FREE_HEIGHT: float = 0.005
AHEAD_DISTANCE: float = 0.04

# --- Cameras ---------------------------------------------------------------------------------
#: Horizontal field of view (rad), RealSense D415-like.
CAMERA_HFOV: float = float(np.deg2rad(69.4))
#: The cameras of the benchmark, one entry each: position, look-at target, up vector (world, m). Every list of
#: camera names (generate --cameras, simulated captures, a real rig's cameras) is this table's, in its order; adding
#: a camera: DATASHEET.md, "Adding a camera".
CAMERAS: dict[str, dict[str, tuple[float, float, float]]] = {
    "front": {"eye": (0.5, -0.7, 0.3), "target": (0.5, 0.0, 0.0), "up": (0.0, 0.3, 0.7)},
    "back": {"eye": (0.5, 0.7, 0.3), "target": (0.5, 0.0, 0.0), "up": (0.0, -0.3, 0.7)},
}
#: The camera the models see (the 2D track's images and the predictions' motion_2d): required in every sequence,
#: capture and rig; the others are optional views.
MODEL_CAMERA: str = "front"
#: Image size (height, width) of the stored 2D data.
IMAGE_SHAPE: tuple[int, int] = (240, 320)
#: Depth image size used to integrate the TSDF (2 mm pixels at the far edge of the grid).
TSDF_IMAGE_SHAPE: tuple[int, int] = (480, 640)

# --- Scenes ------------------------------------------------------------------------------------
DEFAULT_STEPS: int = 10
DEFAULT_OBJECTS_PER_SCENE: int = 4
MAX_OBJECTS_PER_SCENE: int = 5
MIN_VISIBLE_FRACTION: float = 0.4
MIN_OBJECT_SEPARATION: float = 0.07
MIN_LARGE_SEPARATION: float = 0.13
#: Mask slots of the models (K), background last.
NUM_MASK_SLOTS: int = 5

# --- Policy ----------------------------------------------------------------------------------
POLICY_DIRECTION_TEMPERATURE: float = 2.0
POLICY_FAR_FROM_CENTER: float = 0.2
#: Added by the policy helper: the official heuristic's remaining numbers (m, counts, score weights).
POLICY_LARGE_OBJECT_BONUS: float = 0.5
POLICY_COUNTER_MAX: int = 2
POLICY_COUNTER_RESET: int = -2
POLICY_EARLY_RESET_PROB: float = 0.5
POLICY_NEIGHBOUR_DISTANCE: float = 0.15
POLICY_NEAR_START_DISTANCE: float = 0.25
POLICY_OUTWARD_PENALTY: float = 10.0
POLICY_MAX_SAMPLES: int = 64

# --- Planning track (docs/planning.md) ---------------------------------------------------------
#: Pushes per plan (the paper: "action sequences with a length of 3"), and per task's target.
PLAN_STEPS: int = 3
#: Candidate actions per step (appendix: 100 for DSR-Net and SE3Pose-Net, 200 for SE3-Net).
DEFAULT_CANDIDATES: int = 100
#: Candidates scored per model call (memory: one uint8 volume of 786 kB per candidate in flight).
DEFAULT_BATCH: int = 25
#: lambda of the cost (per cm^2): the weight of an object's position MSE (cm^2, the mean over x, y, z of
#: the squared centroid difference) against its IoU; 0.1 makes a 3.2 cm error along every axis (5.5 cm
#: in 3D) cost as much as an IoU of 1. The paper gives no value ("a weighting factor for each channel").
COST_LAMBDA: float = 0.1
#: The position MSE (cm^2) charged for a target object that no non-empty predicted slot is matched to:
#: that of a 10 cm error along every axis.
UNMATCHED_POSITION_MSE: float = 100.0
#: Tie-break of the matching: slot-object scores are IoU + MATCH_TIE_BREAK / (1 + centroid distance in cm),
#: so that pairs of equal IoU (in practice: no overlap at all) match by proximity. Never outweighs IoU.
MATCH_TIE_BREAK: float = 1e-3
#: The furthest a start point is backed off from the chosen cell of an object, in cells (10 cm).
MAX_BACKOFF_CELLS: int = 25
#: How far a clear push's sweep is checked, in cells from its start (44 cells, 17.6 cm): the tool stays below the
#: objects' height along the push (about 14.6 cm) and the start of its lift (to about 16 cm; generators/arm.py).
CLEAR_SWEEP_CELLS: int = 44
#: Clear pushes (`dsr_bench.planning.sampling.sample_clear`) among a step's candidates: a plan may keep the scene.
CLEAR_CANDIDATES: int = 10
#: A learned planner's margin (cost units: an IoU of 1 on one object is 1): it pushes an object only when that
#: push's predicted cost beats the best clear push's by more than this, else it keeps the scene (a clear push).
#: Chosen on the validation tasks `plan-val` (training objects), never on plan-novel-test (docs/planning.md).
PLAN_MARGIN: float = 0.75
#: Voxels at or above this z index count as above the table for footprints (8 mm > FREE_HEIGHT).
FOOTPRINT_MIN_Z: int = 2

# --- File format -----------------------------------------------------------------------------
#: 2 (dsr-bench 0.2): digests by group (`dsr_bench.dataset.digests`), the exact renderer, the authors' policy
#: and dynamics; files of schema 1 hold the data of an earlier benchmark version and are regenerated.
#: 3 (dsr-bench 0.3): the same arrays; a camera's world points may be left out of the file and derived from its
#: depth on reading (`derived_arrays`), and the 3D flow is stored in tiles (dsr_bench.dataset.storage).
SCHEMA_VERSION: int = 3
#: Schemas this toolkit reads: 2 holds the same arrays with every camera's points stored.
READABLE_SCHEMA_VERSIONS: tuple[int, ...] = (2, 3)
FORMAT_NAME: str = "dsr-bench-sequence"
