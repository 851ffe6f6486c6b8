"""Built-in object sets, deterministic from the rng and needing no download.

- `cube`: the paper's boxes, half extents (30, 30, 35) / s m for s in the official list.
- `procedural`: parametric families for the five ShapeNet training categories (mug with a handle,
  bottle, can, phone-like slab, sofa) with the official category scale ranges (normal / large)
  applied to shapes whose bounding-box diagonal is 0.15 m at scale 1 (as ShapeNetCore v2 models,
  normalised to a unit diagonal, scaled to 0.15 m), and the official mix rules.
- `procedural-novel`: YCB-like shapes at their real sizes (boxes, cans, cups, a bowl, a foam brick,
  an L-shaped clamp, a mustard-like bottle, a peg board), disjoint from `procedural`, for the
  novel-object test split.
"""

from __future__ import annotations

import numpy as np

from generators.objects.spec import ObjectSpec, make_spec, random_color

CUBE_DIVISORS = (700, 750, 800, 850, 900, 1000, 1100, 1200, 1400)
NORMALISED_DIAGONAL = 0.15  # m: bounding-box diagonal at scale 1 (ShapeNetCore v2 normalises it to 1)
#: Official category scale ranges: (normal low, normal high), (large low, large high).
CATEGORY_SCALES = {
    "bottle": ((0.7, 0.8), (1.1, 1.2)),
    "can": ((0.7, 0.9), (1.1, 1.2)),
    "mug": ((0.8, 0.9), (1.1, 1.2)),
    "sofa": ((0.4, 0.7), (1.0, 1.2)),
    "phone": ((0.7, 1.0), (1.0, 1.1)),
}
PROCEDURAL_CATEGORIES = tuple(CATEGORY_SCALES)
P_FORCE_CAN = 0.3
P_RANDOM_BOX = 0.3
P_LARGE = 0.5  # a scene has one large object with this probability


def _trimesh():
    import trimesh

    return trimesh


def _box(size, centre=(0, 0, 0)):
    tm = _trimesh()
    return tm.creation.box(extents=np.asarray(size, float), transform=tm.transformations.translation_matrix(centre))


def _revolve(profile) -> object:
    """A solid of revolution about z from a (radius, height) profile starting and ending on the axis."""
    return _trimesh().creation.revolve(np.asarray(profile, float), sections=40)


def _normalise(meshes, diagonal: float) -> list:
    """Scale meshes jointly so their bounding-box diagonal is `diagonal` metres, resting on z = 0."""
    tm = _trimesh()
    bounds = tm.util.concatenate(meshes).bounds
    factor = diagonal / np.linalg.norm(bounds[1] - bounds[0])
    out = []
    for m in meshes:
        m = m.copy()
        m.apply_scale(factor)
        out.append(m)
    low = tm.util.concatenate(out).bounds[0]
    for m in out:
        m.apply_translation([0, 0, -low[2]])
    return out


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
    parts = [body,
             _box([reach + wall, t, bar], [r + reach / 2 - wall / 2, 0, z1 - bar / 2]),   # upper arm
             _box([reach + wall, t, bar], [r + reach / 2 - wall / 2, 0, z0 + bar / 2]),   # lower arm
             _box([bar, t, z1 - z0], [r + reach - bar / 2, 0, (z0 + z1) / 2])]            # grip
    return parts, f"mug_r{r:.3f}_h{h:.3f}_reach{reach:.3f}"


def _phone(rng):
    w, length, t = rng.uniform(0.45, 0.55), 1.0, rng.uniform(0.06, 0.09)
    return [_box([w, length, t], [0, 0, t / 2])], f"phone_w{w:.3f}_t{t:.3f}"


def _sofa(rng):
    width, depth = 1.0, rng.uniform(0.45, 0.6)
    seat_h, back_h, arm_h = rng.uniform(0.15, 0.22), rng.uniform(0.4, 0.55), rng.uniform(0.25, 0.33)
    back_t, arm_w = rng.uniform(0.1, 0.15), rng.uniform(0.08, 0.12)
    parts = [_box([width, depth, seat_h], [0, 0, seat_h / 2]),
             _box([width, back_t, back_h], [0, depth / 2 - back_t / 2, back_h / 2]),
             _box([arm_w, depth, arm_h], [-width / 2 + arm_w / 2, 0, arm_h / 2]),
             _box([arm_w, depth, arm_h], [width / 2 - arm_w / 2, 0, arm_h / 2])]
    return parts, f"sofa_d{depth:.3f}_b{back_h:.3f}"


FAMILIES = {"can": _can, "bottle": _bottle, "mug": _mug, "phone": _phone, "sofa": _sofa}


def _small_box(rng, set_name: str) -> ObjectSpec:
    """The official random small box: 25-40 x 30-60 x 15-32 voxels of 2 mm."""
    size = np.array([rng.integers(25, 41), rng.integers(30, 61), rng.integers(15, 33)]) * 0.002
    return make_spec(set_name, "box", f"box_{int(size[0] * 1000)}x{int(size[1] * 1000)}x{int(size[2] * 1000)}mm",
                     1.0, [_box(size, [0, 0, size[2] / 2])], random_color(rng), False)


class CubeSet:
    """The paper's boxes (official half extents), random colours."""

    name = "cube"

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]:
        out = []
        for _ in range(count):
            s = int(rng.choice(CUBE_DIVISORS))
            half = np.array([30.0, 30.0, 35.0]) / s
            out.append(make_spec(self.name, "box", f"cube_s{s}", 1.0 / s, [_box(2 * half, [0, 0, half[2]])],
                                 random_color(rng), False))
        return out


class ProceduralSet:
    """Parametric mugs, bottles, cans, phones and sofas with the official scales and mix rules."""

    name = "procedural"

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]:
        large = int(rng.integers(count)) if rng.random() < P_LARGE else -1
        out = []
        for i in range(count):
            category = str(rng.choice(PROCEDURAL_CATEGORIES))
            if rng.random() < P_FORCE_CAN:
                category = "can"
            if i != large and rng.random() < P_RANDOM_BOX:
                out.append(_small_box(rng, self.name))
                continue
            meshes, model_id = FAMILIES[category](rng)
            low, high = CATEGORY_SCALES[category][1 if i == large else 0]
            scale = float(rng.uniform(low, high))
            meshes = _normalise(meshes, NORMALISED_DIAGONAL * scale)
            out.append(make_spec(self.name, category, model_id, scale, meshes, random_color(rng), i == large))
        return out


# --- YCB-like novel shapes (metres) -------------------------------------------------------------
def _ycb_box(dims):
    def build(rng):
        return [_box(dims, [0, 0, dims[2] / 2])]
    return build


def _ycb_can(radius, height):
    def build(rng):
        return [_revolve([[0, 0], [radius, 0], [radius, height], [0, height]])]
    return build


def _ycb_cup(radius_top, height):
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


def _clamp(rng, arm=0.11, foot=0.07, t=0.02, h=0.03):
    return [_box([arm, t, h], [arm / 2, 0, h / 2]), _box([t, foot, h], [t / 2, foot / 2 + t / 2, h / 2])]


def _mustard(rng):
    return [_revolve([[0, 0], [0.03, 0], [0.032, 0.13], [0.012, 0.165], [0.012, 0.18], [0, 0.18]])]


NOVEL_NORMAL = {
    "tomato_soup_can": _ycb_can(0.033, 0.101),
    "tuna_fish_can": _ycb_can(0.043, 0.033),
    "pudding_box": _ycb_box([0.035, 0.110, 0.089]),
    "gelatin_box": _ycb_box([0.028, 0.085, 0.073]),
    "potted_meat_can": _ycb_box([0.050, 0.097, 0.082]),
    "foam_brick": _ycb_box([0.050, 0.075, 0.050]),
    "rubiks_cube": _ycb_box([0.057, 0.057, 0.057]),
    "cup_small": _ycb_cup(0.030, 0.055),
    "cup_medium": _ycb_cup(0.036, 0.064),
    "cup_large": _ycb_cup(0.042, 0.073),
    "bowl": _bowl,
    "duplo_brick": _ycb_box([0.032, 0.064, 0.024]),
}
NOVEL_LARGE = {
    "master_chef_can": _ycb_can(0.051, 0.140),
    "sugar_box": _ycb_box([0.038, 0.089, 0.175]),
    "mustard_bottle": _mustard,
    "nine_hole_peg_test": _ycb_box([0.125, 0.125, 0.05]),
    "large_clamp": _clamp,
}


class ProceduralNovelSet:
    """YCB-like shapes at their real sizes, one optional large object per scene."""

    name = "procedural-novel"

    def sample(self, rng: np.random.Generator, count: int) -> list[ObjectSpec]:
        large = int(rng.integers(count)) if rng.random() < P_LARGE else -1
        out = []
        for i in range(count):
            table = NOVEL_LARGE if i == large else NOVEL_NORMAL
            name = str(rng.choice(sorted(table)))
            meshes = table[name](rng)
            out.append(make_spec(self.name, name, name, 1.0, meshes, random_color(rng), i == large))
        return out
