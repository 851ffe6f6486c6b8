"""Checkpoints of `dsr-bench train`: plain dicts (state_dicts, configs as dicts, RNG states as
tensors, data position, git hash) loadable with torch.load(weights_only=True), written atomically.

Also the pieces every user of a checkpoint shares: `torch_device` (a --device option checked),
`unwrap` (the network inside DDP and torch.compile wrappers), `load_weights` and the RNG states that
make a resumed run exact.
"""

from __future__ import annotations

import json
import random
import subprocess
from pathlib import Path

import numpy as np
import torch

from dsr_bench.atomic import atomic_path
from dsr_bench.errors import UserError
from dsr_bench.models.config import ModelConfig
from dsr_bench.models.training.schedules import StageConfig

__all__ = ["CHECKPOINT_FORMAT", "git_hash", "load_checkpoint", "load_weights", "rng_state", "save_checkpoint",
           "read_weights_only", "set_rng_state", "trained_split_checksum", "unwrap", "write_weights_file"]

CHECKPOINT_FORMAT = "dsr-bench-checkpoint"


def torch_device(device: str) -> torch.device:
    """The torch device of a --device option (cpu, cuda, cuda:N); UserError if it is not one or no CUDA
    device is available for it."""
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise UserError(f"--device {device!r}: use cpu, cuda or cuda:N") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError("--device cuda but no CUDA device is available; use --device cpu")
    return dev


def git_hash() -> str:
    """The toolkit's git commit (or "unknown" outside a checkout)."""
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                              cwd=Path(__file__).resolve().parent).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def rng_state() -> dict:
    """The torch, numpy, Python and CUDA generators' states, as tensors and strings (weights_only-safe)."""
    np_state = np.random.get_state()
    return {"torch": torch.get_rng_state(), "numpy": torch.from_numpy(np_state[1].astype(np.int64)),
            "numpy_pos": int(np_state[2]), "python": json.dumps(random.getstate()[1]),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}


def set_rng_state(state: dict) -> None:
    """Restore the generators from `rng_state()`."""
    torch.set_rng_state(state["torch"])
    np.random.set_state(("MT19937", state["numpy"].numpy().astype(np.uint32), state["numpy_pos"], 0, 0.0))
    random.setstate((3, tuple(json.loads(state["python"])), None))
    if torch.cuda.is_available() and state["cuda"]:
        torch.cuda.set_rng_state_all(state["cuda"])


def unwrap(model: torch.nn.Module) -> torch.nn.Module:
    """The network inside a DistributedDataParallel (`.module`) and/or torch.compile (`_orig_mod`) wrapper."""
    net = model.module if hasattr(model, "module") else model
    return getattr(net, "_orig_mod", net)


def load_weights(net: torch.nn.Module, state: dict, source, *, model: str = "this model", fix: str = "") -> None:
    """Load a checkpoint's weights (`state["model"]`) into `net`; weights of another shape are a
    UserError naming `source`, the `model` they were meant for, and the `fix` if one is given."""
    try:
        net.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise UserError(f"{source}: weights do not fit {model} ({str(exc).splitlines()[0][:160]})"
                        + (f"; {fix}" if fix else "")) from None


def save_checkpoint(path: Path, model, optimizer, scheduler, model_config: ModelConfig, stage: StageConfig,
                    epoch: int, batch_index: int, step: int, extra: dict | None = None) -> Path:
    """Write a checkpoint atomically: model/optimizer/scheduler state, configs, RNG states, data
    position (epoch, batch_index = batches of that epoch already consumed), step, git hash."""
    payload = {"format": CHECKPOINT_FORMAT, "model": unwrap(model).state_dict(), "optimizer": optimizer.state_dict(),
               "scheduler": scheduler.state_dict(), "model_config": model_config.as_dict(),
               "stage": stage.as_dict(), "epoch": int(epoch), "batch_index": int(batch_index), "step": int(step),
               "rng": rng_state(), "git": git_hash(), "torch_version": str(torch.__version__), **(extra or {})}
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


def read_weights_only(path: Path, map_location="cpu"):
    """torch.load(path, weights_only=True): what a checkpoint or weights file holds; UserError naming the file if it
    is missing or cannot be loaded that way (no code in it is ever run)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint not found: {path}")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise UserError(f"{path}: not a loadable dsr-bench checkpoint ({type(exc).__name__}: {first[:200]})") from None


def load_checkpoint(path: Path, map_location="cpu") -> dict:
    """Load a dsr-bench checkpoint safely (weights_only=True); UserError if it is not one."""
    path = Path(path)
    state = read_weights_only(path, map_location)
    if not isinstance(state, dict) or not {"model", "model_config"} <= set(state):
        raise UserError(f"{path}: not a dsr-bench checkpoint (no model / model_config); "
                        "train one with `dsr-bench train`")
    try:
        ModelConfig.from_dict(state["model_config"])
    except (TypeError, ValueError, KeyError) as exc:
        raise UserError(f"{path}: unusable model_config ({exc})") from None
    return state


def trained_split_checksum(data_dir: Path, split: str | None) -> str:
    """The ground-truth checksum of the split trained on (what `dsr-bench info` shows), "" if unknown."""
    from dsr_bench.dataset.manifest import load_manifest, read_split, split_digest

    try:
        name, _ = read_split(data_dir, split)
        return split_digest(load_manifest(data_dir), name)
    except (UserError, KeyError, ValueError):
        return ""


def half(state: dict) -> dict:
    """A state dict with its floating-point tensors in fp16 (the CPU-sized tracks' weights files)."""
    return {k: (v.half() if v.is_floating_point() else v) for k, v in state.items()}


def write_weights_file(out: Path, fmt: str, model_config: dict, state: dict, data_dir: Path, split: str | None,
                       sequences: int, **extra) -> Path:
    """Write a weights-only file atomically: `fmt`, the model config, fp16 weights, `extra` (the recipe, losses, ...)
    and the provenance: the data trained on (directory name, split, sequence count, split checksum, never a local
    path), the git commit and torch's version. Loadable with torch.load(weights_only=True)."""
    payload = {"format": fmt, "model_config": model_config, "model": half(state), **extra,
               "data": {"dir": Path(data_dir).resolve().name, "split": split, "sequences": int(sequences),
                        "split_checksum": trained_split_checksum(Path(data_dir), split)},
               "git": git_hash(), "torch_version": str(torch.__version__)}
    with atomic_path(out) as tmp:
        torch.save(payload, tmp)
    return Path(out)
