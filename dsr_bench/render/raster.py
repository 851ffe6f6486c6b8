"""Exact triangle rasterisation in numpy: the same bits on every x86-64 CPU.

Every rendered observation comes from here: the generator's images, depth, TSDF, heightmap and amodal
voxels, and the annotator's exported masks and outlines.
Only IEEE-754 operations that are correctly rounded by definition are used (+, -, *, /, sqrt,
comparisons, min / max), each written out in a fixed order: no BLAS, no transcendental functions,
no float reductions whose order could depend on the SIMD width, no ray tracer that picks its code
path by the CPU's instruction set (open3d's Embree does, and gave last-bit differences in depth
between AVX2 and AVX-512 machines). So a pinned split reproduces bit for bit on any x86-64 CPU.

A fragment is a sample point (a pixel centre at integer coordinates, or a grid column) inside a
triangle's 2D projection. Edge functions are computed from each edge's endpoints in a canonical
order (lower vertex index first), so the two triangles sharing an edge see exactly opposite values;
a sample exactly on an edge goes to one of two same-facing neighbours by a half-plane rule on the
edge's direction (and to both or neither of two folded ones, so vertical lines cross a closed mesh
an even number of times). Rasterisation is therefore watertight: no pixel of a closed mesh falls
through a shared edge, and no column of a voxelised solid is counted twice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Fragments produced per batch of triangles, bounding memory (about 100 bytes each).
_BATCH_FRAGMENTS = 4_000_000


@dataclass(frozen=True)
class Fragments:
    """Samples covered by triangles: triangle index (M,), flat sample index row * width + col (M,),
    and barycentric weights (M, 3) of the triangle's three vertices (each >= 0, summing to 1)."""

    triangle: np.ndarray
    sample: np.ndarray
    weights: np.ndarray


def _edge_table(p: np.ndarray, faces: np.ndarray, area: np.ndarray) -> np.ndarray:
    """Per triangle and edge k (opposite vertex k): (origin u, origin v, du, dv, sign, on-edge rule),
    shape (F, 3, 6). The edge function at sample (su, sv) is sign * (du (sv - v0) - dv (su - u0)),
    computed from the lower-indexed endpoint so that the two triangles sharing an edge get exactly
    negated values; sign also turns clockwise triangles counter-clockwise, so inside is > 0. A
    sample exactly on the edge belongs to the triangle when the rule is 1: the edge, traversed
    counter-clockwise, points down or exactly left."""
    table = np.empty((len(faces), 3, 6))
    flip = area < 0
    for k in range(3):
        a, b = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]
        swap = a > b
        lo, hi = np.where(swap, b, a), np.where(swap, a, b)
        du, dv = p[hi, 0] - p[lo, 0], p[hi, 1] - p[lo, 1]
        sign = np.where(swap != flip, -1.0, 1.0)
        tu, tv = sign * du, sign * dv  # the edge's direction, traversed counter-clockwise (exact: a sign)
        table[:, k] = np.stack([p[lo, 0], p[lo, 1], du, dv, sign, (tv > 0) | ((tv == 0) & (tu < 0))], axis=1)
    return table


def rasterize(points: np.ndarray, faces: np.ndarray, height: int, width: int) -> Fragments:
    """Every (triangle, sample) pair whose sample lies inside the triangle.

    points: (V, 2) float64 sample-space coordinates (u along columns, v along rows; sample (r, c) at
    u = c, v = r); faces: (F, 3) vertex indices; samples: the integer points of [0, width) x [0,
    height). Triangles of zero projected area produce nothing; both orientations are rasterised.
    """
    p = np.asarray(points, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    empty = Fragments(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))
    if len(faces) == 0:
        return empty
    corner = p[faces]  # (F, 3, 2)
    d1, d2 = corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0]
    area = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    finite = np.all(np.isfinite(corner), axis=(1, 2))
    with np.errstate(invalid="ignore"):
        u0 = np.clip(np.ceil(corner[..., 0].min(1)), 0, width)
        u1 = np.clip(np.floor(corner[..., 0].max(1)), -1, width - 1)
        v0 = np.clip(np.ceil(corner[..., 1].min(1)), 0, height)
        v1 = np.clip(np.floor(corner[..., 1].max(1)), -1, height - 1)
    nv = np.where(finite & (area != 0) & (u1 >= u0), v1 - v0 + 1, 0).clip(0).astype(np.int64)
    tris = np.flatnonzero(nv)
    if len(tris) == 0:
        return empty
    # one span per (triangle, sample row): the columns between the triangle's edges on that row, widened
    # by a sample on each side (the exact edge tests below decide; the span only bounds the candidates)
    tri = np.repeat(tris, nv[tris])
    row = np.repeat(v0[tris], nv[tris]) + (np.arange(len(tri)) - np.repeat(np.cumsum(nv[tris]) - nv[tris], nv[tris]))
    lo, hi = np.full(len(tri), np.inf), np.full(len(tri), -np.inf)
    for k in range(3):
        a_, b_ = corner[tri, k], corner[tri, (k + 1) % 3]
        dv = b_[:, 1] - a_[:, 1]
        crosses = (dv != 0) & (row >= np.minimum(a_[:, 1], b_[:, 1])) & (row <= np.maximum(a_[:, 1], b_[:, 1]))
        with np.errstate(invalid="ignore", divide="ignore"):
            x = a_[:, 0] + (row - a_[:, 1]) * (b_[:, 0] - a_[:, 0]) / dv
        lo = np.where(crosses, np.minimum(lo, x), lo)
        hi = np.where(crosses, np.maximum(hi, x), hi)
    lo = np.where(np.isfinite(lo), np.maximum(np.ceil(lo) - 1, u0[tri]), u0[tri])
    hi = np.where(np.isfinite(hi), np.minimum(np.floor(hi) + 1, u1[tri]), u1[tri])
    counts = np.maximum(hi - lo + 1, 0).astype(np.int64)
    keep = counts > 0
    tri, row, lo, counts = tri[keep], row[keep], lo[keep], counts[keep]
    if len(tri) == 0:
        return empty
    edges = _edge_table(p, faces, area)
    out: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    ends = np.cumsum(counts)
    start = 0
    while start < len(tri):
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + _BATCH_FRAGMENTS, side="right"))
        stop = max(stop, start + 1)
        out.append(_fragments_of(edges, tri[start:stop], row[start:stop], lo[start:stop], counts[start:stop], width))
        start = stop
    triangle, sample, weights = (np.concatenate(parts) for parts in zip(*out))
    return Fragments(triangle, sample, weights)


def _fragments_of(edges, tri, row, lo, counts, width):
    """The fragments of the spans (triangle `tri`, sample row `row`, first column `lo`, `counts` columns),
    given every triangle's `_edge_table` rows `edges`."""
    local = np.arange(int(counts.sum()), dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)
    su = np.repeat(lo, counts) + local
    sv = np.repeat(row, counts).astype(np.float64)
    tri = np.repeat(tri, counts)
    table = edges[tri]  # (M, 3, 6)
    inside = np.ones(len(tri), dtype=bool)
    w = []
    for k in range(3):
        t = table[:, k]
        e = t[:, 4] * (t[:, 2] * (sv - t[:, 1]) - t[:, 3] * (su - t[:, 0]))
        inside &= (e > 0) | ((e == 0) & (t[:, 5] > 0))
        w.append(e)
    keep = np.flatnonzero(inside)
    w0, w1, w2 = (x[keep] for x in w)
    total = w0 + w1 + w2
    weights = np.stack([w0 / total, w1 / total, w2 / total], axis=1)
    sample = sv[keep].astype(np.int64) * width + su[keep].astype(np.int64)
    return tri[keep], sample, weights


def interpolate(fragments: Fragments, faces: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Per fragment, the barycentric combination of per-vertex `values` (V,): w0 a + w1 b + w2 c."""
    corner = np.asarray(values, dtype=np.float64)[np.asarray(faces)[fragments.triangle]]  # (M, 3)
    w = fragments.weights
    return w[:, 0] * corner[:, 0] + w[:, 1] * corner[:, 1] + w[:, 2] * corner[:, 2]


def perspective_depth(fragments: Fragments, faces: np.ndarray, vertex_z: np.ndarray) -> np.ndarray:
    """Camera z-depth per fragment of a perspective projection: 1 / (w0 / z0 + w1 / z1 + w2 / z2)
    (1 / z is affine in the image plane), exactly where the pixel's ray meets the triangle's plane."""
    inv = interpolate(fragments, faces, 1.0 / np.asarray(vertex_z, dtype=np.float64))
    return 1.0 / inv


def nearest(fragments: Fragments, depth: np.ndarray, num_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer: per sample the smallest depth (inf where none) and the lowest triangle index among
    the fragments at that depth (-1 where none); independent of the order of the fragments."""
    best = np.full(num_samples, np.inf)
    np.minimum.at(best, fragments.sample, depth)
    winner = np.full(num_samples, np.iinfo(np.int64).max)
    at = depth == best[fragments.sample]
    np.minimum.at(winner, fragments.sample[at], fragments.triangle[at])
    winner[~np.isfinite(best)] = -1
    return best, winner


def highest(fragments: Fragments, z: np.ndarray, num_samples: int, floor: float = 0.0) -> np.ndarray:
    """Per sample the largest z of its fragments, at least `floor` (a heightmap over a table at `floor`)."""
    top = np.full(num_samples, floor)
    np.maximum.at(top, fragments.sample, z)
    return top


def solid_intervals(fragments: Fragments, z: np.ndarray, z_samples: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The runs of points of each column inside a closed mesh: (column, first, stop), one row per run,
    the points `z_samples[first:stop]` of that column being inside.

    `fragments` are a closed mesh's triangles rasterised over the columns (orthographic, looking
    along z) and `z` their heights there. Along each column the crossings, sorted, pair up as
    (enter, exit); a point at height c is inside when enter < c <= exit for one pair. A column with
    an odd number of crossings (it grazes an edge of a mesh that is not watertight) keeps its
    complete pairs. `z_samples` must be increasing.
    """
    if len(z) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.lexsort((z, fragments.sample))
    col, zs = fragments.sample[order], z[order]
    starts = np.flatnonzero(np.r_[True, col[1:] != col[:-1]])
    counts = np.diff(np.r_[starts, len(col)])
    rank = np.arange(len(col)) - np.repeat(starts, counts)
    paired = rank < np.repeat(counts - counts % 2, counts)
    enter = np.flatnonzero(paired & (rank % 2 == 0))
    first = np.searchsorted(z_samples, zs[enter], side="right")  # first point above the entry
    stop = np.searchsorted(z_samples, zs[enter + 1], side="right")  # first point above the exit
    keep = stop > first
    return col[enter][keep], first[keep], stop[keep]
