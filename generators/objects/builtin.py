"""Built-in object sets, deterministic from the rng and needing no download.

- `cube`: the paper's boxes, half extents (30, 30, 35) / s m for s in the official list.
- `procedural`: parametric families for the five ShapeNet training categories (mug with a handle,
  bottle, can, phone-like slab, sofa) with the official category scale ranges (normal / large)
  applied to shapes whose bounding-box diagonal is 0.15 m at scale 1 (as the official URDFs scale
  the unit-diagonal ShapeNetCore v2 models by 0.15), and the official scene mix (random boxes,
  forced cans, one optional large object).
- `procedural-novel`: YCB-like shapes at their real sizes, shrunk uniformly where needed to stay
  within 0.12 m height and 0.16 m side (boxes, cans, cups, a bowl, a foam brick, a Duplo brick, an
  L-shaped clamp, a mustard-like bottle, a peg board), disjoint from `procedural`, for the
  novel-object test split.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from dsr_bench.geometry import vector_norm
from dsr_bench.generators.objects.primitives import (Solid, bounds, box_solid, cylinder_solid, revolve_solid, scaled,
                                                     solid, translated)
from dsr_bench.generators.objects.spec import ObjectSpec, make_spec, random_color

CUBE_DIVISORS = (700, 750, 800, 850, 900, 1000, 1100, 1200, 1400)
CUBE_HALF_EXTENTS = (30.0, 30.0, 35.0)  # divided by s: metres
#: m: bounding-box diagonal at scale 1 (the official URDFs scale unit-diagonal meshes by 0.15)
NORMALISED_DIAGONAL = 0.15
#: Official category scale ranges: (normal low, normal high), (large low, large high).
CATEGORY_SCALES = {
    "bottle": ((0.7, 0.8), (1.1, 1.2)),
    "can": ((0.7, 0.9), (1.1, 1.2)),
    "mug": ((0.8, 0.9), (1.1, 1.2)),
    "sofa": ((0.4, 0.7), (1.0, 1.2)),
    "phone": ((0.7, 1.0), (1.0, 1.1)),
}
PROCEDURAL_CATEGORIES = tuple(CATEGORY_SCALES)
# The official scene mix (shapenet and ycb; cube scenes have no large object):
P_NO_LARGE = 0.1  # otherwise one object, chosen uniformly, is the "large" one
P_RANDOM_BOX = 0.3  # a non-large object is replaced by a random box
P_LARGE_BOX = 0.12  # the large object is replaced by a large random box
P_FORCE_CAN = 0.3  # the category drawn is replaced by "can"
P_CAN_WITH_BOX = 0.1  # after a large can, a random box is a large one (once)
#: Random box sizes in 2 mm voxels (official: numpy ranges, upper bounds excluded).
SMALL_BOX_VOXELS = (tuple(range(25, 40)), tuple(range(30, 60)), tuple(range(15, 25)) + (30, 32))
LARGE_BOX_VOXELS = (tuple(range(35, 55)), tuple(range(70, 85)), tuple(range(15, 30)))
BOX_VOXEL = 0.002  # m
# procedural-novel: real sizes, shrunk uniformly (the factor is the spec's scale) to fit these limits
NOVEL_MAX_HEIGHT = 0.12  # m
NOVEL_MAX_SIDE = 0.16  # m, longest horizontal side


def _revolve(profile) -> Solid:
    """A solid of revolution about z from a (radius, height) profile starting and ending on the axis."""
    return revolve_solid(profile, sections=40)


def _normalise(parts: list[Solid], diagonal: float) -> list[Solid]:
    """Scale parts jointly so their bounding-box diagonal is `diagonal` metres, resting on z = 0."""
    low, high = bounds(parts)
    factor = diagonal / vector_norm(high - low)
    out = [scaled(p, factor) for p in parts]
    lift = -bounds(out)[0][2]
    return [translated(p, [0, 0, lift]) for p in out]


# --- ShapeNet-like families (unit-free shapes, normalised afterwards) ---------------------------
def _can(rng):
    r, h = rng.uniform(0.25, 0.4), rng.uniform(0.6, 1.1)
    return [_revolve([[0, 0], [r, 0], [r, h], [0, h]])], f"can_r{r:.3f}_h{h:.3f}"


def _bottle(rng):
    r, body, neck_r = rng.uniform(0.22, 0.32), rng.uniform(0.45, 0.65), rng.uniform(0.08, 0.12)
    shoulder, neck = rng.uniform(0.12, 0.2), rng.uniform(0.15, 0.25)
    profile = [[0, 0], [r, 0], [r, body], [neck_r, body + shoulder], [neck_r, body + shoulder + neck],
               [0, body + shoulder + neck]]
    return [_revolve(profile)], f"bottle_r{r:.3f}_b{body:.3f}_n{neck_r:.3f}"


def _mug(rng):
    r, h, wall = rng.uniform(0.3, 0.4), rng.uniform(0.65, 0.9), rng.uniform(0.03, 0.05)
    body = _revolve([[0, 0], [r, 0], [r, h], [r - wall, h], [r - wall, 0.08], [0, 0.08]])
    reach, bar, t = rng.uniform(0.18, 0.25), 0.07, 0.08
    z0, z1 = 0.22 * h, 0.78 * h
    # parts barely overlap (arms enter the wall by 0.01), so the volume-weighted centre of mass is exact
    x0, x1 = r - 0.01, r + reach - bar  # arm span, from inside the wall to the grip
    parts = [body,
             box_solid([x1 - x0, t, bar], [(x0 + x1) / 2, 0, z1 - bar / 2]),   # upper arm
             box_solid([x1 - x0, t, bar], [(x0 + x1) / 2, 0, z0 + bar / 2]),   # lower arm
             box_solid([bar, t, z1 - z0], [r + reach - bar / 2, 0, (z0 + z1) / 2])]            # grip
    return parts, f"mug_r{r:.3f}_h{h:.3f}_reach{reach:.3f}"


def _phone(rng):
    w, length, t = rng.uniform(0.45, 0.55), 1.0, rng.uniform(0.06, 0.09)
    return [box_solid([w, length, t], [0, 0, t / 2])], f"phone_w{w:.3f}_t{t:.3f}"


def _sofa(rng):
    width, depth = 1.0, rng.uniform(0.45, 0.6)
    seat_h, back_h, arm_h = rng.uniform(0.15, 0.22), rng.uniform(0.4, 0.55), rng.uniform(0.25, 0.33)
    back_t, arm_w = rng.uniform(0.1, 0.15), rng.uniform(0.08, 0.12)
    inner = width - 2 * arm_w  # seat and back sit between the arms, the seat in front of the back: no overlap
    parts = [box_solid([inner, depth - back_t, seat_h], [0, -back_t / 2, seat_h / 2]),
             box_solid([inner, back_t, back_h], [0, depth / 2 - back_t / 2, back_h / 2]),
             box_solid([arm_w, depth, arm_h], [-width / 2 + arm_w / 2, 0, arm_h / 2]),
             box_solid([arm_w, depth, arm_h], [width / 2 - arm_w / 2, 0, arm_h / 2])]
    return parts, f"sofa_d{depth:.3f}_b{back_h:.3f}"


FAMILIES = {"can": _can, "bottle": _bottle, "mug": _mug, "phone": _phone, "sofa": _sofa}


def random_box(rng: np.random.Generator, set_name: str, large: bool, is_large: bool) -> ObjectSpec:
    """The official random box: small 25-39 x 30-59 x (15-24, 30 or 32) voxels of 2 mm, large
    35-54 x 70-84 x 15-29 voxels."""
    ranges = LARGE_BOX_VOXELS if large else SMALL_BOX_VOXELS
    voxels = [int(rng.choice(r)) for r in ranges]
    size = np.array(voxels, dtype=np.float64) * BOX_VOXEL
    model_id = f"box_{'large' if large else 'small'}_{voxels[0]}x{voxels[1]}x{voxels[2]}vox"
    return make_spec(set_name, "box", model_id, 1.0, [box_solid(size, [0, 0, size[2] / 2])], random_color(rng),
                     is_large)


def choose_large(rng: np.random.Generator, count: int) -> int:
    """Index of the scene's large object, or -1 (probability P_NO_LARGE), as the official generator."""
    large = int(rng.integers(count))
    return -1 if rng.random() < P_NO_LARGE else large


def sample_category_mix(rng: np.random.Generator, count: int, set_name: str,
                        build: Callable[[str, np.random.Generator, bool], ObjectSpec]) -> list[ObjectSpec]:
    """The official ShapeNet scene mix: random boxes (p 0.3; the large object p 0.12), else a uniform
    category with "can" forced at p 0.3; build(category, rng, is_large) makes the object."""
    large = choose_large(rng, count)
    can_with_box = False
    out = []
    for i in range(count):
        if i != large and rng.random() < P_RANDOM_BOX:
            big = can_with_box and rng.random() < P_CAN_WITH_BOX
            can_with_box = can_with_box and not big
            out.append(random_box(rng, set_name, big, False))
        elif i == large and rng.random() < P_LARGE_BOX:
            out.append(random_box(rng, set_name, True, True))
        else:
            category = PROCEDURAL_CATEGORIES[int(rng.integers(len(PROCEDURAL_CATEGORIES)))]
            if rng.random() < P_FORCE_CAN:
                category = "can"
            can_with_box = can_with_box or (i == large and category == "can")
            out.append(build(category, rng, i == large))
    return out


def category_scale(rng: np.random.Generator, category: str, is_large: bool) -> float:
    """A scale drawn uniformly from the official normal or large range of the category."""
    low, high = CATEGORY_SCALES[category][1 if is_large else 0]
    return float(rng.uniform(low, high))


class CubeSet:
    """The paper's boxes (official half extents), random colours; no large object. Built with numpy alone
    (`generators.objects.primitives`): a cube run imports no mesh library."""

    name = "cube"

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]:
        out = []
        for _ in range(count):
            s = int(rng.choice(CUBE_DIVISORS))
            half = np.array(CUBE_HALF_EXTENTS) / s
            out.append(make_spec(self.name, "cube", f"cube_s{s}", 1.0 / s, [box_solid(2 * half, [0, 0, half[2]])],
                                 random_color(rng), False))
        return out


class ProceduralSet:
    """Parametric mugs, bottles, cans, phones and sofas with the official scales and scene mix."""

    name = "procedural"

    def _build(self, category: str, rng: np.random.Generator, is_large: bool) -> ObjectSpec:
        meshes, model_id = FAMILIES[category](rng)
        scale = category_scale(rng, category, is_large)
        meshes = _normalise(meshes, NORMALISED_DIAGONAL * scale)
        return make_spec(self.name, category, model_id, scale, meshes, random_color(rng), is_large)

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]:
        return sample_category_mix(rng, count, self.name, self._build)


# --- YCB-like novel shapes (metres, real sizes before fitting) ------------------------------------
def _ycb_box(dims):
    def build(rng):
        return [box_solid(dims, [0, 0, dims[2] / 2])]
    return build


def _ycb_can(radius, height):
    def build(rng):
        return [_revolve([[0, 0], [radius, 0], [radius, height], [0, height]])]
    return build


def _rounded_can(width, depth, height, corner):
    """A can with a rounded-rectangle section (potted meat): the hull of its corner circles."""
    def build(rng):
        a = np.linspace(0, 2 * np.pi, 48, endpoint=False)
        cx, cy = width / 2 - corner, depth / 2 - corner
        ring = np.concatenate([np.stack([sx * cx + corner * np.cos(a), sy * cy + corner * np.sin(a)], 1)
                               for sx in (-1, 1) for sy in (-1, 1)])
        pts = np.concatenate([np.c_[ring, np.zeros(len(ring))], np.c_[ring, np.full(len(ring), height)]])
        import trimesh  # qhull's triangulation of the hull: the one shape that needs a mesh library

        hull = trimesh.Trimesh(pts).convex_hull
        return [solid(hull.vertices, hull.faces)]
    return build


def _ycb_cup(radius_top, height):
    """An open-top cup: a truncated cone with a 3 mm wall and a 4 mm base."""
    def build(rng):
        wall, base_r = 0.003, radius_top * 0.8
        return [_revolve([[0, 0], [base_r, 0], [radius_top, height], [radius_top - wall, height],
                          [base_r - wall, 0.004], [0, 0.004]])]
    return build


def _bowl(rng):
    r, h, wall = 0.08, 0.055, 0.005
    a = np.linspace(0, np.pi / 2, 10)
    outer = np.stack([0.035 + (r - 0.035) * np.sin(a), h * (1 - np.cos(a))], 1)
    inner = np.stack([(0.035 + (r - 0.035) * np.sin(a))[::-1] - wall, (h * (1 - np.cos(a)))[::-1] + wall], 1)
    inner = inner[inner[:, 0] > 0]
    return [_revolve(np.vstack([[[0, 0]], outer, inner, [[0, wall]]]))]


def _clamp(rng, arm=0.12, foot=0.08, t=0.025, h=0.035):
    """An L-shaped clamp lying flat: two bars meeting at a corner."""
    return [box_solid([arm, t, h], [arm / 2, 0, h / 2]), box_solid([t, foot, h], [t / 2, foot / 2 + t / 2, h / 2])]


def _mustard(rng):
    """A mustard bottle: a revolved profile squeezed to an oval section (95 x 58 mm), 190 mm tall."""
    body = _revolve([[0, 0], [0.0475, 0], [0.0475, 0.14], [0.014, 0.172], [0.014, 0.19], [0, 0.19]])
    return [scaled(body, [1.0, 0.61, 1.0])]


def _duplo(rng, pitch=0.016, rows=2, cols=4, height=0.0192):
    """A filled 2 x 4 Duplo brick with its eight studs (parts overlap the top by 0.5 mm)."""
    w, d = rows * pitch - 0.0002, cols * pitch - 0.0002
    parts = [box_solid([w, d, height], [0, 0, height / 2])]
    stud = cylinder_solid(radius=0.0048, height=0.0050, sections=24)
    for i in range(rows):
        for j in range(cols):
            parts.append(translated(stud, [(i - (rows - 1) / 2) * pitch, (j - (cols - 1) / 2) * pitch, height + 0.002]))
    return parts


NOVEL_NORMAL = {
    "tomato_soup_can": _ycb_can(0.0335, 0.101),
    "tuna_fish_can": _ycb_can(0.043, 0.033),
    "pudding_box": _ycb_box([0.110, 0.089, 0.035]),
    "gelatin_box": _ycb_box([0.085, 0.073, 0.028]),
    "potted_meat_can": _rounded_can(0.097, 0.050, 0.082, 0.012),
    "foam_brick": _ycb_box([0.075, 0.050, 0.050]),
    "rubiks_cube": _ycb_box([0.057, 0.057, 0.057]),
    "cup_a": _ycb_cup(0.0275, 0.060),
    "cup_d": _ycb_cup(0.034, 0.066),
    "cup_g": _ycb_cup(0.039, 0.072),
    "duplo_brick": _duplo,
}
NOVEL_LARGE = {
    "master_chef_can": _ycb_can(0.051, 0.140),
    "sugar_box": _ycb_box([0.175, 0.089, 0.038]),  # lying on its broad side
    "cracker_box": _ycb_box([0.210, 0.158, 0.060]),  # lying on its broad side
    "mustard_bottle": _mustard,
    "cup_j": _ycb_cup(0.045, 0.078),
    "bowl": _bowl,
    "nine_hole_peg_test": _ycb_box([0.150, 0.150, 0.050]),
    "large_clamp": _clamp,
}


def fit_scale(meshes) -> float:
    """Uniform shrink factor (<= 1) that keeps an object within NOVEL_MAX_HEIGHT and NOVEL_MAX_SIDE."""
    low, high = bounds(meshes)
    extent = high - low
    return float(min(1.0, NOVEL_MAX_HEIGHT / extent[2], NOVEL_MAX_SIDE / max(extent[0], extent[1])))


class ProceduralNovelSet:
    """YCB-like shapes at their real sizes (shrunk to fit where needed), one optional large object."""

    name = "procedural-novel"

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]:
        large = choose_large(rng, count)
        out = []
        for i in range(count):
            table = NOVEL_LARGE if i == large else NOVEL_NORMAL
            names = sorted(table)
            name = names[int(rng.integers(len(names)))]
            meshes = table[name](rng)
            scale = fit_scale(meshes)
            if scale < 1.0:
                meshes = [scaled(m, scale) for m in meshes]
            model_id = name if scale == 1.0 else f"{name}_x{scale:.3f}"
            out.append(make_spec(self.name, name, model_id, scale, meshes, random_color(rng), i == large))
        return out
