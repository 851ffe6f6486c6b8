"""Conventions of the grid, poses and cameras (see DATASHEET.md, Conventions)."""

import numpy as np
import pytest

from dsr_bench.constants import GRID_BOUNDS, GRID_SHAPE, VOXEL_SIZE
from dsr_bench.geometry import (
    direction_vector, make_camera, matrix_to_pose, pixel_to_world, pose_to_matrix, quat_to_matrix, relative_motion,
    resized_camera, voxel_points, voxel_points_of, voxel_to_world, world_to_pixel, world_to_voxel,
)


def test_grid_matches_official_bounds():
    extent = GRID_BOUNDS[:, 1] - GRID_BOUNDS[:, 0]
    # axis order (y, x, z): 128 along y, 128 along x, 48 along z, 4 mm voxels
    assert np.allclose(extent[[1, 0, 2]] / VOXEL_SIZE, GRID_SHAPE)


def test_voxel_sample_points_axis_order_corner_and_round_trip():
    points = voxel_points()
    assert points.shape == GRID_SHAPE + (3,)
    # index 0 runs along world y, index 1 along world x
    assert np.isclose(points[1, 0, 0, 1] - points[0, 0, 0, 1], VOXEL_SIZE)
    assert np.isclose(points[0, 1, 0, 0] - points[0, 0, 0, 0], VOXEL_SIZE)
    # the official release samples a voxel at its lower corner: bound_min + index * 0.004
    assert np.array_equal(points[0, 0, 0], GRID_BOUNDS[:, 0])
    assert np.allclose(points[5, 7, 3], GRID_BOUNDS[:, 0] + np.array([7, 5, 3]) * VOXEL_SIZE, atol=0)
    idx = np.array([[3, 100, 7], [127, 0, 47]])
    world = voxel_to_world(idx)
    assert np.allclose(world_to_voxel(world), idx)
    assert np.allclose(world, points[tuple(idx.T)]) and np.array_equal(voxel_points_of(idx), points[tuple(idx.T)])


def test_workspace_cells_row_along_y():
    rc = world_to_pixel(np.array([[0.5, 0.0], [0.245, -0.255]]))
    assert rc.tolist() == [[64, 64], [0, 0]]
    assert np.allclose(world_to_pixel(pixel_to_world(np.array([[10, 120]]))), [[10, 120]])


def test_direction_angles():
    assert np.allclose(direction_vector(0), [1, 0])
    assert np.allclose(direction_vector(2), [0, 1])
    # exact: 0 where the cosine or sine is 0 (numpy's cos(pi / 2) is 6e-17), the same bits on every CPU
    assert direction_vector(2)[0] == 0.0 and direction_vector(6).tolist() == [0.0, -1.0]
    angles = np.arange(8) * np.pi / 4
    assert np.allclose(direction_vector(np.arange(8)), np.stack([np.cos(angles), np.sin(angles)], 1), atol=1e-15)
    with pytest.raises(ValueError, match="0..7"):
        direction_vector(8)
    assert np.allclose(direction_vector(5), [-np.sqrt(0.5), -np.sqrt(0.5)])


def test_quaternion_xyzw_and_relative_motion():
    yaw = np.pi / 2
    rot = quat_to_matrix(np.array([0, 0, np.sin(yaw / 2), np.cos(yaw / 2)]))
    assert np.allclose(rot @ [1, 0, 0], [0, 1, 0])
    a = np.array([0.4, 0.1, 0.03, 0, 0, 0, 1.0])
    b = np.array([0.5, 0.1, 0.03, 0, 0, np.sin(0.2), np.cos(0.2)])
    motion = relative_motion(a, b)
    assert np.allclose(motion @ pose_to_matrix(a), pose_to_matrix(b))


def test_front_camera_looks_at_workspace_centre():
    cam = make_camera("front", 240, 320)
    assert np.allclose(cam.extrinsics[:3, 3], [0.5, -0.7, 0.3])
    uv, z = cam.project(np.array([0.5, 0.0, 0.0]))
    assert np.allclose(uv, [160, 120], atol=1e-6) and z > 0
    # up in the world is up in the image (smaller v), right is +x
    uv_up, _ = cam.project(np.array([0.5, 0.0, 0.05]))
    uv_right, _ = cam.project(np.array([0.55, 0.0, 0.0]))
    assert uv_up[1] < 120 and uv_right[0] > 160
    assert np.isclose(cam.intrinsics[0, 0], 160 / np.tan(np.deg2rad(34.7)))


def test_backproject_inverts_project():
    cam = make_camera("back", 24, 32)
    depth = np.full((24, 32), 0.6)
    pts = cam.backproject(depth)
    uv, z = cam.project(pts.reshape(-1, 3))
    v, u = np.meshgrid(np.arange(24), np.arange(32), indexing="ij")
    assert np.allclose(z, 0.6) and np.allclose(uv, np.stack([u, v], -1).reshape(-1, 2))


def test_camera_attrs_round_trip_through_json():
    import json

    from dsr_bench.geometry import Camera

    cam = resized_camera(make_camera("back", 480, 640), 240, 320)
    attrs = json.loads(json.dumps(cam.as_attrs()))  # as a sequence file stores it
    assert attrs["convention"] == "opencv, camera-to-world" and (attrs["height"], attrs["width"]) == (240, 320)
    back = Camera.from_attrs("back", attrs)
    assert (back.name, back.height, back.width) == ("back", 240, 320)
    assert type(back.height) is int and type(back.width) is int
    assert np.array_equal(back.intrinsics, cam.intrinsics) and np.array_equal(back.extrinsics, cam.extrinsics)
    assert back.as_attrs() == cam.as_attrs()
    assert np.array_equal(back.ray_directions_world(), cam.ray_directions_world())


def test_unknown_camera():
    with pytest.raises(ValueError, match="unknown camera 'side'"):
        make_camera("side", 10, 10)


def test_matrix_to_pose_inverts_pose_to_matrix_with_non_negative_qw():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.standard_normal(4)
        q /= np.linalg.norm(q)
        pose = np.concatenate([rng.uniform(-1, 1, 3), q])
        back = matrix_to_pose(pose_to_matrix(pose))
        assert back.shape == (7,) and back.dtype == np.float64 and back[6] >= 0
        assert np.allclose(back, pose if q[3] >= 0 else np.concatenate([pose[:3], -q]), atol=1e-12)
        assert np.allclose(pose_to_matrix(back), pose_to_matrix(pose), atol=1e-12)


def test_resized_camera_keeps_rays_of_corresponding_pixels():
    full = make_camera("front", 480, 640)
    small = resized_camera(full, 240, 320)
    assert (small.height, small.width, small.name) == (240, 320, "front")
    assert np.array_equal(small.extrinsics, full.extrinsics)
    assert np.array_equal(small.intrinsics, make_camera("front", 240, 320).intrinsics)
    # stored pixel (u', v') looks along the ray of full-resolution pixel (2 u', 2 v'); also for unequal scales
    assert np.allclose(small.ray_directions_world(), full.ray_directions_world()[::2, ::2], atol=1e-12)
    odd = resized_camera(full, 120, 320)
    point = np.array([0.45, 0.05, 0.02])
    (u, v), z = full.project(point)
    (u2, v2), z2 = odd.project(point)
    assert np.allclose([u2, v2, z2], [u / 2, v / 4, z], atol=1e-9)
