"""The fit score's checks for wrong poses that coverage and RMSE accept (issue 32 part 1): a short ICP that would
improve the pose (a 10 degree turn), the colours of the surface against another step (a swapped identity), the
unexplained cloud of a thin object (a phone shifted along the table). Each verdict is asserted on its named checks
(`annotator.checks.Check`: name, value, threshold, pass or fail), not on its text (issue 45).

Fixture: the small ideal-sensor capture of conftest.py (box 0, can 1, box 2; 3 pushes, 240 x 320 images).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from dsr_bench.annotator.thresholds import THRESHOLDS
from dsr_bench.geometry import matrix_to_pose, pose_to_matrix


def _turned(pose: np.ndarray, axis, degrees: float) -> np.ndarray:
    """A 4x4 pose turned by `degrees` about a world axis through the object's origin (its centre of mass)."""
    from dsr_bench.annotator.align import rotvec_to_matrix

    m = pose_to_matrix(pose)
    m[:3, :3] = rotvec_to_matrix(np.asarray(axis, np.float64) * np.deg2rad(degrees)) @ m[:3, :3]
    return m


def _scoring(session, obj: int, step: int, truth: np.ndarray, transform: np.ndarray):
    """(samples, crop, views, keywords of align.fit_score) of object `obj` at a step, the others at their truth."""
    samples = session.samples(obj)
    others = [(k, truth[step, k]) for k in range(session.num_objects)]
    views, checks = session._context(obj, step, others)
    return samples, session._crop(step, transform, samples), views, checks


def _failed(score) -> list[str]:
    """The names of a verdict's failed checks, in order, each checked against its rule (value against threshold) and
    the verdict's consistency: accepted when none failed, and its reason built from the checks."""
    from dsr_bench.annotator.checks import holds, verdict_reason

    assert score.checks and all(c.passed == holds(c) for c in score.checks), score.checks
    assert score.accepted == all(c.passed for c in score.checks) and score.reason == verdict_reason(score.checks)
    return [c.name for c in score.failed()]


def test_a_ten_degree_turn_that_coverage_and_rmse_accept_is_flagged_by_the_refinement(capture_dir, truth, tmp_path):
    from dsr_bench.annotator import align
    from dsr_bench.annotator.session import Session

    session = Session.open(capture_dir, tmp_path / "work")
    true = pose_to_matrix(truth[0, 2])
    samples, crop, views, checks = _scoring(session, 2, 0, truth, true)
    still = align.refinement(samples, true, crop, views)
    assert still.translation < 0.001 and still.rotation < np.deg2rad(0.5) and not still.improves()
    assert _failed(align.fit_score(samples, true, crop, views, refine=True, **checks)) == []

    turned = _turned(truth[0, 2], [0.0, 0.0, 1.0], 10.0)  # box 2 turned 10 degrees about the vertical
    samples, crop, views, checks = _scoring(session, 2, 0, truth, turned)
    plain = align.fit_score(samples, turned, crop, views, **checks)
    assert _failed(plain) == [], plain.reason  # what the score said before: coverage and RMSE pass
    assert [c.name for c in plain.checks if c.name in ("snap_move", "snap_turn")] == []  # the refinement did not run
    moved = align.refinement(samples, turned, crop, views)
    assert moved.improves() and np.rad2deg(moved.rotation) > 8.0 and moved.gain > THRESHOLDS.refine_gain
    score = align.fit_score(samples, turned, crop, views, refine=True, **checks)
    assert _failed(score) == ["snap_move", "snap_turn"]  # turned beyond both limits, and closer beyond both gains
    for check in score.failed():
        assert check.applies and check.value == moved.gain and check.value > check.threshold
        assert dict(check.measured)["rotation"] == moved.rotation > THRESHOLDS.refine_turn
    # the session scores with the refinement: the window shows the turned box for a check, not the true one
    others = [(k, truth[0, k]) for k in range(session.num_objects)]
    assert not session._fit(2, 0, matrix_to_pose(turned), others).accepted
    assert session._fit(2, 0, truth[0, 2], others).accepted
    session.close()


def test_a_surface_of_another_colour_is_flagged_and_the_same_colours_are_not(capture_dir, truth, tmp_path):
    from dsr_bench.annotator import align
    from dsr_bench.annotator.session import Session

    session = Session.open(capture_dir, tmp_path / "work")
    true = pose_to_matrix(truth[0, 1])
    samples, crop, views, checks = _scoring(session, 1, 0, truth, true)
    checks.pop("reference_colours")
    reference = align.sample_colours(*align.posed_samples(samples, true), views)
    seen = np.all(np.isfinite(reference), axis=1)
    assert seen.sum() > 200 and not seen.all()  # the side the cameras saw, not the table side
    assert np.all(reference[seen] >= 0.0) and np.all(reference[seen] <= 1.0)
    assert align.colour_mismatch(reference, reference) == (0.0, int(seen.sum()))
    same = align.fit_score(samples, true, crop, views, reference_colours=reference, **checks)
    assert _failed(same) == [], same.reason
    colour = same.check("colour")[0]
    assert colour.value == 0.0 and dict(colour.measured)["compared"] == seen.sum() and colour.applies
    # another object of the same shape at the same place: the cameras see the can's colours with r, g, b rotated
    other = [replace(view, color=np.roll(view.color, 1, axis=2)) for view in views]
    changed, compared = align.colour_mismatch(align.sample_colours(*align.posed_samples(samples, true), other),
                                              reference)
    assert compared == seen.sum() and changed > 0.9
    score = align.fit_score(samples, true, crop, other, reference_colours=reference, **checks)
    assert _failed(score) == ["colour"]
    colour = score.check("colour")[0]
    assert colour.value == changed > colour.threshold == THRESHOLDS.colour_fraction
    session.close()


def test_the_reference_colours_come_from_the_nearest_checked_step(capture_dir, truth, tmp_path):
    from dsr_bench.annotator import align
    from dsr_bench.annotator.session import Session

    session = Session.open(capture_dir, tmp_path / "work")
    assert session._context(1, 1)[1]["reference_colours"] is None  # nothing checked yet: no colour check
    session._commit("confirm", {(t, k): (truth[t, k], "confirmed", None) for t in (0, 2)
                                for k in range(session.num_objects)})
    ref = session._context(1, 1)[1]["reference_colours"]
    views, _ = session._context(1, 0, colours=False)
    expected = align.sample_colours(*align.posed_samples(session.samples(1), pose_to_matrix(truth[0, 1])), views)
    np.testing.assert_array_equal(ref, expected)  # steps 0 and 2 are as near: the earlier one
    views, _ = session._context(1, 2, colours=False)
    expected = align.sample_colours(*align.posed_samples(session.samples(1), pose_to_matrix(truth[2, 1])), views)
    np.testing.assert_array_equal(session._context(1, 3)[1]["reference_colours"], expected)  # step 3: from step 2
    # the can rolled between the steps (other shading, other samples seen): its true pose still passes
    for t in (1, 3):
        score = session._fit(1, t, truth[t, 1], [(k, truth[t, k]) for k in range(session.num_objects)])
        assert _failed(score) == [], (t, score.reason)
        assert score.check("colour")[0].value <= THRESHOLDS.colour_fraction
    session.close()


def test_a_thin_object_shifted_along_the_table_leaves_its_cloud_unexplained():
    trimesh = pytest.importorskip("trimesh")
    from dsr_bench.annotator import align

    phone = trimesh.creation.box(extents=(0.05, 0.107, 0.007))  # a phone lying flat: its top 7 mm above the table
    samples = align.sample_surface(np.asarray(phone.vertices), np.asarray(phone.faces))
    true = np.eye(4)
    true[:3, 3] = (0.5, 0.0, 0.0035)
    surface = align.posed_samples(samples, true)[0]
    measured = surface[surface[:, 2] > 0.005]  # its top and the upper part of its sides, no table
    assert THRESHOLDS.unexplained_min_height > 0.007  # the rule for taller objects counts none of these points
    fraction, count = align.unexplained_fraction(samples, true, measured, [])
    assert fraction == 0.0 and count == len(measured)
    shifted = true.copy()
    shifted[0, 3] += 0.02  # 20 mm across: its top face still lies on 30 of the 50 mm of the measured one
    fraction, count = align.unexplained_fraction(samples, shifted, measured, [])
    assert count >= THRESHOLDS.unexplained_min_points and fraction > THRESHOLDS.unexplained_fraction
    check = align.unexplained_check(samples, shifted, measured, [])
    assert not check.passed and check.applies and check.value == fraction and dict(check.measured)["points"] == count


def test_a_shift_every_object_shares_is_the_calibration_not_a_wrong_pose(capture_dir, truth, tmp_path):
    from dsr_bench.annotator.session import Session

    session = Session.open(capture_dir, tmp_path / "work")
    shifted = truth[0].copy()
    shifted[:, 1] += 0.004  # 4 mm across the cameras' view: the cloud shows it (box 0 hardly: too thin along y)
    for obj in (1, 2):
        alone = session._fit(obj, 0, shifted[obj], [(k, truth[0, k]) for k in range(session.num_objects)])
        assert "snap_move" in _failed(alone)
        move = alone.check("snap_move")[0]
        assert 0.0035 < dict(move.measured)["translation"] < 0.0045 and move.value > move.threshold
        # every object 4 mm off alike (as the cameras' calibration error puts a whole scene): none is flagged
        together = [(k, shifted[k]) for k in range(session.num_objects)]
        np.testing.assert_allclose(session._shared_shift(obj, 0, together), [0.0, -0.004, 0.0], atol=5e-4)
        together_score = session._fit(obj, 0, shifted[obj], together)
        assert _failed(together_score) == []
        assert dict(together_score.check("snap_move")[0].measured)["translation"] < THRESHOLDS.refine_translation
    assert session._shared_shift(1, 0, [(2, truth[0, 2])]) is None  # one other object: no shared shift
    session.close()


def test_the_thresholds_are_one_frozen_dataclass_each_field_documented():
    import dataclasses
    import inspect

    from dsr_bench.annotator import thresholds
    from dsr_bench.annotator.checks import CHECKS
    from dsr_bench.annotator.thresholds import Thresholds

    assert Thresholds() == THRESHOLDS
    with pytest.raises(dataclasses.FrozenInstanceError):
        THRESHOLDS.min_coverage = 0.5
    names = [f.name for f in dataclasses.fields(Thresholds)]
    assert {kind.threshold for kind in CHECKS.values()} - {""} <= set(names)  # every check's threshold is a field
    # each field (or group of fields) has its comment right above it: its unit and why
    lines = inspect.getsource(thresholds).splitlines()
    for name in names:
        row = next(i for i, line in enumerate(lines) if line.startswith(f"    {name}: "))
        while lines[row - 1].strip() and not lines[row - 1].lstrip().startswith("#"):
            row -= 1  # a field of the same group
        assert lines[row - 1].lstrip().startswith("#:"), name
    tried = THRESHOLDS.replaced({"slide_gain": "0.02", "slide_distances": "0.01,0.02", "refine_samples": "500"})
    assert (tried.slide_gain, tried.slide_distances, tried.refine_samples) == (0.02, (0.01, 0.02), 500)
    assert THRESHOLDS.slide_gain != 0.02  # the defaults stay
    with pytest.raises(ValueError, match="no threshold 'nope'"):
        THRESHOLDS.replaced({"nope": "1"})


def test_a_verdict_follows_the_thresholds_it_is_given(capture_dir, truth, tmp_path):
    """The same pose held to stricter thresholds fails exactly the checks whose value is beyond them; a session's
    `limits` are what its scores use."""
    from dataclasses import replace

    from dsr_bench.annotator import align
    from dsr_bench.annotator.session import Session

    session = Session.open(capture_dir, tmp_path / "work")
    true = pose_to_matrix(truth[0, 1])
    samples, crop, views, checks = _scoring(session, 1, 0, truth, true)
    assert checks.pop("limits") is THRESHOLDS
    default = align.fit_score(samples, true, crop, views, refine=True, **checks)
    assert _failed(default) == []
    coverage, rmse = default.check("coverage")[0], default.check("rmse")[0]
    assert (coverage.threshold, rmse.threshold) == (THRESHOLDS.min_coverage, THRESHOLDS.max_rmse)
    strict = replace(THRESHOLDS, min_coverage=min(1.0, coverage.value + 0.01), max_rmse=rmse.value / 2)
    score = align.fit_score(samples, true, crop, views, refine=True, limits=strict, **checks)
    assert _failed(score) == ["coverage", "rmse"]
    assert score.check("coverage")[0].value == coverage.value and score.check("rmse")[0].threshold == rmse.value / 2
    others = [(k, truth[0, k]) for k in range(session.num_objects)]
    assert session._fit(1, 0, truth[0, 1], others).accepted
    session.limits = strict
    assert _failed(session._fit(1, 0, truth[0, 1], others)) == ["coverage", "rmse"]
    session.close()


def test_for_an_object_resting_on_the_table_only_the_refinements_move_along_it_counts(capture_dir, truth, tmp_path):
    """Box 2 raised 4.5 mm (still within the table's tolerance): the refinement brings it back down, but the table
    fixes its height (the floats / sinks checks judge that), so only its move along the table counts (issue 45:
    the simulated sensor measures a sofa's seat or a phone a few millimetres off their height). Counted in 3D, as
    before, the same move is beyond refine_translation."""
    from dataclasses import replace

    from dsr_bench.annotator import align
    from dsr_bench.annotator.session import Session

    session = Session.open(capture_dir, tmp_path / "work")
    raised = pose_to_matrix(truth[0, 2])
    raised[2, 3] += 0.0045
    samples, crop, views, _ = _scoring(session, 2, 0, truth, raised)
    assert 0.004 < align.lowest_point(samples, raised) <= THRESHOLDS.refine_resting_height
    moved = align.refinement(samples, raised, crop, views)
    assert moved.resting and abs(moved.vertical + 0.0045) < 0.001 and moved.translation < 0.001
    assert abs(moved.translation - np.linalg.norm(moved.shift[:2])) < 1e-12  # no shared shift given
    in_3d = align.refinement(samples, raised, crop, views, limits=replace(THRESHOLDS, refine_resting_height=0.0))
    assert not in_3d.resting and in_3d.translation > THRESHOLDS.refine_translation
    assert in_3d.gain == moved.gain and in_3d.improves() and not moved.improves()
    move = align.refinement_checks(moved)[0]
    assert move.name == "snap_move" and move.passed and not move.applies and dict(move.measured)["resting"] == 1.0
    assert not align.refinement_checks(in_3d)[0].passed
    # its height is judged by the cloud fit (4.5 mm off the measured top face) and the table checks
    score = session._fit(2, 0, matrix_to_pose(raised), [(k, truth[0, k]) for k in range(session.num_objects)])
    assert _failed(score) == ["rmse"] and score.check("floats")[0].passed
    session.close()


def _phone_views(phone, transform: np.ndarray):
    """The benchmark's two cameras (240 x 320) seeing a mesh at `transform` (4, 4) on the table, ideally: their
    views and the cloud (M, 3) their depth images give above the table (as a crop keeps it)."""
    from dsr_bench.annotator import align
    from dsr_bench.geometry.camera import make_camera

    vertices = np.asarray(phone.vertices) @ transform[:3, :3].T + transform[:3, 3]
    table = (np.array([[0.2, -0.3, 0.0], [0.8, -0.3, 0.0], [0.8, 0.3, 0.0], [0.2, 0.3, 0.0]]),
             np.array([[0, 1, 2], [0, 2, 3]]))
    views, cloud = [], []
    for name in ("front", "back"):
        camera = make_camera(name, 240, 320)
        depth = align.render_depth(camera, [(vertices, np.asarray(phone.faces)), table])
        depth = np.where(np.isfinite(depth), depth, 0.0)
        views.append(align.View(camera, depth))
        points = camera.backproject(depth).reshape(-1, 3)
        cloud.append(points[np.all(np.isfinite(points), axis=1) & (points[:, 2] > THRESHOLDS.table_margin)])
    return views, np.vstack(cloud)


def test_a_thin_object_slid_along_the_table_is_flagged_by_the_slide_check():
    """A phone lying flat (7 mm) slid 20 mm along the table: its top face still lies on most of the measured one and
    ICP hardly moves it back, but sliding it back fits the cloud clearly better ("slide"); its true pose has no
    better slide, and a taller object is not slide-checked."""
    trimesh = pytest.importorskip("trimesh")
    from scipy.spatial import cKDTree

    from dsr_bench.annotator import align

    phone = trimesh.creation.box(extents=(0.05, 0.107, 0.007))
    samples = align.sample_surface(np.asarray(phone.vertices), np.asarray(phone.faces))
    true = np.eye(4)
    true[:3, 3] = (0.5, 0.0, 0.0035)
    views, cloud = _phone_views(phone, true)
    tree = cKDTree(cloud)
    check = align.slide_check(samples, true, tree, views)
    assert check is not None and check.passed and check.value <= check.threshold == THRESHOLDS.slide_gain
    assert dict(check.measured)["height_m"] < THRESHOLDS.slide_max_height
    score = align.fit_score(samples, true, cloud, views, tree=tree, neighbours=[], refine=True)
    assert score.accepted and [c.name for c in score.checks][-1] == "slide"
    slid = true.copy()
    slid[0, 3] += 0.02
    check = align.slide_check(samples, slid, tree, views)
    assert check is not None and not check.passed and check.value > check.threshold
    assert dict(check.measured)["distance_m"] in THRESHOLDS.slide_distances
    gain, distance, before, after = align.slide_gain(samples, slid, tree, views)
    assert (gain, distance) == (check.value, dict(check.measured)["distance_m"]) and after > before
    tall = align.sample_surface(*(np.asarray(a) for a in (trimesh.creation.box(extents=(0.05, 0.05, 0.05)).vertices,
                                                           trimesh.creation.box(extents=(0.05, 0.05, 0.05)).faces)))
    assert align.slide_check(tall, true, tree, views) is None
