"""TSDF definition and pose-derived scene flow."""

import numpy as np

from dsr_bench.constants import GRID_BOUNDS, TSDF_TRUNCATION, VOXEL_SIZE
from dsr_bench.geometry import make_camera, rigid_inverse, transform_points, voxel_points
from dsr_bench.geometry.groundtruth import rigid_scene_flow_2d, rigid_scene_flow_3d
from dsr_bench.geometry.tsdf import integrate_tsdf


def _plane_depth(cam, height):
    """Exact z-depth of the horizontal plane z = height seen by `cam`."""
    dirs = cam.ray_directions_world()
    t = (height - cam.extrinsics[2, 3]) / dirs[..., 2]
    return np.where(t > 0, t, 0.0)


def test_tsdf_of_a_plane_matches_the_definition():
    cam = make_camera("front", 480, 640)
    height = 0.05
    tsdf = integrate_tsdf(_plane_depth(cam, height), cam)
    assert tsdf.dtype == np.float32 and tsdf.min() >= -1 and tsdf.max() <= 1
    # the definition along each voxel's own ray: sdf = depth of the plane on that ray - z_cam(voxel)
    centres = voxel_points()[::8, ::8].reshape(-1, 3)
    origin = cam.extrinsics[:3, 3]
    z_cam = (centres - origin) @ cam.extrinsics[:3, 2]
    s = (height - origin[2]) / (centres[:, 2] - origin[2])
    sdf = z_cam * (s - 1)
    expected = np.where(sdf >= -TSDF_TRUNCATION, np.minimum(1, sdf / TSDF_TRUNCATION), 1.0)
    got = tsdf[::8, ::8].reshape(-1)
    clear = np.abs(sdf + TSDF_TRUNCATION) > 0.006  # away from the band's far edge (nearest-pixel depth: ~5 mm)
    error = np.abs(got - expected)[clear]
    # nearest-pixel depth on a grazing plane: at most ~5 mm off, and exact on average
    assert error.max() < 0.25 and error.mean() < 0.01
    # above the plane is positive (free), the band just below the surface is negative
    assert np.all(got[centres[:, 2] > height + 0.004] > 0)
    assert np.any(got < 0) and np.all(got[got < 0] >= -1)


def _authors_tsdf(depth: np.ndarray, cam, trunc: float = TSDF_TRUNCATION) -> np.ndarray:
    """The TSDF by the official release's definition, written from its notes alone: volume initialised to
    +1; each voxel's corner bound_min + index * 0.004 projected with the camera's pose to the rounded
    pixel; where that pixel's depth d > 0 and d - z >= -trunc the value becomes min(1, (d - z) / trunc)."""
    ny, nx, nz = 128, 128, 48
    iy, ix, iz = np.meshgrid(np.arange(ny), np.arange(nx), np.arange(nz), indexing="ij")
    world = np.stack([GRID_BOUNDS[0, 0] + ix * VOXEL_SIZE, GRID_BOUNDS[1, 0] + iy * VOXEL_SIZE,
                      GRID_BOUNDS[2, 0] + iz * VOXEL_SIZE], -1).reshape(-1, 3)
    c = transform_points(rigid_inverse(cam.extrinsics), world)
    z = c[:, 2]
    u = np.round(c[:, 0] * cam.intrinsics[0, 0] / z + cam.intrinsics[0, 2]).astype(int)
    v = np.round(c[:, 1] * cam.intrinsics[1, 1] / z + cam.intrinsics[1, 2]).astype(int)
    seen = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    d = np.zeros(len(z))
    d[seen] = depth[v[seen], u[seen]]
    sdf = d - z
    tsdf = np.ones(len(z))
    update = seen & (d > 0) & (sdf >= -trunc)
    tsdf[update] = np.minimum(1.0, sdf[update] / trunc)
    return tsdf.reshape(ny, nx, nz)


def test_tsdf_is_the_authors_definition_at_voxel_corners():
    """On a rendered scene (a box on the table) at the authors' 960 x 1280, and at our 480 x 640: our
    TSDF equals a TSDF written from the release's definition (corner sampling) to float32 rounding."""
    from types import SimpleNamespace

    import trimesh

    from dsr_bench.render import create_renderer

    box = trimesh.creation.box(extents=[0.06, 0.05, 0.07])
    spec = SimpleNamespace(parts=[SimpleNamespace(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces))],
                           color=(1.0, 0.0, 0.0))
    pose = np.array([[0.52, 0.03, 0.035, 0.0, 0.0, np.sin(0.3), np.cos(0.3)]])
    for shape in ((960, 1280), (480, 640)):
        cam = make_camera("front", *shape)
        renderer = create_renderer([spec], cameras={"front": cam})
        depth = renderer.render_camera(*renderer.scene(pose), "front").depth
        ours = integrate_tsdf(depth, cam)
        theirs = _authors_tsdf(depth.astype(np.float64), cam)
        assert np.abs(ours - theirs).max() < 1e-5, shape
        assert (theirs < 0).sum() > 1000  # the box and the table leave a band


def test_tsdf_missing_depth_stays_free():
    cam = make_camera("front", 24, 32)
    assert np.all(integrate_tsdf(np.zeros((24, 32)), cam) == 1.0)


def test_rigid_flow_translation_and_rotation():
    mask = np.zeros((128, 128, 48), np.uint8)
    mask[10:14, 20:22, 0:3] = 1
    mask[60:62, 60:62, 5:7] = 2
    p0 = np.array([[0.3, -0.2, 0.01, 0, 0, 0, 1], [0.5, 0.0, 0.02, 0, 0, 0, 1.0]])
    p1 = p0.copy()
    p1[0, :3] += [0.008, -0.004, 0.0]  # +2 voxels in x, -1 in y
    yaw = np.pi / 2
    p1[1, 3:] = [0, 0, np.sin(yaw / 2), np.cos(yaw / 2)]
    flow = rigid_scene_flow_3d(mask, p0, p1)
    assert flow.shape == (3, 128, 128, 48) and flow.dtype == np.float32
    obj1 = flow[:, mask == 1]
    assert np.allclose(obj1[0], -1) and np.allclose(obj1[1], 2) and np.allclose(obj1[2], 0)
    assert np.all(flow[:, mask == 0] == 0)
    # rotation about the object's origin: a voxel's sample point at offset (dx, dy) moves to (-dy, dx)
    c = voxel_points()[60, 60, 5]
    off = c - p0[1, :3]
    expected_world = np.array([-off[1], off[0], off[2]]) - off
    assert np.allclose(flow[:, 60, 60, 5], expected_world[[1, 0, 2]] / VOXEL_SIZE, atol=1e-4)


def test_rigid_flow_2d_components_dy_dx_dz():
    points = np.full((2, 2, 3), np.nan, np.float32)
    points[0, 0] = [0.5, 0.0, 0.01]
    mask = np.array([[1, 0], [0, 0]], np.uint8)
    p0 = np.array([[0.5, 0.0, 0.01, 0, 0, 0, 1.0]])
    p1 = p0.copy()
    p1[0, 0] += 0.02
    flow = rigid_scene_flow_2d(points, mask, p0, p1)
    assert np.allclose(flow[0, 0], [0, 0.02, 0]) and np.all(flow[1:] == 0) and np.all(flow[0, 1] == 0)
    assert GRID_BOUNDS.shape == (3, 2)
