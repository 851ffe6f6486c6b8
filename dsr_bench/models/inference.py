"""Running a trained model over sequences: the predictor behind `dsr-bench predict --model dsr|...`.

A predictor runs one sequence at a time, or `bn_batch` independent sequences of a split side by side
(`predict_sequences`): the authors' test protocol (their test.py) runs their weights on batches of 12
consecutive sequences of the split with BatchNorm normalising over the batch at every step, so one
sequence's predictions depend on the other 11 (`load_official_predictor`, OFFICIAL_BN_BATCH).

`load_voxel` is the voxel kind's loader (`registry.KINDS`) behind `predictors.load_predictor`, the one loader of
predictors (imported here too, where it used to live).

`dsr-bench predict` runs the shipped CPU-track networks on a CPU under `same_bits_on_any_cpu`, so that their
predictions are the same bytes on every x86-64 CPU with AVX2 (docs/models.md, "Predictions across CPUs").
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np
import torch

from dsr_bench.dataset.sequence import SequenceReader
from dsr_bench.constants import GRID_SHAPE
from dsr_bench.errors import UserError
from dsr_bench.models import registry
from dsr_bench.models.config import ModelConfig
from dsr_bench.models.dsr_net import DSRNet, batchnorm_statistics
from dsr_bench.models.labels import slot_labels
from dsr_bench.models.predictors import load_predictor  # noqa: F401  (the one loader, also found here)
from dsr_bench.models.training.checkpoints import mark_finetuned, read_weights, torch_device
from dsr_bench.models.warp import FLOOR, OFFICIAL, check_kernel

#: What each model is, in one line (predictions' meta.json, the leaderboard): `dsr_bench.models.registry`.
_DESCRIPTIONS = {name: entry.description for name, entry in registry.MODELS.items()}
#: The authors' test protocol: sequences per batch, BatchNorm normalising over the batch (their test.py's default)
OFFICIAL_BN_BATCH = 12
#: The warp kernels in words, for the predictions' meta.json (`warp.WARP_KERNELS`)
KERNEL_WORDS = {FLOOR: "floor: ours (base corner floor(p), weights in [0, 1])",
                OFFICIAL: "official: the authors' kernel (base corner int(p), truncated toward zero)"}
NO_WARP = "none (this model does not warp its history)"
#: The fast path in words, for the predictions' meta.json (`fast.FastDSRNet`)
FAST_WORDS = ("fast: BatchNorm's running statistics folded into the convs, channels_last_3d, fp32 "
              "(dsr_bench.models.fast; equal to the eager network up to rounding)")


@dataclass(frozen=True)
class _Inputs:
    """One sequence for `ModelPredictor._predict`: its steps, TSDF shape (T, Y, X, Z), the TSDF of a step,
    the actions (T, 3), the ground truth (flow, mask) of a step (read by gtwarp only), and its name."""

    steps: int
    tsdf_shape: tuple
    tsdf_at: Callable[[int], np.ndarray]
    read_actions: Callable[[], np.ndarray]
    ground_truth: Callable[[int], tuple[np.ndarray, np.ndarray]]
    source: str


def batchnorm_words(official_bn: bool, bn_batch: int = 1) -> str:
    """How BatchNorm normalised, for the predictions' meta.json."""
    if not official_bn:
        return "running statistics (eval)"
    if bn_batch == 1:
        return "batch statistics (official)"
    protocol = " (the authors' test protocol)" if bn_batch == OFFICIAL_BN_BATCH else ""
    return (f"batch statistics over {bn_batch} consecutive sequences of the split{protocol}; "
            "the last batch holds the rest")


def fast_by_default(model: DSRNet, device: torch.device, official_bn: bool, bf16: bool) -> bool:
    """Whether a predictor runs `fast.FastDSRNet` unless told: on a CPU, fp32, with BatchNorm's running statistics
    (a dsr-bench checkpoint, or the authors' weights with official_bn=False), for a network on the benchmark's full
    128 x 128 x 48 grid, where a step takes a fraction of a second and the copy pays for itself. The CPU track's
    32 x 32 x 16 networks keep the eager path: the fast path would move their predictions by rounding."""
    return (device.type == "cpu" and not official_bn and not bf16 and model.config.voxel_factor == 1
            and tuple(model.config.grid) == GRID_SHAPE)


#: threads the shipped CPU-track networks run on under `same_bits_on_any_cpu`: MKL's reproducible branch and oneDNN
#: give the same bits only for a fixed thread count (DSR-Net's differ on 3 and 8 threads, 2DFlow's on 2)
SAME_BITS_THREADS = 1


@contextmanager
def same_bits_on_any_cpu() -> Iterator[None]:
    """Run torch on `SAME_BITS_THREADS` threads, restored after. With `dsr_bench.cli.scoring.SAME_BITS_ENV` in force
    when torch loaded (MKL's reproducible branch, oneDNN's and ATen's AVX2 kernels), the shipped CPU-track networks'
    predictions are then the same bytes on every x86-64 CPU with AVX2 (tests/test_prediction_reproducibility.py);
    without it (torch loaded before), the same bytes on one machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(SAME_BITS_THREADS)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def warp_name(model: DSRNet) -> str:
    """The kernel that warps the model's history (`warp.WARP_KERNELS`), or "none" for a model that does not warp."""
    return model.warp_kernel if model.config.history in ("warp", "gtwarp") else "none"


def warp_words(model: DSRNet) -> str:
    """Which kernel warps the model's history, in words, for the predictions' meta.json."""
    return KERNEL_WORDS.get(warp_name(model), NO_WARP)


class ModelPredictor:
    """A trained network run over a sequence's steps with its state carried as in training.

    Prediction t sees observations 0..t and action t. mask: `slot_labels` of the K softmax
    channels (background, the last, -> 0; object slot k -> k + 1); motion: fp32 voxels (dy, dx, dz).

    BatchNorm normalises with its running statistics (eval mode), or with `official_bn` with each
    step's own statistics, as the official code evaluates: over the sequences run together, `bn_batch`
    of them (`predict_sequences`; `predict_split` groups a split's sequences so). Either way the model's
    running statistics are left as they are (`dsr_net.batchnorm_statistics`). The history is warped with
    the model's `warp_kernel`.

    `fast`: run the steps through `fast.FastDSRNet`, a copy of the network made at the first prediction (later
    changes to the model's weights are not seen), equal to it up to rounding (docs/models.md, "Inference speed
    on CPU"); None: on where `fast_by_default` says so."""

    #: where the weights came from (source, file, sha256, BatchNorm mode, warp kernel), set by the loaders
    weights: dict[str, str]

    def __init__(self, model: DSRNet, device: torch.device, official_bn: bool = False, bf16: bool = False,
                 bn_batch: int = 1, fast: bool | None = None):
        if bn_batch < 1:
            raise UserError(f"--bn-batch {bn_batch}: sequences per batch must be at least 1")
        self.model, self.device, self.bf16, self.official_bn = model, device, bf16, official_bn
        #: steps run through `fast.FastDSRNet` (BatchNorm folded, channels_last_3d, the restructured warp): `set_fast`
        self.fast = False
        self._runner: DSRNet | None = None
        self.set_fast(fast)
        #: sequences run side by side by `predict_split` (BatchNorm's batch when official_bn)
        self.bn_batch = bn_batch
        config = model.config
        self.name = config.name if config.voxel_factor == 1 else f"{config.name}-cpu"
        self.num_slots = config.num_slots - 1
        self.description = _DESCRIPTIONS.get(config.name, config.name) + (
            "" if config.voxel_factor == 1 else f" (CPU track: a {'x'.join(map(str, config.grid))} grid)")
        #: the grid the network works on (y, x, z), recorded in the predictions' meta.json
        self.grid = tuple(config.grid)
        model.eval()  # the statistics BatchNorm uses are chosen for each sequence (_predict)

    def set_fast(self, fast: bool | None) -> None:
        """Run the steps through `fast.FastDSRNet` (True), the network itself (False), or where `fast_by_default`
        says (None). UserError for True with batch statistics (official_bn) or bf16: only running statistics fold
        into fp32 convs."""
        if fast and (self.official_bn or self.bf16):
            raise UserError("fast inference folds BatchNorm's running statistics into fp32 convs: not with batch "
                            "statistics (the authors' protocol) or bf16; run the network as it is (fast=False)")
        self.fast = fast_by_default(self.model, self.device, self.official_bn, self.bf16) if fast is None else fast
        self._runner = None

    @property
    def runner(self) -> DSRNet:
        """The network the steps run through: the model, or with `fast` its `FastDSRNet` copy (made once, with the
        model's warp kernel at that time; made again if the kernel changes)."""
        if not self.fast:
            return self.model
        if self._runner is None or self._runner.warp_kernel != self.model.warp_kernel:
            from dsr_bench.models.fast import FastDSRNet

            self._runner = FastDSRNet.from_network(self.model)
        return self._runner

    @property
    def inference(self) -> str:
        """How the steps are run, in words, for the predictions' meta.json."""
        return FAST_WORDS if self.fast else "eager: the network as trained"

    def predict_sequence(self, seq: SequenceReader) -> dict[str, np.ndarray]:
        """{"mask": (T, Y, X, Z) uint8, "motion": (T, 3, Y, X, Z) float32} for one sequence (read step by step),
        and "motion_2d" (T, H, W, 3) float32 metres (dy, dx, dz) when it has `cameras/front/points` and the
        predictions are on the benchmark's grid: the predicted flow read at each pixel's world point over the
        predicted object voxels (`geometry.projection.flow_at_points`), as the paper scores DSR-Net in 2D."""
        return self.predict_sequences([seq])[0]

    def predict_sequences(self, seqs: list[SequenceReader]) -> list[dict[str, np.ndarray]]:
        """`predict_sequence` of several independent sequences run side by side as one batch: with
        official_bn, BatchNorm normalises over them at every step (the authors' test protocol). A sequence
        with fewer steps than the others leaves the batch after its last step."""
        from dsr_bench.geometry.projection import flow_at_points

        def inputs(seq: SequenceReader) -> _Inputs:
            steps = seq.num_steps
            return _Inputs(steps, tuple(seq.dataset("tsdf").shape), lambda t: seq.read("tsdf", t),
                           lambda: np.asarray(seq.read("action"))[:steps],
                           lambda t: (seq.read("scene_flow_3d", t), seq.read("mask_3d", t)), str(seq.path))

        outs = self._predict([inputs(seq) for seq in seqs])
        for seq, out in zip(seqs, outs):
            if "cameras/front/points" in seq and out["mask"].shape[1:] == GRID_SHAPE:
                out["motion_2d"] = np.stack([flow_at_points(out["motion"][t], out["mask"][t],
                                                            seq.read("cameras/front/points", t))
                                             for t in range(seq.num_steps)])
        return outs

    def predict_arrays(self, tsdf: np.ndarray, actions: np.ndarray, flow: np.ndarray | None = None,
                       mask: np.ndarray | None = None, source: str = "arrays") -> dict[str, np.ndarray]:
        """The same for a sequence held in memory: tsdf (T, Y, X, Z), actions (T, 3); the ground-truth
        flow (T, 3, Y, X, Z) and mask (T, Y, X, Z) are read only by the gtwarp oracle."""
        return self.predict_arrays_batch([(tsdf, actions, flow, mask)], source)[0]

    def predict_arrays_batch(self, sequences: list[tuple], source: str = "arrays") -> list[dict[str, np.ndarray]]:
        """`predict_arrays` of several sequences, each (tsdf, actions[, flow, mask]), run side by side as one
        batch (`predict_sequences`)."""
        def inputs(i: int, tsdf, actions, flow=None, mask=None) -> _Inputs:
            def ground_truth(t: int) -> tuple[np.ndarray, np.ndarray]:
                if flow is None or mask is None:
                    raise ValueError("gtwarp needs the ground-truth flow and mask (flow=, mask=)")
                return flow[t], mask[t]

            name = source if len(sequences) == 1 else f"{source}[{i}]"
            return _Inputs(len(actions), tuple(np.shape(tsdf)), lambda t: tsdf[t], lambda: np.asarray(actions),
                           ground_truth, name)

        return self._predict([inputs(i, *seq) for i, seq in enumerate(sequences)])

    @torch.no_grad()
    def _predict(self, sequences: list[_Inputs]) -> list[dict[str, np.ndarray]]:
        """The sequences' steps in order, as one batch: tsdf_at(t) and ground_truth(t) (flow, mask) read one
        step at a time. At step t the batch holds the sequences with more than t steps (a shorter one leaves
        it). A CPU-track model (`voxel_factor` > 1) sees the volumes pooled (`models.coarse`) and its
        predictions are brought back to the benchmark's grid."""
        from dsr_bench.models import coarse
        from dsr_bench.models.data import action_map, check_actions

        config = self.model.config
        grid, factor = tuple(config.grid), config.voxel_factor
        data_grid = grid if factor == 1 else GRID_SHAPE
        maps, masks, motions = [], [], []
        for seq in sequences:
            if seq.tsdf_shape[1:] != data_grid or seq.tsdf_shape[0] < seq.steps:
                raise UserError(f"{seq.source}: tsdf {seq.tsdf_shape} does not fit the model's grid {data_grid}")
            actions = seq.read_actions()
            if len(actions) != seq.steps:
                raise UserError(f"{seq.source}: {len(actions)} actions for {seq.steps} pushes; "
                                "check it with `dsr-bench validate`")
            actions = check_actions(actions, data_grid[:2], seq.source)
            maps.append(action_map(actions if factor == 1 else coarse.coarse_action(actions, factor), grid[:2]))
            masks.append(np.zeros((seq.steps,) + data_grid, dtype=np.uint8))
            motions.append(np.zeros((seq.steps, 3) + data_grid, dtype=np.float32))
        active = [i for i, seq in enumerate(sequences) if seq.steps > 0]
        state = self.model.initial_state(len(active), self.device)
        t = 0
        while active:
            volumes = [np.asarray(sequences[i].tsdf_at(t), dtype=np.float32) for i in active]
            tsdf = torch.from_numpy(np.stack([v if factor == 1 else coarse.pool_tsdf(v, factor) for v in volumes]))
            action = torch.stack([maps[i][t] for i in active]).to(self.device)
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16), \
                    batchnorm_statistics(self.model, batch=self.official_bn):
                try:
                    out = self.runner(tsdf.to(self.device), action, state)
                except ValueError as exc:  # batch statistics of a single value (a small grid at batch 1)
                    if self.official_bn and "more than 1 value per channel" in str(exc):
                        raise UserError(f"official BatchNorm (batch statistics) at batch {len(active)} needs more "
                                        f"than one value per channel, and the grid {grid} leaves one voxel in the "
                                        "SE(3) head; predict with BatchNorm in eval mode or more sequences per "
                                        "batch") from None
                    raise
            labels, motion = slot_labels(out["mask"]).cpu().numpy(), out["motion"].float().cpu().numpy()
            for row, i in enumerate(active):
                masks[i][t] = labels[row] if factor == 1 else coarse.unpool_mask(labels[row], factor)
                motions[i][t] = motion[row] if factor == 1 else coarse.unpool_motion(motion[row], factor)
            going = [row for row, i in enumerate(active) if t + 1 < sequences[i].steps]
            if going:
                if len(going) < len(active):  # a sequence ended: its row leaves the batch
                    index = torch.tensor(going, device=self.device)
                    out = {key: value.index_select(0, index) for key, value in out.items()}
                gt_flow = gt_mask = None
                if config.history == "gtwarp":
                    flows, gt_masks = [], []
                    for row in going:
                        flow, mask = sequences[active[row]].ground_truth(t)
                        if factor != 1:
                            flow, mask = coarse.pool_flow(flow, mask, factor), coarse.pool_labels(mask, factor)
                        flows.append(np.asarray(flow, np.float32))
                        gt_masks.append(np.asarray(mask, np.int64))
                    gt_flow = torch.from_numpy(np.stack(flows)).to(self.device)
                    gt_mask = torch.from_numpy(np.stack(gt_masks)).to(self.device)
                state = self.runner.next_state(out, gt_flow, gt_mask)
            active = [active[row] for row in going]
            t += 1
        return [{"mask": mask, "motion": motion} for mask, motion in zip(masks, motions)]


def load_voxel(entry: registry.ModelEntry, *, checkpoint: Path | None = None, device: str = "cpu",
               weights: Path | None = None, official_bn: bool | None = None, warp: str | None = None,
               bn_batch: int | None = None) -> ModelPredictor:
    """The voxel kind's loader (`registry.KINDS`, called by `predictors.load_predictor`): a 3D-track model from the
    authors' `weights` (their warp kernel and test protocol unless told otherwise, `load_official_predictor`), or
    from a dsr-bench weights file of any role and version of the one format (`training.checkpoints`: a run's
    last.pt, a CPU-track weights file), by default the shipped CPU-track weights: our warp kernel (`warp.FLOOR`, the
    one our models were trained with; `warp` overrides it), BatchNorm's running statistics unless `official_bn`."""
    from dsr_bench.models.predictors import weights_file

    if checkpoint is not None and weights is not None:
        raise UserError("pass either --checkpoint (a dsr-bench checkpoint) or --weights (the authors' file), not both")
    if weights is not None:
        return load_official_predictor(entry.name, Path(weights), device, True if official_bn is None else official_bn,
                                       warp=OFFICIAL if warp is None else warp,
                                       bn_batch=OFFICIAL_BN_BATCH if bn_batch is None else bn_batch)
    path, source = weights_file(entry, checkpoint)
    dev = torch_device(device)
    read = read_weights(path, dev, kind=registry.VOXEL, model=entry.name)
    net = cast(DSRNet, read.network(dev))
    net.set_warp_kernel(check_kernel(FLOOR if warp is None else warp))
    predictor = ModelPredictor(net, dev, bool(official_bn), False)
    predictor.weights = {**source, "batchnorm": batchnorm_words(bool(official_bn)), "warp": warp_words(net)}
    mark_finetuned(predictor, read)  # NAME-ft: fine-tuned on a real split (`training.finetune`)
    return predictor


def load_official_predictor(model: str, weights: Path, device: str = "cpu", official_bn: bool = True,
                            bf16: bool = False, warp: str = OFFICIAL,
                            bn_batch: int = OFFICIAL_BN_BATCH, fast: bool | None = None) -> ModelPredictor:
    """A predictor from the authors' released weights (dsr.pth, dsr_ft.pth, single.pth, nowarp.pth,
    gtwarp.pth, 3dflow.pth; `dsr_bench.models.official_weights`) on the official 128 x 128 x 48 grid, run
    as the authors ran them by default: the history warped with their kernel (`warp.OFFICIAL`, which they
    were trained with) and their test protocol, BatchNorm with batch statistics (official_bn=True) over
    `bn_batch` = 12 consecutive sequences of a split (`predict_split`; the last batch holds the rest, as
    their unshuffled DataLoader's last batch does). `warp=warp.FLOOR`, `bn_batch=1` or official_bn=False
    (running statistics) depart from it. The predictor's `weights` records the file (source, name,
    sha256), the BatchNorm mode and the warp kernel, and its description says the same. fast: `ModelPredictor`'s
    (it applies with official_bn=False only)."""
    from dsr_bench.dataset.manifest import file_sha256
    from dsr_bench.models.official_weights import check_release_name, convert_official_state, read_official_file

    dev = torch_device(device)
    weights = Path(weights)
    state = convert_official_state(read_official_file(weights), model, source=str(weights))
    check_release_name(weights, model)
    net = DSRNet(ModelConfig.for_model(model))
    net.load_state_dict(state)  # strict: the converter returns exactly our keys, shapes checked
    net.set_warp_kernel(check_kernel(warp))
    predictor = ModelPredictor(net.to(dev), dev, official_bn, bf16, bn_batch if official_bn else 1, fast=fast)
    predictor.weights = {"source": "official", "file": weights.name, "sha256": file_sha256(weights),
                         "batchnorm": batchnorm_words(official_bn, predictor.bn_batch), "warp": warp_words(net)}
    warps = warp_name(net)
    faithful = warps != FLOOR and official_bn and predictor.bn_batch == OFFICIAL_BN_BATCH
    predictor.description += (f"; the authors' released weights ({weights.name}), "
                              + ("run as the authors ran them" if faithful else "run departing from the authors' way")
                              + f": warp kernel {warps}, BatchNorm {predictor.weights['batchnorm']}")
    return predictor
