"""The shipped CPU-track networks' predictions are the same bytes on every x86-64 CPU with AVX2: `dsr-bench predict`
runs them with the same kernels whatever the CPU (MKL's reproducible branch, oneDNN's and ATen's AVX2 kernels, set
before torch loads: `dsr_bench.cli.scoring.SAME_BITS_ENV`; one thread: `inference.same_bits_on_any_cpu`). Checked by
predicting a small synthetic sequence in fresh processes under other dispatch levels (MKL told to use fewer
instructions, numpy's SIMD targets switched off, OpenBLAS forced to its Haswell kernels, more threads asked for), and
on an emulated AMD EPYC-Rome (AVX2, no AVX-512, other cache sizes) where qemu-user is installed; and that the kernels
matter: with MKL or oneDNN left to pick their own per CPU, the bytes differ."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torch")

from dsr_bench.cli.scoring import SAME_BITS_ENV  # noqa: E402

#: a 3D-track network (MKL's GEMMs under slow_conv3d, the warp) and a 2D-track one (torch sends its convs to oneDNN)
MODELS = ("dsr", "2dflow")
#: variables that choose kernels, removed from the environment of the reference run
KERNEL_VARIABLES = (*SAME_BITS_ENV, "ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA", "MKL_ENABLE_INSTRUCTIONS",
                    "NPY_DISABLE_CPU_FEATURES", "OPENBLAS_CORETYPE", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def _dispatched_features() -> list[str]:
    """numpy's SIMD dispatch targets above its baseline that this CPU has (to switch them off)."""
    from numpy._core._multiarray_umath import __cpu_baseline__, __cpu_dispatch__, __cpu_features__

    return [f for f in __cpu_dispatch__ if __cpu_features__.get(f) and f not in __cpu_baseline__]


def _predict(data: Path, model: str, out: Path, env: dict[str, str], prefix: tuple[str, ...] = (),
             extra: tuple[str, ...] = ()) -> dict[str, bytes]:
    """`dsr-bench predict --model MODEL` (its shipped weights, unless `extra` says otherwise) in a fresh process; the
    prediction files' bytes."""
    base = {k: v for k, v in os.environ.items() if k not in KERNEL_VARIABLES}
    cmd = [*prefix, sys.executable, "-m", "dsr_bench.cli", "predict", "--model", model, "--data", str(data),
           "--out", str(out), *extra]
    done = subprocess.run(cmd, env={**base, **env}, capture_output=True, text=True, timeout=1800)
    assert done.returncode == 0, done.stderr[-2000:]
    return {p.name: p.read_bytes() for p in sorted(out.glob("*.h5"))}  # meta.json holds the time a step took


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    from dsr_bench.testing import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("seq") / "data", num_sequences=1, num_steps=2)


@pytest.fixture(scope="module")
def reference(data, tmp_path_factory) -> dict[str, dict[str, bytes]]:
    out = tmp_path_factory.mktemp("reference")
    return {model: _predict(data, model, out / model, {}) for model in MODELS}


def _an_avx2_cpu() -> dict[str, str]:
    """What an AVX2 machine without AVX-512 would dispatch to, as far as the environment can say it."""
    env = {"ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_ENABLE_INSTRUCTIONS": "AVX2", "OPENBLAS_CORETYPE": "Haswell",
           "OMP_NUM_THREADS": "2"}
    features = _dispatched_features()
    if features:
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(features)
    return env


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("level", ["avx2-cpu", "sse4-3-threads"])
def test_the_same_prediction_bytes_whatever_the_cpu_dispatches_to(data, reference, tmp_path, model, level):
    env = {"avx2-cpu": _an_avx2_cpu(),
           "sse4-3-threads": {"MKL_ENABLE_INSTRUCTIONS": "SSE4_2", "OMP_NUM_THREADS": "3",
                              "MKL_NUM_THREADS": "3"}}[level]
    assert reference[model], "no prediction file"
    assert _predict(data, model, tmp_path / "p", env) == reference[model]


@pytest.mark.parametrize("model,env", [("dsr", {"MKL_CBWR": "AUTO"}), ("2dflow", {"ONEDNN_MAX_CPU_ISA": "SSE41"})],
                         ids=["dsr-mkl-auto", "2dflow-onednn-sse41"])
def test_the_kernels_matter(data, reference, tmp_path, model, env):
    """The check above can fail: with MKL choosing its kernels by CPU, or oneDNN capped elsewhere (a user's
    setting is kept), the predictions differ in their last bits, as an Intel Xeon's differed from an AMD EPYC's."""
    assert _predict(data, model, tmp_path / "p", env) != reference[model]


def test_a_checkpoint_predicted_as_the_evidence_scripts_do_is_the_shipped_weights_bytes(data, reference, tmp_path,
                                                                                         monkeypatch):
    """scripts/cpu_track_evidence.py predicts a --checkpoint in `same_bits_env()`: the shipped file given as a
    checkpoint then makes the bytes the shipped path makes (with this machine's own kernels it need not)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    import cpu_track_evidence

    from dsr_bench.models.predictors import shipped_weights

    for name in KERNEL_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    env = {k: v for k, v in cpu_track_evidence.same_bits_env().items() if k in KERNEL_VARIABLES}
    assert env == {**SAME_BITS_ENV, "OMP_NUM_THREADS": "1"}
    got = _predict(data, "dsr", tmp_path / "p", env, extra=("--checkpoint", str(shipped_weights("dsr"))))
    assert got == reference["dsr"]


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("qemu-x86_64") is None, reason="qemu-user is not installed")
@pytest.mark.parametrize("model", MODELS)
def test_the_same_prediction_bytes_on_an_emulated_avx2_cpu(data, reference, tmp_path, model):
    """The whole prediction (torch, MKL, oneDNN, numpy, the predictions' writer) on an emulated AMD EPYC-Rome (AVX2,
    no AVX-512, its own cache sizes): about a minute here, most of it torch loading under emulation. numpy keeps to
    its baseline loops there, as in tests/test_reproducibility.py."""
    env = {"OPENBLAS_CORETYPE": "Haswell"}
    features = _dispatched_features()
    if features:
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(features)
    got = _predict(data, model, tmp_path / "p", env, prefix=("qemu-x86_64", "-cpu", "EPYC-Rome"))
    assert got == reference[model]
