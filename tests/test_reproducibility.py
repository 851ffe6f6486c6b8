"""What "reproducible" means, tested: the same bits on other instruction sets, and a pin comparison that
tells rendering noise from a changed benchmark."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dsr_bench.dataset.digests import fingerprint, within_tolerance
from dsr_bench.dataset.manifest import build_manifest, load_manifest, write_manifest
from dsr_bench.dataset.pins import build_pin, compare_with_pin, summarize
from dsr_bench.dataset.sequence import SequenceReader, write_sequence

GENERATE = ["generate", "--objects", "cube", "-n", "1", "--steps", "2", "--seed", "11"]


def _array_digests(directory: Path) -> dict[str, str]:
    with SequenceReader(directory / "seq_0000.h5") as seq:
        return dict(seq.attrs["array_sha256"])


def _generate(out: Path, env: dict | None = None, prefix: tuple[str, ...] = ()) -> None:
    cmd = [*prefix, sys.executable, "-m", "dsr_bench.cli", *GENERATE, "--out", str(out)]
    subprocess.run(cmd, check=True, env={**os.environ, **(env or {})}, capture_output=True, timeout=900)


def _dispatched_features() -> list[str]:
    """numpy's SIMD dispatch targets above its baseline that this CPU has (to switch them off)."""
    from numpy._core._multiarray_umath import __cpu_baseline__, __cpu_dispatch__, __cpu_features__

    return [f for f in __cpu_dispatch__ if __cpu_features__.get(f) and f not in __cpu_baseline__]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    pytest.importorskip("pybullet")
    out = tmp_path_factory.mktemp("native") / "data"
    _generate(out)
    return out


def test_same_bits_whatever_simd_and_blas_kernels_the_cpu_selects(reference, tmp_path):
    """numpy's SIMD loops (AVX-512 / AVX2 / baseline) and OpenBLAS's kernels are picked per CPU at run
    time: with every dispatch target above numpy's baseline switched off and OpenBLAS forced to its
    Haswell kernels, as on an AVX2-only machine, every array is identical."""
    features = _dispatched_features()
    env = {"OPENBLAS_CORETYPE": "Haswell"}
    if features:
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(features)
    _generate(tmp_path / "d", env)
    assert _array_digests(tmp_path / "d") == _array_digests(reference)


@pytest.mark.skipif(shutil.which("qemu-x86_64") is None, reason="qemu-user is not installed")
def test_same_bits_on_an_emulated_avx2_cpu(reference, tmp_path):
    """The whole generator (pybullet, glibc's libm, numpy, our rasteriser) on an emulated AMD EPYC-Rome
    (AVX2, no AVX-512). numpy keeps to its baseline loops there (qemu's AVX2 emulation miscomputes some
    of numpy's AVX2 kernels); the test above covers those natively."""
    env = {"NPY_DISABLE_CPU_FEATURES": " ".join(_dispatched_features()), "OPENBLAS_CORETYPE": "Haswell"}
    if not env["NPY_DISABLE_CPU_FEATURES"]:
        del env["NPY_DISABLE_CPU_FEATURES"]
    _generate(tmp_path / "d", env, prefix=("qemu-x86_64", "-cpu", "EPYC-Rome"))
    assert _array_digests(tmp_path / "d") == _array_digests(reference)


# --- pins: rendering noise is not a changed benchmark --------------------------------------------------
def _rewrite(path: Path, change) -> None:
    """Rewrite a sequence with `change(arrays)` applied (`write_sequence` recomputes its digests), as a generator
    that produced those arrays would have written it."""
    with SequenceReader(path) as seq:
        arrays = {n: seq.read(n) for n in seq.array_names()}  # stored and derived (points)
        attrs = {k: v for k, v in seq.attrs.items() if k not in ("format", "schema_version")}
        meshes = {i: seq.mesh(i) for i in range(seq.num_objects) if seq.mesh(i) is not None}
    change(arrays)
    write_sequence(path, arrays, attrs, meshes)


def _one_ulp(a: np.ndarray, rng: np.random.Generator, share: float = 0.01) -> np.ndarray:
    """`a` with a share of its finite non-zero values moved by one ulp up or down."""
    out = a.copy()
    flat = out.reshape(-1)
    candidates = np.flatnonzero(np.isfinite(flat) & (flat != 0))
    pick = rng.choice(candidates, size=max(1, int(share * len(candidates))), replace=False)
    direction = np.where(rng.random(len(pick)) < 0.5, -np.inf, np.inf).astype(flat.dtype)
    flat[pick] = np.nextafter(flat[pick], direction)
    return out


def _pinned(data: Path) -> dict:
    build = load_manifest(data)
    return build_pin(data, ["seq_0000"], build, "all")


def _compare(data: Path, pin: dict):
    write_manifest(data, build_manifest(data))
    manifest = load_manifest(data)
    digests = {s["name"]: s for s in manifest["sequences"]}

    def prints(name):
        from dsr_bench.dataset.sequence import file_fingerprints
        return file_fingerprints(data / f"{name}.h5")[0]

    return compare_with_pin(pin, digests, prints)


def test_a_rendering_difference_of_one_ulp_is_noted_and_a_ground_truth_change_is_caught(reference, tmp_path):
    pin = _pinned(reference)
    rng = np.random.default_rng(0)

    noisy = tmp_path / "noisy"
    shutil.copytree(reference, noisy)

    def rendering_noise(arrays):  # what another CPU's renderer could do: last bits of depth and what follows
        for name in ("tsdf", "heightmap", "cameras/front/depth", "cameras/front/points",
                     "cameras/front/scene_flow_2d"):
            arrays[name] = _one_ulp(arrays[name], rng)

    _rewrite(noisy / "seq_0000.h5", rendering_noise)
    result = _compare(noisy, pin)
    assert result.reproduced and not result.ground_truth
    assert set(result.observations_within) == {"seq_0000"}
    noted = " ".join(result.observations_within["seq_0000"])
    assert all(name in noted for name in ("tsdf", "heightmap", "cameras/front/depth"))
    lines = summarize("all", result)
    assert len(lines) == 1 and lines[0][1].startswith("note:") and "ground truth is identical" in lines[0][1]

    changed = tmp_path / "changed"
    shutil.copytree(reference, changed)

    def one_voxel(arrays):  # a real ground-truth change: one voxel of one object's amodal mask
        mask = arrays["mask_3d"]
        index = tuple(np.argwhere(mask[1] > 0)[0])
        mask[1][index] = 0

    _rewrite(changed / "seq_0000.h5", one_voxel)
    result = _compare(changed, pin)
    assert not result.reproduced
    assert list(result.ground_truth) == ["seq_0000"]
    (detail,) = result.ground_truth["seq_0000"]
    assert detail.startswith("mask_3d: -1 non-zero values")
    (line,) = summarize("all", result)
    assert line[0] == "seq_0000" and "ground truth differs" in line[1] and "mask_3d" in line[1]


def test_a_pin_without_fingerprints_names_the_changed_group_and_is_built_alike_in_workers(reference, tmp_path):
    """A training split of thousands of sequences is pinned without array fingerprints (`fingerprints=False`):
    a sequence whose ground truth or observations changed is still caught, by group; the digests are those of the
    full pin, whether read here or in worker processes."""
    data = tmp_path / "two"
    shutil.copytree(reference, data)
    shutil.copyfile(data / "seq_0000.h5", data / "seq_0001.h5")
    write_manifest(data, build_manifest(data))
    full = build_pin(data, ["seq_0000", "seq_0001"], load_manifest(data), "all")
    slim = build_pin(data, ["seq_0000", "seq_0001"], load_manifest(data), "all", workers=2, fingerprints=False)
    assert slim["fields"] == [] and all(entry["arrays"] == [] for entry in slim["sequences"].values())
    assert {k: slim[k] for k in ("checksum", "observations_checksum")} == \
        {k: full[k] for k in ("checksum", "observations_checksum")}
    assert all({k: v for k, v in slim["sequences"][n].items() if k != "arrays"} ==
               {k: v for k, v in full["sequences"][n].items() if k != "arrays"} for n in full["sequences"])

    def one_voxel(arrays):
        mask = arrays["mask_3d"]
        mask[1][tuple(np.argwhere(mask[1] > 0)[0])] = 0

    _rewrite(data / "seq_0001.h5", one_voxel)
    result = _compare(data, slim)
    assert not result.reproduced and list(result.ground_truth) == ["seq_0001"]
    assert result.ground_truth["seq_0001"] == ["its ground truth differs from the pin (this split pins no array "
                                               "fingerprints)"]
    assert not result.observations_out and not result.observations_within


def test_the_tolerance_tells_noise_from_a_different_scene():
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.4, 0.9, (11, 240, 320)).astype(np.float32)
    depth[:, :40] = 0  # no return
    pinned = fingerprint("depth", depth)
    assert within_tolerance(fingerprint("depth", _one_ulp(depth, rng, share=0.5)), pinned)
    moved = depth.copy()
    moved[3] = np.roll(moved[3], 30, axis=1)  # one step of another scene
    assert not within_tolerance(fingerprint("depth", moved), pinned)


def test_the_policy_ignores_one_ulp_of_rendering_noise(reference):
    """Every decision of the policy, drawn from the same rng, is unchanged when the heightmap it sees
    moves by one ulp anywhere (its only rendered input; a choice could flip only for a cell within
    one ulp, 1e-9 m, of the 5 mm free-height threshold)."""
    from dsr_bench.generators.policy import make_policy

    with SequenceReader(reference / "seq_0000.h5") as seq:
        heightmap = seq.read("heightmap", 0)
        xy = seq.read("object_poses", 0)[:, :2]
    rng = np.random.default_rng(5)
    noisy = [_one_ulp(heightmap, rng, share=1.0) for _ in range(3)]
    for seed in range(20):
        decisions = []
        for hm in [heightmap, *noisy]:
            policy = make_policy("heuristic", np.random.default_rng(seed), len(xy))
            policy.reset(xy)
            d = policy.propose(hm, xy)
            decisions.append(None if d is None else (d.object_index, d.direction, d.start_rc, d.attempts))
        assert decisions[0] is not None and all(d == decisions[0] for d in decisions)
