"""The one checkpoint module: every file a training writes, and every dsr-bench weights file that
`dsr-bench predict --checkpoint`, `train --init` / `--resume` and the CPU track's `--init` read.

One weights format (`WEIGHTS_FORMAT`, version `WEIGHTS_VERSION`): a plain dict, loadable with
`torch.load(weights_only=True)`, written atomically:

- `format`, `version`; `model_type`: the model's name (dsr, single, nowarp, gtwarp, 3dflow, 2dflow,
  se3net, se3posenet), whose entry in `dsr_bench.models.registry` resolves its kind, hence its
  configuration and network class (`registry.KINDS`: the type saved with the weights chooses the class);
  `model_config` (that configuration as a dict); `model` (the state dict; fp16 for the CPU-sized
  tracks' finished weights);
- `role`: "checkpoint" (a `dsr-bench train` run that resumes exactly: + optimizer, scheduler, stage,
  epoch, batch_index, step, rng, seed, world_size), "weights" (a finished model: + recipe and its
  training record) or "stage1" (the CPU track's stage-1 weights, for `--init`);
- `data` (the data trained on: directory name, split, sequence count, split checksum; never a local
  path), `git`, `torch_version`.

Version 1, the files written before this format, is still read: "dsr-bench-checkpoint" (last.pt),
"dsr-bench-cpu-weights", "dsr-bench-cpu-weights-stage1", "dsr-bench-image-weights" (their model type is
their config's name, their role is what the format said). The shipped CPU-track weights stay byte for byte
as they were written (3DFlow's and the 2D track's are version-1 files): their SHA-256 is recorded in the
leaderboard's entries and docs/models.md. The authors' released files are another layout (`models.official_weights`).

Also the pieces every user of a checkpoint shares: `torch_device` (a --device option checked),
`unwrap` (the network inside DDP and torch.compile wrappers) and the RNG states that make a resumed
run exact.
"""

from __future__ import annotations

import json
import random
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch

from dsr_bench.atomic import atomic_path
from dsr_bench.errors import UserError
from dsr_bench.models import registry

if TYPE_CHECKING:
    from dsr_bench.models.dsr_net import DSRNet
    from dsr_bench.models.image_nets import ImageNet

__all__ = ["ROLES", "WEIGHTS_FORMAT", "WEIGHTS_VERSION", "Weights", "data_provenance", "git_hash",
           "half", "mark_finetuned", "read_weights", "rng_state", "save_checkpoint", "save_weights", "set_rng_state",
           "torch_device",
           "trained_split_checksum", "unwrap"]

WEIGHTS_FORMAT = "dsr-bench-weights"
WEIGHTS_VERSION = 2
ROLES = ("checkpoint", "weights", "stage1")
#: what a checkpoint that --resume continues holds beside the weights
CHECKPOINT_SECTIONS = ("optimizer", "scheduler", "stage", "epoch", "batch_index", "step", "rng")
#: version 1: each training path's own format name -> (kind, role)
LEGACY_FORMATS = {"dsr-bench-checkpoint": (registry.VOXEL, "checkpoint"),
                  "dsr-bench-cpu-weights": (registry.VOXEL, "weights"),
                  "dsr-bench-cpu-weights-stage1": (registry.VOXEL, "stage1"),
                  "dsr-bench-image-weights": (registry.IMAGE, "weights")}


def model_types() -> tuple[str, ...]:
    """The model types a weights file may record: the registry's trainable models."""
    return registry.names(*registry.trainable())


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
    np_state = cast(tuple, np.random.get_state())  # legacy=True (the default): the MT19937 tuple
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


def unwrap(model: torch.nn.Module) -> Any:
    """The network inside a DistributedDataParallel (`.module`) and/or torch.compile (`_orig_mod`) wrapper
    (typed Any: the wrappers do not say what they wrap; the caller knows)."""
    net = getattr(model, "module", model)
    return getattr(net, "_orig_mod", net)


def half(state: dict) -> dict:
    """A state dict with its floating-point tensors in fp16 (the CPU-sized tracks' weights files)."""
    return {k: (v.half() if v.is_floating_point() else v) for k, v in state.items()}


def trained_split_checksum(data_dir: Path, split: str | None) -> str:
    """The ground-truth checksum of the split trained on (what `dsr-bench info` shows), "" if unknown."""
    from dsr_bench.dataset.manifest import load_manifest, read_split, split_digest

    try:
        name, _ = read_split(data_dir, split)
        return split_digest(load_manifest(data_dir), name)
    except (UserError, KeyError, ValueError):
        return ""


def data_provenance(data_dir: Path, split: str | None, sequences: int) -> dict:
    """What a weights file records of the data trained on: the directory's name (never a local path), the
    split, the number of sequences and the split's checksum."""
    return {"dir": Path(data_dir).resolve().name, "split": split, "sequences": int(sequences),
            "split_checksum": trained_split_checksum(Path(data_dir), split)}


# --- writing ------------------------------------------------------------------------------------------
def save_weights(path: Path, config, state: dict, role: str, *, fp16: bool = False, data: dict | None = None,
                 **sections) -> Path:
    """Write a weights file atomically: the model type and configuration of `config` (a `ModelConfig` or
    `ImageModelConfig`), the state dict (`fp16`: its floating-point tensors halved), the `role`, the role's
    `sections` (optimizer, recipe, ...), the `data` provenance (`data_provenance`), git commit and torch version."""
    if role not in ROLES:
        raise ValueError(f"role {role!r}: one of {', '.join(ROLES)}")
    if config.name not in model_types():
        raise ValueError(f"model type {config.name!r}: one of {', '.join(model_types())}")
    payload = {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "model_type": config.name, "role": role,
               "model_config": config.as_dict(), "model": half(state) if fp16 else state, **sections,
               **({} if data is None else {"data": data}), "git": git_hash(), "torch_version": str(torch.__version__)}
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


def save_checkpoint(path: Path, model, optimizer, scheduler, model_config, stage, epoch: int, batch_index: int,
                    step: int, extra: dict | None = None) -> Path:
    """A `dsr-bench train` run's checkpoint (role "checkpoint"): model/optimizer/scheduler state, the stage,
    RNG states, data position (epoch, batch_index = batches of that epoch already consumed), step; `extra`:
    further sections (data, seed, world_size)."""
    return save_weights(path, model_config, unwrap(model).state_dict(), "checkpoint",
                        optimizer=optimizer.state_dict(), scheduler=scheduler.state_dict(), stage=stage.as_dict(),
                        epoch=int(epoch), batch_index=int(batch_index), step=int(step), rng=rng_state(),
                        **(extra or {}))


# --- reading ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Weights:
    """A weights file read and checked (`read_weights`): its model type, kind (`registry`), role, format
    version, the model's configuration, and what the file holds (`payload`; also by key: `weights["step"]`)."""

    path: Path
    payload: dict
    model_type: str
    kind: str
    role: str
    version: int
    config: Any  # ModelConfig | ImageModelConfig: its kind's configuration class (`registry.KINDS`), chosen on reading

    def __getitem__(self, key: str):
        return self.payload[key]

    def get(self, key: str, default=None):
        return self.payload.get(key, default)

    def state(self) -> dict:
        """The state dict in fp32 (fp16 files are widened exactly)."""
        return {k: v.float() if v.is_floating_point() else v for k, v in self.payload["model"].items()}

    def load_into(self, net: DSRNet | ImageNet, *, fix: str = "") -> None:
        """Load the weights into `net` (strict); weights of another shape are a UserError naming the file, the
        model they were meant for, and the `fix` if one is given."""
        try:
            net.load_state_dict(self.state())
        except RuntimeError as exc:
            raise UserError(f"{self.path}: weights do not fit the {net.config.name!r} model "
                            f"({str(exc).splitlines()[0][:160]})" + (f"; {fix}" if fix else "")) from None

    def network(self, device="cpu") -> torch.nn.Module:
        """The network its model type names (`DSRNet`, `ImageNet`), built from its configuration, the
        weights loaded, on `device`, in eval mode."""
        net = registry.KINDS[self.kind].network_class()(self.config)
        self.load_into(net)
        return net.to(device).eval()


def mark_finetuned(predictor, weights: Weights) -> None:
    """A predictor of fine-tuned weights (`training.finetune`: a `finetune` record) named `NAME-ft`, as the paper labels
    its fine-tuned rows, its description and weights record saying on what; nothing for other weights."""
    record = weights.get("finetune")
    if not isinstance(record, dict):
        return
    data = record.get("data") or {}
    real = record.get("real_split") or {}
    on = (f"the fine-tune part of the real split {real.get('name')!r} (checksum {str(real.get('checksum'))[:12]})"
          if real else f"the split {data.get('split')} of {data.get('dir')}")
    predictor.name = f"{predictor.name}-ft"
    predictor.description += f"; fine-tuned from {record.get('from')} on {on}"
    predictor.weights = {**predictor.weights, "finetune": {
        "from": record.get("from"), "from_sha256": record.get("from_sha256"), "split": data.get("split"),
        "split_checksum": data.get("split_checksum"), "real_split": real or None, "epochs": record.get("epochs"),
        "sample_steps": record.get("sample_steps")}}


def _fail(path: Path, what: str) -> UserError:
    return UserError(f"{path}: {what}")


def _header(path: Path, payload) -> tuple[str, str, str, int]:
    """(model type, kind, role, version) of a loaded file, or a UserError saying what it is not."""
    if not isinstance(payload, dict) or not {"model", "model_config"} <= set(payload):
        raise _fail(path, "not a dsr-bench checkpoint (no model / model_config); train one with `dsr-bench train`")
    if not isinstance(payload["model_config"], dict) or not isinstance(payload["model"], dict):
        raise _fail(path, "not a dsr-bench checkpoint (model_config and model must be dicts)")
    fmt = payload.get("format")
    if fmt == WEIGHTS_FORMAT:
        version, model_type, role = payload.get("version"), payload.get("model_type"), payload.get("role")
        if not isinstance(version, int) or isinstance(version, bool) or version < 2:
            raise _fail(path, f"version {version!r} of {WEIGHTS_FORMAT} is not one dsr-bench writes")
        if version > WEIGHTS_VERSION:
            raise _fail(path, f"{WEIGHTS_FORMAT} version {version}, newer than this dsr-bench reads "
                              f"({WEIGHTS_VERSION}); update dsr-bench")
        if not isinstance(model_type, str) or model_type not in model_types():
            raise _fail(path, f"model type {model_type!r} is not one of {', '.join(model_types())}")
        if payload["model_config"].get("name") != model_type:
            raise _fail(path, f"model type {model_type!r} but a model_config of "
                              f"{payload['model_config'].get('name')!r}; the file is damaged")
        if role not in ROLES:
            raise _fail(path, f"role {role!r} is not one of {', '.join(ROLES)}")
        return model_type, registry.MODELS[model_type].kind, role, version
    if fmt is None or fmt in LEGACY_FORMATS:  # version 1 (and the first last.pt files, without a format)
        kind, role = (LEGACY_FORMATS[fmt] if fmt is not None
                      else (registry.VOXEL, "checkpoint" if "optimizer" in payload else "weights"))
        name = payload["model_config"].get("name")
        return (name if isinstance(name, str) else ""), kind, role, 1
    raise _fail(path, f"format {fmt!r} is not a dsr-bench weights file")


def read_weights(path: Path, map_location="cpu", *, kind: str | None = None, model: str | None = None,
                 role: str | None = None) -> Weights:
    """Read a weights file of any role and version with torch.load(weights_only=True) (no code in it is ever
    run) and check it: a one-line UserError naming the file if it is missing, cannot be loaded that way, is not
    a dsr-bench weights file, is not of `kind` (`registry.VOXEL`, `registry.IMAGE`), holds another model than
    `model`, is not of
    `role`, or its configuration or weights are unusable."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint not found: {path}")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise _fail(path, f"not a loadable dsr-bench checkpoint ({type(exc).__name__}: {first[:200]})") from None
    model_type, file_kind, file_role, version = _header(path, payload)
    if kind is not None and file_kind != kind:
        wanted = registry.KINDS[kind]
        raise _fail(path, f"not a {wanted.files} weights file; train one with {wanted.train_command()}")
    if not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in payload["model"].items()):
        raise _fail(path, "not a dsr-bench checkpoint (its model is not a state dict of tensors)")
    if any(v.is_floating_point() and not bool(torch.isfinite(v).all()) for v in payload["model"].values()):
        raise _fail(path, "its weights hold NaN or infinite values")
    try:
        config = registry.KINDS[file_kind].config_class().from_dict(payload["model_config"])
    except (TypeError, ValueError, KeyError) as exc:
        raise _fail(path, f"unusable model_config ({exc})") from None
    model_type = model_type or config.name
    if model is not None and config.name != model:
        raise UserError(f"{path} holds a {config.name!r} model, not {model!r}; pass --model {config.name}")
    if role is not None and file_role != role:
        raise _fail(path, {"checkpoint": "finished weights, not a run's checkpoint (last.pt) that --resume continues; "
                                         "start from them with --init",
                           "stage1": "not the stage-1 weights of a CPU-track run (a .stage1.pt file)",
                           "weights": f"a training {file_role}, not finished weights"}[role])
    missing = [key for key in CHECKPOINT_SECTIONS if key not in payload] if file_role == "checkpoint" else []
    if role == "checkpoint" and missing:
        raise _fail(path, f"a checkpoint without {', '.join(missing)}; it cannot be resumed")
    return Weights(path, payload, model_type, file_kind, file_role, version, config)
