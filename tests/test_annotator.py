"""The annotator's pure parts: alignment, state, session (autosave, resume, carry-forward), export, CLI paths.

Fixture: a small simulated capture (3 objects, 3 pushes, 240 x 320 images, ideal sensor) from
`generators.capture.generate_capture`, with its true poses in truth.json.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from dsr_bench.errors import UserError
from dsr_bench.geometry import pose_to_matrix


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    pytest.importorskip("pybullet")
    pytest.importorskip("open3d")
    from generators.capture import generate_capture

    out = tmp_path_factory.mktemp("captures") / "seq_000"
    return generate_capture(out, name="seq_000", seed=1, steps=3, objects_per_scene=3, noise="none",
                            image_shape=(240, 320))


@pytest.fixture(scope="module")
def truth(capture_dir) -> np.ndarray:
    from dsr_bench.capture import load_capture

    return load_capture(capture_dir).truth_poses()


def _errors(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    from annotator.align import pose_delta

    return pose_delta(pose_to_matrix(a), pose_to_matrix(b))


def _place_from_truth(session, truth, step: int = 0, snap: bool = True) -> None:
    """Initialise every object at `step` from 4 picked pairs on the true pose (as a user's picks would)."""
    for i in range(session.num_objects):
        v, _ = session.capture.mesh(i)
        idx = np.linspace(0, len(v) - 1, 4).astype(int)
        m = pose_to_matrix(truth[step, i])
        session.init_from_picks(i, v[idx], v[idx] @ m[:3, :3].T + m[:3, 3])
        if snap:
            session.snap(i)


def _moved(truth, t: int) -> list[int]:
    return [i for i in range(truth.shape[1]) if max(np.array(_errors(truth[t, i], truth[t + 1, i])) * [1000, 30]) > 1.0]


# --- align -----------------------------------------------------------------------------------------------------------


def test_kabsch_recovers_a_rigid_transform_exactly():
    from annotator.align import kabsch, rotvec_to_matrix

    rng = np.random.default_rng(0)
    src = rng.uniform(-0.05, 0.05, (5, 3))
    truth = np.eye(4)
    truth[:3, :3] = rotvec_to_matrix([0.3, -1.2, 2.0])
    truth[:3, 3] = [0.5, -0.1, 0.03]
    got = kabsch(src, src @ truth[:3, :3].T + truth[:3, 3])
    np.testing.assert_allclose(got, truth, atol=1e-12)
    assert np.isclose(np.linalg.det(got[:3, :3]), 1.0)


def test_kabsch_rejects_too_few_and_collinear_picks():
    from annotator.align import kabsch

    line = np.array([[0.0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [0.03, 0.0001, 0]])
    with pytest.raises(UserError, match="one line"):
        kabsch(line, line + 0.1)
    with pytest.raises(UserError, match="at least 3"):
        kabsch(line[:2], line[:2])
    with pytest.raises(UserError, match="in pairs"):
        kabsch(line[:3], line)


def test_sample_surface_is_on_the_mesh_with_outward_normals():
    import trimesh

    from annotator.align import sample_surface

    box = trimesh.creation.box((0.04, 0.06, 0.02))
    s = sample_surface(box.vertices, box.faces[:, ::-1], spacing=0.002)  # inward faces are flipped
    half = np.array([0.02, 0.03, 0.01])
    on_face = np.isclose(np.abs(s.points), half, atol=1e-9).any(1)
    assert on_face.all() and np.all(np.abs(s.points) <= half + 1e-9)
    assert np.all(np.einsum("ij,ij->i", s.points, s.normals) > 0)  # outward on a centred box
    np.testing.assert_allclose(s.centre, 0, atol=1e-12)


def test_icp_recovers_a_perturbed_pose_on_clean_data(capture_dir, truth):
    from annotator import align
    from annotator.session import Session

    session = Session.open(capture_dir, capture_dir.parent / "work_icp")
    rng = np.random.default_rng(1)
    for i in range(session.num_objects):
        true_m = pose_to_matrix(truth[0, i])
        start = true_m.copy()
        start[:3, :3] = align.rotvec_to_matrix(rng.normal(size=3) * np.deg2rad(2.0) / np.sqrt(3)) @ start[:3, :3]
        start[:3, 3] += rng.normal(size=3) * 0.003 / np.sqrt(3)
        result = session._icp(i, 0, start)
        assert result.applied and result.score.accepted, result.score.reason
        dt, dr = align.pose_delta(true_m, result.transform)
        assert dt < 0.002 and np.rad2deg(dr) < 1.0, (i, dt, np.rad2deg(dr))
        truth_score = session._fit(i, 0, truth[0, i])
        assert truth_score.coverage > 0.8 and truth_score.rmse < 0.001


def test_icp_rejects_jumps_and_keeps_the_start(capture_dir, truth):
    from annotator import align
    from annotator.session import Session

    session = Session.open(capture_dir, capture_dir.parent / "work_jump")
    start = pose_to_matrix(truth[0, 0])
    start[:3, 3] += [0.008, 0.0, 0.0]
    result = session._icp(0, 0, start, max_translation=0.004)
    assert not result.applied and not result.score.accepted
    assert "jump" in result.score.reason and result.translation > 0.004
    np.testing.assert_array_equal(result.transform, start)
    # far from its points: nothing to match; the pose stays, the score says why
    far = pose_to_matrix(truth[0, 0])
    far[:3, 3] += [0.0, 0.0, 0.2]
    far_result = align.icp(session.samples(0), session._crop(0, far, session.samples(0)), far, session._views(0))
    assert not far_result.applied and "cloud points" in far_result.score.reason


def test_fit_score_drops_when_the_mesh_is_off(capture_dir, truth):
    from annotator.session import Session

    session = Session.open(capture_dir, capture_dir.parent / "work_score")
    good = session._fit(1, 0, truth[0, 1])
    off = truth[0, 1].copy()
    off[0] += 0.015
    bad = session._fit(1, 0, off)
    assert good.accepted and not bad.accepted
    assert bad.coverage < good.coverage - 0.2 and good.fitness > 0.8


# --- state and session ------------------------------------------------------------------------------------------------


def test_state_dict_round_trip():
    from annotator.state import AnnotationState, StateError

    state = AnnotationState("cap", 2, 2)
    op = state.operation("pick", {(0, 1): (np.array([0.5, 0, 0.02, 0, 0, 0, 1.0]), "initialised",
                                           {"rmse": float("nan"), "coverage": 0.5})})
    state.apply(op)
    state.count("pick")
    d = json.loads(json.dumps(state.to_dict(), allow_nan=False))
    back = AnnotationState.from_dict(d)
    assert back.to_dict() == d
    np.testing.assert_array_equal(back.poses, state.poses)
    bad = dict(d, poses=d["poses"][:1])
    with pytest.raises(StateError, match="steps"):
        AnnotationState.from_dict(bad)
    with pytest.raises(StateError, match="format"):
        AnnotationState.from_dict({"format": "other"})


def test_undo_redo_are_exact(capture_dir, truth, tmp_path):
    from annotator.session import Session

    session = Session.open(capture_dir, tmp_path / "work")
    snapshots = [session.state.to_dict()]

    def record():
        snapshots.append(session.state.to_dict())

    _place_from_truth(session, truth, snap=False)
    record()
    session.nudge(0, translation=(0.004, -0.002, 0.0), rotation=(0.0, 0.0, 0.05))
    record()
    session.nudge(0, translation=(0.001, 0.0, 0.0), frame="object")
    record()
    session.snap(0)
    record()
    session.confirm(2)
    record()
    ops = len(session.state.undo_stack)
    keys = ("poses", "status", "scores", "visited", "step")
    final = snapshots[-1]
    for _ in range(ops):
        assert session.undo()
    assert not session.undo()
    assert all(session.state.to_dict()[k] == snapshots[0][k] for k in keys)
    for _ in range(ops):
        assert session.redo()
    assert not session.redo()
    assert all(session.state.to_dict()[k] == final[k] for k in keys)
    session.undo()  # back to before the confirm, exactly
    assert session.status()[2] == snapshots[-2]["status"][0][2]
    assert session.action_counts["undo"] == ops + 1 and session.action_counts["redo"] == ops


def test_nudge_rotates_about_the_centre_and_translates_in_the_chosen_axes(capture_dir, truth, tmp_path):
    from annotator.align import rotvec_to_matrix
    from annotator.session import Session

    session = Session.open(capture_dir, tmp_path / "work")
    _place_from_truth(session, truth, snap=False)
    samples = session.samples(1)
    m0 = pose_to_matrix(session.poses()[1])
    centre0 = m0[:3, :3] @ samples.centre + m0[:3, 3]
    session.nudge(1, rotation=(0.0, 0.0, 0.3))
    m1 = pose_to_matrix(session.poses()[1])
    np.testing.assert_allclose(m1[:3, :3] @ samples.centre + m1[:3, 3], centre0, atol=1e-9)
    np.testing.assert_allclose(m1[:3, :3], rotvec_to_matrix([0, 0, 0.3]) @ m0[:3, :3], atol=1e-9)
    session.nudge(1, translation=(0.01, 0.0, 0.0), frame="object")
    m2 = pose_to_matrix(session.poses()[1])
    np.testing.assert_allclose(m2[:3, 3] - m1[:3, 3], m1[:3, :3] @ [0.01, 0, 0], atol=1e-9)
    assert session.status()[1] == "initialised"
    with pytest.raises(UserError, match="frame"):
        session.nudge(1, frame="camera")
    with pytest.raises(UserError, match="out of range"):
        session.nudge(7)


def test_autosave_and_resume_after_a_kill(capture_dir, truth, tmp_path):
    from annotator.session import STATE_FILE, Session

    work = tmp_path / "work"
    session = Session.open(capture_dir, work)
    _place_from_truth(session, truth, snap=False)
    session.snap(1)
    session.select(2)
    saved = json.loads((work / STATE_FILE).read_text())  # written before the calls returned
    assert saved["status"][0] == session.status(0) and saved["selected"] == 2
    assert not list(work.glob(".*tmp*"))
    del session  # a kill: nothing is flushed on exit
    resumed = Session.open(capture_dir, work)
    assert resumed.status(0) == ["initialised", "snapped", "initialised"] and resumed.selected == 2
    np.testing.assert_allclose(resumed.poses(0)[0], truth[0, 0], atol=1e-9)
    assert resumed.action_counts["pick"] == 3 and resumed.action_counts["snap"] == 1
    assert resumed.undo() and resumed.status(0)[1] == "initialised"  # history survives too


def test_state_of_another_capture_is_refused(capture_dir, tmp_path):
    from annotator.session import STATE_FILE, Session
    from dsr_bench.cli import main

    work = tmp_path / "work"
    Session.open(capture_dir, work)
    state = json.loads((work / STATE_FILE).read_text())
    state["capture"] = "seq_999"
    (work / STATE_FILE).write_text(json.dumps(state))
    with pytest.raises(UserError, match="belongs to capture 'seq_999'"):
        Session.open(capture_dir, work)
    assert main(["annotate", str(capture_dir), "--work", str(work), "--status"]) == 2
    (work / STATE_FILE).write_text("{not json")
    with pytest.raises(UserError, match="unreadable annotation state"):
        Session.open(capture_dir, work)


def test_go_to_carries_forward_and_snaps_only_moved_objects(capture_dir, truth, tmp_path):
    from annotator.session import Session

    session = Session.open(capture_dir, tmp_path / "work")
    _place_from_truth(session, truth)
    with pytest.raises(UserError, match="no pose at any step before 0"):
        session.init_from_previous(0)
    for t in range(session.num_steps):
        moved = _moved(truth, t)
        snapped = session.go_to(t + 1)
        assert snapped == moved, (t, snapped, moved)
        assert session.step == t + 1 and session.status() == ["snapped"] * session.num_objects
        for i in range(session.num_objects):
            if i not in moved:  # carried exactly
                np.testing.assert_array_equal(session.poses(t + 1)[i], session.poses(t)[i])
            dt, dr = _errors(session.poses(t + 1)[i], truth[t + 1, i])
            assert dt < 0.003 and np.rad2deg(dr) < 2.0, (t + 1, i, dt, np.rad2deg(dr))
    # a visited step is a plain cursor move; undo of the last visit reverts it exactly
    assert session.go_to(1) == [] and session.step == 1
    assert session.undo() and not session.visited(session.num_steps)
    assert np.isnan(session.poses(session.num_steps)).all() and session.status(session.num_steps)[0] == "unset"
    assert session.action_counts["step"] == session.num_steps + 1


def test_auto_export_round_trip_and_validate(capture_dir, truth, tmp_path):
    from annotator.session import Session
    from dsr_bench.cli import main
    from dsr_bench.geometry import voxel_centers
    from dsr_bench.groundtruth import rigid_scene_flow_3d
    from dsr_bench.sequence import SequenceReader
    from dsr_bench.validate import validate_sequence

    work = tmp_path / "work"
    session = Session.open(capture_dir, work)
    _place_from_truth(session, truth)
    del session
    assert main(["annotate", str(capture_dir), "--work", str(work), "--auto"]) == 0
    data = tmp_path / "data"
    out = data / "seq_0000.h5"
    assert main(["annotate", capture_dir.name, "--captures", str(capture_dir.parent), "--work", str(work),
                 "--export", str(out)]) == 0
    session = Session.open(capture_dir, work)
    poses = np.stack([session.poses(s) for s in range(session.num_steps + 1)])
    centres = voxel_centers()
    with SequenceReader(out) as seq:
        assert seq.attrs["source"] == "annotated" and seq.attrs["annotation"]["capture"] == "seq_000"
        assert seq.attrs["annotation"]["status"] == [session.status(s) for s in range(session.num_steps + 1)]
        assert seq.attrs["annotation"]["action_counts"]["pick"] == 3
        np.testing.assert_allclose(seq.read("object_poses"), poses, atol=1e-9)
        assert seq.read("action").tolist() == session.capture.actions.tolist()
        for t in range(seq.num_steps + 1):
            mask = seq.read("mask_3d", t)
            for i in range(seq.num_objects):
                vox = centres[mask == i + 1]
                m = pose_to_matrix(poses[t, i])
                local = (vox - m[:3, 3]) @ m[:3, :3]  # voxel centres in the object frame lie inside its mesh box
                v, _ = session.capture.mesh(i)
                assert len(vox) > 50 and np.all(local >= v.min(0) - 1e-6) and np.all(local <= v.max(0) + 1e-6)
            assert set(np.unique(seq.read("cameras/front/mask", t))) <= set(range(seq.num_objects + 1))
        for t in range(seq.num_steps):
            expected = rigid_scene_flow_3d(seq.read("mask_3d", t), poses[t], poses[t + 1])
            np.testing.assert_allclose(seq.read("scene_flow_3d", t), expected, atol=1e-5)
    assert validate_sequence(out) == []
    (data / "splits").mkdir()
    (data / "splits" / "real.txt").write_text("seq_0000\n")
    assert main(["manifest", str(data)]) == 0 and main(["validate", str(data)]) == 0
    preds = tmp_path / "pred"
    assert main(["predict", "--model", "oracle", "--data", str(data), "--split", "real", "--out", str(preds)]) == 0
    result = str(tmp_path / "r.json")
    assert main(["evaluate", str(preds), "--data", str(data), "--split", "real", "--out", result]) == 0


def test_stored_camera_takes_every_kth_full_resolution_pixel():
    from annotator.export import stored_camera
    from dsr_bench.geometry import make_camera

    full = make_camera("front", 480, 640)
    small, rows, cols = stored_camera(full, (240, 320))
    assert (small.height, small.width) == (240, 320)
    np.testing.assert_array_equal(rows, np.arange(0, 480, 2))
    np.testing.assert_array_equal(cols, np.arange(0, 640, 2))
    np.testing.assert_allclose(small.ray_directions_world(), full.ray_directions_world()[::2, ::2], atol=1e-12)
    np.testing.assert_allclose(small.intrinsics[:2, 2], [160, 120])  # principal point stays at (W/2, H/2)


def test_export_refuses_unset_and_unchecked_poses(capture_dir, truth, tmp_path):
    from annotator.session import Session
    from dsr_bench.cli import main

    work = tmp_path / "work"
    session = Session.open(capture_dir, work)
    with pytest.raises(UserError, match="have no pose .*step 0 object 0"):
        session.export(tmp_path / "a.h5")
    _place_from_truth(session, truth, snap=False)
    for t in range(1, session.num_steps + 1):
        session.go_to(t)
    assert any(st == "initialised" for *_, st in session.unchecked())
    with pytest.raises(UserError, match="neither snapped nor confirmed.*--allow-unchecked"):
        session.export(tmp_path / "a.h5")
    assert main(["annotate", str(capture_dir), "--work", str(work), "--export", str(tmp_path / "a.h5")]) == 2
    assert not (tmp_path / "a.h5").exists()
    with pytest.raises(UserError, match=r"\.h5"):
        session.export(tmp_path / "a.txt")
    from dsr_bench.sequence import SequenceReader

    with SequenceReader(session.export(tmp_path / "b.h5", allow_unchecked=True)) as seq:
        assert seq.attrs["annotation"]["unchecked_allowed"] is True
        assert "initialised" in sum(seq.attrs["annotation"]["status"], [])


def test_cli_error_paths(capture_dir, tmp_path, capsys):
    from dsr_bench.cli import main

    assert main(["annotate", "no_such_capture", "--captures", str(tmp_path)]) == 2
    assert "no_such_capture" in capsys.readouterr().err
    assert main(["annotate", str(capture_dir), "--work", str(tmp_path / "w"), "--auto"]) == 2
    assert "step 0" in capsys.readouterr().err
    assert main(["annotate", str(capture_dir), "--work", str(tmp_path / "w"), "--allow-unchecked"]) == 2
    assert main(["annotate", str(capture_dir), "--work", str(tmp_path / "w"), "--status"]) == 0
    assert "seq_000" in capsys.readouterr().out
    broken = tmp_path / "broken"
    shutil.copytree(capture_dir, broken, ignore=shutil.ignore_patterns("annotation", "work_*"))
    (broken / "calibration.json").write_text("{}")
    assert main(["annotate", str(broken), "--status"]) == 2
    assert "calibration" in capsys.readouterr().err


def test_display_helpers(capture_dir, truth, tmp_path):
    from annotator.session import Session

    session = Session.open(capture_dir, tmp_path / "work")
    points = session.cloud(0)[0]
    grey = session.residual_colors(0)
    assert grey.shape == points.shape and np.allclose(grey[:, 0], grey[:, 1])  # nothing posed: all grey
    _place_from_truth(session, truth, snap=False)
    colors = session.residual_colors(0)
    assert colors.shape == points.shape and colors.min() >= 0 and colors.max() <= 1
    assert np.mean(np.any(colors != grey, axis=1)) > 0.05  # object points are coloured by residual
    progress = json.loads(json.dumps(session.progress()))
    assert progress["steps"][0]["objects"][0]["status"] == "initialised" and progress["steps_done"] == 0
    assert "initialised" in session.progress_table()
