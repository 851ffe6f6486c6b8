"""The numbers that decide the annotator's verdicts: one frozen dataclass, `Thresholds`, and its defaults, `THRESHOLDS`.

Every threshold of the fit checks (`annotator.checks`), of ICP (`annotator.align.icp`) and of what the cameras could
see (`annotator.fitting.visible_samples`) is a field here, with its unit and why it has its value. Lengths are metres,
angles radians, fractions 0..1, counts plain integers. Functions that read them take `limits: Thresholds =
THRESHOLDS`; `dataclasses.replace(THRESHOLDS, slide_gain=0.02)` gives another set to try (the injected-error benchmark,
`bench/bench_annotate_errors.py --set slide_gain=0.02`). How the values were set, seed by seed, is in
docs/evidence/annotator-checks-history.md.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


@dataclass(frozen=True)
class Thresholds:
    """The annotator's thresholds (see the module docstring); each field says its unit and why."""

    # --- cloud, visibility ------------------------------------------------------------------------------------------
    #: m: a cloud point counts as lying on the mesh surface within this distance (sensor noise + calibration error).
    inlier_distance: float = 0.005
    #: m: points below this height belong to the table: left out of crops and of the visible samples.
    table_margin: float = 0.003
    #: m: a sample is hidden from a camera when the measured surface lies this much in front of it.
    occlusion_tolerance: float = 0.02
    #: cosine: a sample counts for a camera only when its normal is turned at most about 81 degrees from the ray to
    #: the camera: a face seen edge-on covers a few pixels whose depth is hardly measured (a box face at 85 degrees to
    #: one camera, whose other view another object hides, had half its samples without a cloud point).
    min_view_cosine: float = 0.15
    #: m: a sample is hidden by another object when that object's posed surface lies this much in front of it along
    #: the camera's ray (`View.occluders`): coverage counts only the surface no other object hides.
    occluder_tolerance: float = 0.002

    # --- surface samples, ICP ---------------------------------------------------------------------------------------
    #: m: spacing between surface samples (the count is area / spacing^2, clipped to the two bounds below).
    sample_spacing: float = 0.002
    #: samples: the fewest and the most surface samples of a mesh.
    min_samples: int = 500
    max_samples: int = 20000
    #: m: initial correspondence distance of ICP: the basin it converges from (about 1-2 cm).
    max_correspondence: float = 0.02
    #: m, rad: an ICP result moving further than this from its start pose is rejected (a jump to other points).
    max_jump_translation: float = 0.03
    max_jump_rotation: float = float(np.deg2rad(25.0))
    #: correspondences: ICP needs at least this many (fewer: the pose is not on its points).
    min_correspondences: int = 30
    #: relative to the mean curvature: Levenberg damping of each ICP step; holds still the directions the data do not
    #: constrain (the spin of a can about its axis), where noise would otherwise turn the object.
    icp_damping: float = 1e-3
    #: samples: ICP iterates on a fixed random subset of at most this many (the scores use all).
    icp_samples: int = 3000

    # --- the fit: coverage, RMSE ------------------------------------------------------------------------------------
    #: fraction: a fit is good when at least this much of the visible samples has a cloud point within
    #: inlier_distance ...
    min_coverage: float = 0.65
    #: m: ... and the inlier RMSE (along the sample normals) is at most this.
    max_rmse: float = 0.003

    # --- physically possible (`checks.physical_checks`) -------------------------------------------------------------
    #: m: two meshes may interpenetrate by at most this, measured by the penetration_count-th deepest surface sample
    #: of one inside the other (a few deep samples are the meshes' tessellation, not an overlap).
    penetration_tolerance: float = 0.005
    penetration_count: int = 5
    #: m: a mesh's lowest point may lie this far below or above the table (z = 0): sensor noise and calibration.
    table_tolerance: float = 0.005
    #: m: higher, it must rest on another object: some surface sample within this distance of that object's.
    support_distance: float = 0.006
    #: m, fraction, samples: the cameras may measure depth more than free_space_tolerance behind at most
    #: free_space_fraction of the samples that face them and project onto measured pixels (they saw through the mesh
    #: there), counted with at least free_space_min_samples such samples; the measured depth of a pixel is the nearest
    #: of its 3 x 3 neighbourhood, so a silhouette's edge does not count.
    free_space_tolerance: float = 0.01
    free_space_fraction: float = 0.1
    free_space_min_samples: int = 20

    # --- the cloud around it is explained (`checks.unexplained_check`) ----------------------------------------------
    #: m, fraction, points: at most unexplained_fraction of the cloud points within unexplained_reach of the posed
    #: surface (at least unexplained_min_points of them) may lie farther than inlier_distance from every posed mesh: a
    #: wrong pose leaves the surface where the object really is unexplained (true poses under the simulated sensor's
    #: noise: at most 2%; 10 mm off: 20%+; a true pose beside a neighbour left 9 cm behind: 8%).
    unexplained_reach: float = 0.01
    unexplained_fraction: float = 0.1
    unexplained_min_points: int = 30
    #: m: counting only points this high above the table: its measured surface (depth noise, calibration error)
    #: reaches a few millimetres above z = 0 (up to 4 mm seen beside a can: 12% of the points around it) ...
    unexplained_min_height: float = 0.01
    #: fraction, m: ... or, for an object lower than that (a phone lying flat, 7 mm high), above this fraction of its
    #: highest point and at least the floor: otherwise none of its measured surface would count.
    unexplained_thin_fraction: float = 0.65
    unexplained_thin_floor: float = 0.004

    # --- a snap would not improve it (`checks.refinement_checks`) ---------------------------------------------------
    #: ICP steps: the short ICP run from the pose (the correspondence distance shrinking from max_correspondence to
    #: twice inlier_distance, no jump limits).
    refine_iterations: int = 15
    #: samples: it iterates and measures its gain on a fixed random subset of at most this many: with 3000 (as ICP)
    #: three seeds flagged the same errors (but one) for 2.2 times its time.
    refine_samples: int = 1000
    #: m, rad: a move (of the origin, less the shift the other objects share) beyond either ...
    refine_translation: float = 0.0035
    refine_rotation: float = float(np.deg2rad(4.0))
    #: m: ... that brings the visible samples more than this closer to the cloud (mean distance to the nearest cloud
    #: point, capped at refine_cap) says the pose is wrong; a true pose moves by the noise and gains nothing, a shift
    #: along a direction the cloud does not constrain moves the pose without a gain. Set from the true poses of the
    #: injected-error benchmark's seeds 3 and 4 (moved at most 4.2 mm and 3.4 deg, gains up to 0.59 mm) and the
    #: errors the other checks missed there (10-20 deg turns, a mug turned 180 deg, 10 mm shifts).
    refine_gain: float = 0.00035
    #: rad, m: a turn beyond refine_turn with a gain over refine_turn_gain says so too (a 10-20 degree turn that the
    #: cloud fixes little).
    refine_turn: float = float(np.deg2rad(6.0))
    refine_turn_gain: float = 0.00012
    #: m: distances to the cloud are capped at this when measuring the gain (an unmeasured part counts as this far).
    refine_cap: float = 0.01
    #: m: an object whose lowest point lies within this of the table rests on it: only the refinement's move along
    #: the table counts (its height is the table's, and the floats / sinks checks refuse a wrong one). The simulated
    #: stereo sensor measures a sofa's concave seat and a phone lying flat a few millimetres off their true height,
    #: so the refinement moved their true poses 3-4 mm down or up (seed 6: 8 false alarms of 72 without this).
    refine_resting_height: float = 0.005

    # --- no slide along the table fits better (`checks.slide_check`) ------------------------------------------------
    #: m: for an object lower than this (a phone lying flat: its top face lets ICP slide it along the table without
    #: fitting much closer, and its few millimetres of side hardly leave cloud unexplained) ...
    slide_max_height: float = 0.015
    #: m, directions: ... no slide along the table by these distances in this many directions ...
    slide_distances: tuple[float, ...] = (0.01, 0.015, 0.02, 0.025)
    slide_directions: int = 16
    #: quality units (coverage less the RMS distance in units of 2 cm, `fitting.screen_quality` of refine_samples
    #: samples within inlier_distance): ... may fit the cloud better by more than this. Slides start at 1 cm: the
    #: calibration error moves a whole scene by up to 4-5 mm. Set on seeds 6-8 (23 thin true poses: best slides
    #: -0.078..-0.002; the same poses 10 mm off 0.025..0.23, 20 mm off 0.047..0.36).
    slide_gain: float = 0.015

    # --- the colours match another step (`checks.colour_check`) -----------------------------------------------------
    #: L1 chromaticity, fraction, samples, 0..1: at most colour_fraction of the surface samples seen at both steps (at
    #: least colour_min_samples, each brighter than colour_min_brightness) may differ in chromaticity (r, g, b over
    #: their sum, which shading does not change) by more than colour_distance. True poses of the simulated captures:
    #: at most 1% of the samples differ (7.8% on one seed); two cans of different colours swapped: all of them.
    colour_distance: float = 0.1
    colour_fraction: float = 0.3
    colour_min_samples: int = 30
    colour_min_brightness: float = 0.05

    def replaced(self, overrides: dict[str, str]) -> Thresholds:
        """A copy with fields replaced from text ({name: "0.02"}; a tuple as "0.01,0.02"), for the benchmark's --set;
        ValueError naming an unknown field or a value of the wrong type."""
        from dataclasses import replace

        kinds = {f.name: type(getattr(self, f.name)) for f in fields(self)}
        values: dict[str, object] = {}
        for name, text in overrides.items():
            if name not in kinds:
                raise ValueError(f"no threshold {name!r}: one of {', '.join(kinds)}")
            kind = kinds[name]
            values[name] = tuple(float(x) for x in text.split(",")) if kind is tuple else kind(text)
        return replace(self, **values)  # type: ignore[arg-type]


#: Today's thresholds: what the session, the window and the CLI use.
THRESHOLDS = Thresholds()
