"""Grid, pose and camera geometry shared by the generator, the readers, the metrics and the viewer:
`transforms` (poses and their matrices, fixed-order products), `grid` (voxel and workspace grids), `camera` (pinhole
cameras), `tsdf` (projective TSDF), `groundtruth` (flow from poses) and `projection` (a volume's flow read at
world points: 3D predictions on the 2D track).

Conventions (see DATASHEET.md):
- World frame: table plane z = 0, metres. Quaternions are (x, y, z, w), as in pybullet and the
  official release.
- Volumes are indexed (iy, ix, iz); voxel (iy, ix, iz) is sampled at its sample point
  bound_min + (index + VOXEL_SAMPLE_OFFSET) * VOXEL_SIZE, the voxel's lower corner as in the
  official release (TSDF, amodal masks and 3D flow alike).
- The workspace grid of actions and the heightmap (128 x 128 cells, row along y) is an image:
  cell (row, col) covers [bound_min + index * VOXEL_SIZE, + VOXEL_SIZE) and is sampled at its centre.
- Cameras use the OpenCV convention (x right, y down, z forward); an extrinsic is the 4x4
  camera-to-world transform; pixel (u, v) centres sit at integer coordinates and the principal
  point is (W / 2, H / 2), as in the official release.
"""

from dsr_bench.geometry.camera import (
    Camera, look_at, pinhole_inverse, pinhole_intrinsics, make_camera, resized_camera,
)
from dsr_bench.geometry.grid import (
    axis_samples, voxel_points, voxel_points_of, world_to_voxel, voxel_to_world, world_to_pixel, pixel_to_world,
    direction_vector,
)
from dsr_bench.geometry.projection import flow_at_points
from dsr_bench.geometry.transforms import (
    quat_to_matrix, pose_to_matrix, matrix_to_pose, apply_matrix, dot_last, vector_norm, transform_points,
    rigid_inverse, compose, relative_motion, rotation_angle,
)

__all__ = ["Camera", "apply_matrix", "axis_samples", "compose", "direction_vector", "dot_last", "flow_at_points",
           "look_at", "make_camera", "matrix_to_pose", "pinhole_intrinsics", "pinhole_inverse", "pixel_to_world",
           "pose_to_matrix", "quat_to_matrix", "relative_motion", "resized_camera", "rigid_inverse", "rotation_angle",
           "transform_points", "vector_norm", "voxel_points", "voxel_points_of", "voxel_to_world", "world_to_pixel",
           "world_to_voxel"]
