"""The authors' released checkpoints (dsr.pth, dsr_ft.pth, single.pth, nowarp.pth, gtwarp.pth,
3dflow.pth) converted to `DSRNet` state dicts by an explicit table of names.

An official file is a torch.save'd dict whose 'state_dict' holds `ModelDSR(object_num=5,
transform_type='se3euler', motion_type=...)`'s weights: `motion_type='se3'` (a `transform_decoder`
and a `mask_decoder`) for dsr, dsr_ft, single, nowarp and gtwarp, `motion_type='conv'` (a
`motion_decoder`, no mask decoder) for 3dflow. The layers are the same as ours (conv3 without bias
-> BatchNorm -> LeakyReLU, the same channel counts and concatenation order), only their names differ;
no tensor needs transposing or reshaping (convs are (out, in, k...) and linear layers (out, in) in both),
and BatchNorm's running statistics and `num_batches_tracked` come across with the weights.

Rules (official prefix -> ours), module by module:
  volume_encoder.conv00 -> encoder.level0; conv1i -> encoder.level1.i (i 0..3); conv2i -> encoder.level2.i
    (i 0..3); conv30 -> encoder.level3.0; resn31, resn32 -> encoder.level3.1, encoder.level3.2
  feature_decoder.convji -> decoder.upj.i (j 0..3, i 0..1)
  mask_decoder.decoder -> mask_head
  {transform,motion}_decoder.conv2d1i -> motion_head.action.trunk1.i (i 0..3); conv2d14 -> action.emb1;
    conv2d2i -> action.trunk2.i (i 0..3); conv2d24 -> action.emb2
  transform_decoder.conv3d00 -> motion_head.conv0; conv3d10 -> conv1; conv3d20..23 -> conv2.0..3;
    conv3d30 -> conv2.4; conv3d40 -> conv2.5; conv3d50 -> to_vector; mlp._layers.i -> mlp.(2 i)
    (ours interleaves the LeakyReLU modules in one nn.Sequential)
  motion_decoder.conv3d00, 10, 20 -> motion_head.down0, down1, down2; conv3d30, 40, 50 -> up0, up1, up2;
    conv3d60 -> out

Every official tensor has a counterpart. One of ours has none: the official 3DFlow has no mask head,
and ours keeps one so the baseline fills the predictions' masks. Converting 3dflow.pth sets our mask
head to predict background everywhere (weights 0, biases 0 but the background's, `FILLED_MASK_BIAS`):
its masks are empty, and its mask scores mean nothing.

Converted weights are run as the authors ran them by `inference.load_official_predictor` (`predict
--weights`): the history warped with their kernel (`warp.OFFICIAL`, base corner truncated toward zero,
which they were trained with), BatchNorm with statistics over batches of 12 sequences (their test
protocol); `--warp floor` and `--bn-batch 1` depart from it, and the predictions' meta.json says which.
"""

from __future__ import annotations

import functools
from pathlib import Path

import torch

from dsr_bench.errors import UserError

#: the official network's top-level modules, and which motion layout each of our variants needs
OFFICIAL_MODULES = ("volume_encoder", "feature_decoder", "mask_decoder", "transform_decoder", "motion_decoder")
LAYOUT = {"dsr": "se3", "single": "se3", "nowarp": "se3", "gtwarp": "se3", "3dflow": "conv"}
#: the released files, by stem, and the variant each one is
RELEASE_FILES = {"dsr": "dsr", "dsr_ft": "dsr", "single": "single", "nowarp": "nowarp", "gtwarp": "gtwarp",
                 "3dflow": "3dflow"}
#: our tensors the official conv-motion (3DFlow) layout has no counterpart for
NOT_IN_OFFICIAL = {"se3": (), "conv": ("mask_head.weight", "mask_head.bias")}
FILLED_MASK_BIAS = 10.0  # background logit of the filled 3DFlow mask head: P(background) = 0.9998
OFFICIAL_GRID = (128, 128, 48)

_BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
_LAYOUT_WORDS = {"se3": "an SE(3)-motion network (dsr, dsr_ft, single, nowarp, gtwarp)",
                 "conv": "a conv-motion (3DFlow) network"}
_USE = {"se3": "use --model dsr, single, nowarp or gtwarp (the one the file was trained as)",
        "conv": "use --model 3dflow"}


def _block(theirs: str, ours: str) -> list[tuple[str, str]]:
    """A conv block: conv (no bias) + BatchNorm, named conv/norm in both."""
    return [(f"{theirs}.conv.weight", f"{ours}.conv.weight")] + [(f"{theirs}.norm.{p}", f"{ours}.norm.{p}")
                                                                  for p in _BN]


def _resblock(theirs: str, ours: str) -> list[tuple[str, str]]:
    """A residual block: conv1/bn1/conv2/bn2 in both."""
    out = []
    for i in (1, 2):
        out.append((f"{theirs}.conv{i}.weight", f"{ours}.conv{i}.weight"))
        out += [(f"{theirs}.bn{i}.{p}", f"{ours}.bn{i}.{p}") for p in _BN]
    return out


def _conv(theirs: str, ours: str) -> list[tuple[str, str]]:
    """A plain conv with a bias (no BatchNorm)."""
    return [(f"{theirs}.weight", f"{ours}.weight"), (f"{theirs}.bias", f"{ours}.bias")]


def _action_encoder(head: str) -> list[tuple[str, str]]:
    out = []
    for level in (1, 2):
        out += [p for i in range(4) for p in _block(f"{head}.conv2d{level}{i}", f"motion_head.action.trunk{level}.{i}")]
        out += _block(f"{head}.conv2d{level}4", f"motion_head.action.emb{level}")
    return out


@functools.cache
def key_table(layout: str, mlp_layers: int = 5) -> tuple[tuple[str, str], ...]:
    """(official key, our key) for every tensor of the official `layout` ("se3" or "conv"), in the
    official order; `mlp_layers` is the SE(3) MLP's linear layers (official: 5)."""
    if layout not in NOT_IN_OFFICIAL:
        raise ValueError(f"layout {layout!r}: se3 or conv")
    t = _block("volume_encoder.conv00", "encoder.level0")
    for level in (1, 2):
        t += [p for i in range(4) for p in _block(f"volume_encoder.conv{level}{i}", f"encoder.level{level}.{i}")]
    t += _block("volume_encoder.conv30", "encoder.level3.0")
    t += _resblock("volume_encoder.resn31", "encoder.level3.1") + _resblock("volume_encoder.resn32", "encoder.level3.2")
    t += [p for j in range(4) for i in range(2) for p in _block(f"feature_decoder.conv{j}{i}", f"decoder.up{j}.{i}")]
    if layout == "se3":
        t += _conv("mask_decoder.decoder", "mask_head")
        h = "transform_decoder"
        t += _block(f"{h}.conv3d00", "motion_head.conv0") + _block(f"{h}.conv3d10", "motion_head.conv1")
        for theirs, i in (("20", 0), ("21", 1), ("22", 2), ("23", 3), ("30", 4), ("40", 5)):
            t += _block(f"{h}.conv3d{theirs}", f"motion_head.conv2.{i}")
        t += _conv(f"{h}.conv3d50", "motion_head.to_vector")
        t += _action_encoder(h)
        t += [(f"{h}.mlp._layers.{i}.{p}", f"motion_head.mlp.{2 * i}.{p}") for i in range(mlp_layers)
              for p in ("weight", "bias")]
    else:
        h = "motion_decoder"
        for theirs, ours in (("00", "down0"), ("10", "down1"), ("20", "down2"), ("30", "up0"), ("40", "up1"),
                             ("50", "up2")):
            t += _block(f"{h}.conv3d{theirs}", f"motion_head.{ours}")
        t += _conv(f"{h}.conv3d60", "motion_head.out")
        t += _action_encoder(h)
    return tuple(t)


def _weights_of(obj):
    """The state dict inside an official file's dict (its 'state_dict'), or `obj` itself."""
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if isinstance(obj, dict) and obj and all(isinstance(k, str) for k in obj):
        if all(k.startswith("module.") for k in obj):  # saved from a DataParallel wrapper
            obj = {k[len("module."):]: v for k, v in obj.items()}
        return obj
    return None


def is_official_state(obj) -> bool:
    """True for the authors' layout: a dict whose 'state_dict' (or the dict itself) has the official
    names (volume_encoder.*, ...). Conversion then checks every key and shape."""
    weights = _weights_of(obj)
    return weights is not None and any(k.startswith("volume_encoder.") for k in weights)


def official_layout(obj) -> str | None:
    """"se3" or "conv" (which motion decoder the official weights have), None if neither."""
    weights = _weights_of(obj) or {}
    if any(k.startswith("motion_decoder.") for k in weights):
        return "conv"
    if any(k.startswith("transform_decoder.") for k in weights):
        return "se3"
    return None


@functools.cache
def _our_shapes(model_name: str, grid: tuple[int, ...]) -> dict[str, tuple[int, ...]]:
    """Our network's state_dict shapes (built on the meta device: no memory, no initialisation cost)."""
    from dsr_bench.models.config import ModelConfig
    from dsr_bench.models.dsr_net import DSRNet

    with torch.device("meta"):
        net = DSRNet(ModelConfig.for_model(model_name, grid=grid))
    return {k: tuple(v.shape) for k, v in net.state_dict().items()}


def convert_official_state(state, model_name: str, *, grid: tuple[int, int, int] = OFFICIAL_GRID,
                           source: str = "the official weights") -> dict[str, torch.Tensor]:
    """Our `DSRNet(ModelConfig.for_model(model_name, grid=grid))` state dict from an official file's
    dict (or its bare state_dict). Every official key is mapped by `key_table` and its shape checked;
    the first unknown key, missing key or differing shape, or a file of the other motion layout, is a
    one-line UserError naming `source`. The official 3DFlow's missing mask head is filled (see the
    module's docstring). Tensors are shared with `state`, not copied."""
    if model_name not in LAYOUT:
        raise UserError(f"--model {model_name!r}: the authors released {', '.join(LAYOUT)} networks")
    weights = _weights_of(state)
    if weights is None or not is_official_state(weights):
        raise UserError(f"{source}: not the authors' DSR weights (no state_dict with volume_encoder.* keys); "
                        "pass one of the release's dsr.pth, dsr_ft.pth, single.pth, nowarp.pth, gtwarp.pth, 3dflow.pth")
    want, have = LAYOUT[model_name], official_layout(weights)
    if have is not None and have != want:
        raise UserError(f"{source} holds {_LAYOUT_WORDS[have]}, not what --model {model_name} needs; {_USE[have]}")
    shape = tuple(int(g) for g in grid)
    ours = _our_shapes(model_name, shape)
    linear = sum(1 for k in ours if k.startswith("motion_head.mlp.") and k.endswith(".weight"))
    table = dict(key_table(want, linear or 5))
    for key in weights:
        if key not in table:
            raise UserError(f"{source}: unknown key {key!r} for the official {want} layout (an edited file, or not "
                            "the authors' ModelDSR(object_num=5)); pass the release's file unmodified")
    for key in table:
        if key not in weights:
            raise UserError(f"{source}: key {key!r} is missing (a truncated or edited file); "
                            "download the release's file again")
    out: dict[str, torch.Tensor] = {}
    for key, mine in table.items():
        value = weights[key]
        if not isinstance(value, torch.Tensor):
            raise UserError(f"{source}: {key} is a {type(value).__name__}, not a tensor; pass the release's file "
                            "unmodified")
        if tuple(value.shape) != ours[mine]:
            fix = (f"the authors' networks run on the {' x '.join(map(str, OFFICIAL_GRID))} grid only"
                   if mine == "motion_head.to_vector.weight" and shape != OFFICIAL_GRID
                   else "pass the release's file unmodified (ModelDSR with object_num=5)")
            raise UserError(f"{source}: {key} has shape {tuple(value.shape)}, our {mine} needs {ours[mine]}; {fix}")
        out[mine] = value
    if want == "conv":
        slots = ours["mask_head.bias"][0]
        out["mask_head.weight"] = torch.zeros(ours["mask_head.weight"])
        bias = torch.zeros(slots)
        bias[-1] = FILLED_MASK_BIAS
        out["mask_head.bias"] = bias
    return {k: out[k] for k in ours}  # our order; exactly our keys


def read_official_file(path: Path) -> dict:
    """Load an official file (torch.load, weights_only=True, on the CPU); one-line UserError if it is
    unreadable, a dsr-bench checkpoint (those go through --checkpoint) or not the authors' layout."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"weights not found: {path}")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise UserError(f"{path}: not a loadable torch file ({type(exc).__name__}: {first[:200]})") from None
    if isinstance(obj, dict) and ("model_config" in obj or obj.get("format") == "dsr-bench-checkpoint"):
        raise UserError(f"{path} is a dsr-bench checkpoint; pass it with --checkpoint instead of --weights")
    if not is_official_state(obj):
        raise UserError(f"{path}: not the authors' DSR weights (no state_dict with volume_encoder.* keys); "
                        "pass one of the release's dsr.pth, dsr_ft.pth, single.pth, nowarp.pth, gtwarp.pth, 3dflow.pth")
    return obj


def check_release_name(path: Path, model_name: str) -> None:
    """A released file by its own name (dsr.pth ... 3dflow.pth) run as another variant is refused: the
    four SE(3) files share one layout, so only the name tells single.pth from dsr.pth."""
    stem = Path(path).stem
    meant = RELEASE_FILES.get(stem)
    if meant is not None and meant != model_name:
        raise UserError(f"{Path(path).name} is the release's {meant!r} network, not {model_name!r}; "
                        f"use --model {meant} (or rename the file to run it as another variant)")
