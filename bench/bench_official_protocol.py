"""Benchmark: what running the authors' weights faithfully changes, over the first steps of real sequences.

    python bench/bench_official_protocol.py --data DIR [--split NAME] [--sequences 12] [--steps 4]
        [--weights dsr.pth | --seed 0] [--model dsr] [--device cpu] [--json OUT.json]

The authors' weights (`--weights`, their dsr.pth ...) or, without it, a random state dict in their layout
(seeded: fan-in scaled weights, BatchNorm affine near (1, 0), running statistics near (0, 1)), written to a
temporary .pth and loaded through `load_official_predictor` as `dsr-bench predict --weights` loads it, run
over the first `--sequences` sequences of the split (consecutive, as their test.py batches them), steps
0 .. `--steps` - 1, three ways:

- faithful: the authors' warp kernel (`warp.OFFICIAL`) and their test protocol, BatchNorm over the batch of
  `--sequences` (12: theirs), what `predict --weights` does by default;
- floor warp: our kernel (`warp.FLOOR`), the same batch (`predict --weights --warp floor`);
- batch 1: the authors' kernel, BatchNorm over each sequence alone (`predict --weights --bn-batch 1`).

Per step it prints, against the faithful chain: mask agreement (% of voxels of all sequences whose predicted
slot agrees), the largest and mean motion difference (voxels), and for the faithful chain the voxels whose
target (voxel + motion) is negative on some axis (where the kernels differ), and the history step 0 hands
on (the representation warped by step 0's motion) under each kernel: its largest magnitude and the voxels
whose summed splat weight is under 1e-3 but not 0 (divided by 1e-3). Step 0 has no history, so the warp
cannot change it; BatchNorm's batch can. Without `--weights` the figures say how far the chains part
for weights of the authors' shapes and scales, not for their trained network.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path


def random_official_state(model: str, seed: int) -> dict:
    """A random state dict in the authors' layout (their names) for `model`'s network on the official grid."""
    import torch

    from dsr_bench.models import DSRNet, ModelConfig
    from dsr_bench.models.official_weights import LAYOUT, key_table

    gen = torch.Generator().manual_seed(seed)
    with torch.device("meta"):
        ours = DSRNet(ModelConfig.for_model(model)).state_dict()
    inverse = {mine: theirs for theirs, mine in key_table(LAYOUT[model])}
    out = {}
    for key, value in ours.items():
        if key not in inverse:  # our 3DFlow's mask head: the converter fills it
            continue
        shape = tuple(value.shape)
        if key.endswith("num_batches_tracked"):
            tensor = torch.tensor(1000)
        elif key.endswith("running_var"):
            tensor = torch.rand(shape, generator=gen) + 0.5
        elif len(shape) >= 2:  # conv / linear weight, fan-in scaled
            tensor = torch.randn(shape, generator=gen) * (1.0 / torch.Size(shape[1:]).numel()) ** 0.5
        elif key.endswith(("norm.weight", "bn1.weight", "bn2.weight")):
            tensor = 1 + 0.1 * torch.randn(shape, generator=gen)
        else:
            tensor = 0.1 * torch.randn(shape, generator=gen)
        out[inverse[key]] = tensor
    return {"state_dict": out}


def step0_history(net, dev, inputs: list[tuple]) -> dict:
    """Step 0 of the sequences as one batch (BatchNorm over it), its history warped by each kernel: the largest
    |value| and the voxels whose summed weight w is non-zero and under 1e-3 (negative included)."""
    import numpy as np
    import torch

    from dsr_bench.models.data import action_map
    from dsr_bench.models.dsr_net import batchnorm_statistics
    from dsr_bench.models.warp import WARP_KERNELS, forward_warp

    tsdf = torch.from_numpy(np.stack([np.asarray(i[0][0], np.float32) for i in inputs])).to(dev)
    action = torch.cat([action_map(np.asarray(i[1])[:1], tuple(net.config.grid[:2])) for i in inputs]).to(dev)
    with torch.no_grad(), batchnorm_statistics(net, batch=True):
        out = net(tsdf, action, net.initial_state(len(inputs), dev))
    fg = out["mask"][:, :-1].sum(1)
    ones = torch.ones_like(fg).unsqueeze(1)
    result = {}
    for kernel in WARP_KERNELS:
        net.set_warp_kernel(kernel)
        state = net.next_state(out)
        # a feature of ones warps to w / max(w, 1e-3) (w: the summed weight, accumulated with the feature in one
        # add): exactly 1 where w >= 1e-3, 0 where nothing landed, anything else where w is tiny or negative
        ratio = forward_warp(ones, out["motion"], fg, kernel=kernel)
        tiny = int(((ratio != 1) & (ratio != 0)).sum())
        result[kernel] = {"max_abs": float(state.abs().max()), "tiny_or_negative": tiny}
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="Dataset directory (benchmark grid).")
    parser.add_argument("--split", help="Split (default: the only one).")
    parser.add_argument("--sequences", type=int, default=12, help="Sequences, one batch (12: the authors' batch).")
    parser.add_argument("--steps", type=int, default=4, help="Steps 0 .. N-1 of each sequence.")
    parser.add_argument("--weights", type=Path, help="The authors' file (dsr.pth ...); default: random weights.")
    parser.add_argument("--model", default="dsr", help="dsr, single, nowarp, gtwarp or 3dflow.")
    parser.add_argument("--seed", type=int, default=0, help="Seed of the random weights.")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", help="Also write the figures to this JSON file.")
    args = parser.parse_args()

    import numpy as np
    import torch

    from dsr_bench.atomic import write_text
    from dsr_bench.dataset.manifest import read_split
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.models.inference import ModelPredictor, load_official_predictor
    from dsr_bench.models.warp import FLOOR, OFFICIAL

    split, names = read_split(args.data, args.split)
    names = names[: args.sequences]
    inputs = []
    for name in names:
        with SequenceReader(Path(args.data) / f"{name}.h5") as seq:
            steps = min(args.steps, seq.num_steps)
            arrays = [seq.read("tsdf", slice(0, steps)), np.asarray(seq.read("action"))[:steps]]
            if args.model == "gtwarp":
                arrays += [seq.read("scene_flow_3d", slice(0, steps)), seq.read("mask_3d", slice(0, steps))]
            inputs.append(tuple(arrays))
    with tempfile.TemporaryDirectory(prefix="dsr-bench-official-") as tmp:
        weights = args.weights
        if weights is None:
            weights = Path(tmp) / "random.pth"
            torch.save(random_official_state(args.model, args.seed), weights)
        predictor = load_official_predictor(args.model, weights, args.device)  # as `predict --weights` loads it
    net, dev = predictor.model, predictor.device

    def run(kernel: str, batch: int) -> tuple[list[dict], float]:
        net.set_warp_kernel(kernel)
        chain = ModelPredictor(net, dev, official_bn=True, bn_batch=batch)
        start = time.perf_counter()
        out = []
        for first in range(0, len(inputs), batch):
            out += chain.predict_arrays_batch(inputs[first: first + batch], source=str(args.data))
        return out, time.perf_counter() - start

    batch = len(inputs)
    history = step0_history(net, dev, inputs)
    faithful, t_faithful = run(OFFICIAL, batch)
    chains = {"floor warp": run(FLOOR, batch), "batch 1": run(OFFICIAL, 1)}
    net.set_warp_kernel(OFFICIAL)
    steps = min(len(p["mask"]) for p in faithful)
    grid = faithful[0]["mask"].shape[1:]
    coords = np.stack(np.meshgrid(*(np.arange(g) for g in grid), indexing="ij")).astype(np.float32)
    negative = [int(sum(((coords + p["motion"][t]) < 0).any(0).sum() for p in faithful)) for t in range(steps)]
    voxels = len(faithful) * int(np.prod(grid))

    source = (f"the authors' weights {args.weights.name}" if args.weights
              else f"random weights in their layout (seed {args.seed})")
    print(f"{args.model}, {source}; {len(names)} sequences of {args.data} ({split}), steps 0-{steps - 1}, "
          f"{predictor.device.type}")
    print(f"faithful (authors' warp, BatchNorm over {batch}): {t_faithful:.1f} s; voxels with a negative target "
          f"per step (of {voxels:,}): {', '.join(f'{n:,}' for n in negative)}")
    for kernel, h in history.items():
        print(f"history after step 0, {kernel} kernel: largest |value| {h['max_abs']:.4g}, voxels divided by 1e-3 "
              f"with a non-zero summed weight: {h['tiny_or_negative']:,}")
    figures: dict = {"model": args.model, "weights": source, "data": str(args.data), "split": split,
                     "sequences": names, "steps": steps, "negative_targets": negative, "voxels": voxels,
                     "history_after_step0": history, "seconds": {"faithful": t_faithful}, "against_faithful": {}}
    for label, (preds, seconds) in chains.items():
        figures["seconds"][label] = seconds
        rows = []
        for t in range(steps):
            agree = sum(int((p["mask"][t] == f["mask"][t]).sum()) for p, f in zip(preds, faithful)) / voxels
            diff = [np.abs(p["motion"][t] - f["motion"][t]) for p, f in zip(preds, faithful)]
            rows.append({"step": t, "mask_agreement_pct": 100 * agree,
                         "max_motion_diff": float(max(d.max() for d in diff)),
                         "mean_motion_diff": float(np.mean([d.mean() for d in diff]))})
        figures["against_faithful"][label] = rows
        print(f"{label} against faithful ({seconds:.1f} s):")
        for r in rows:
            print(f"  step {r['step']}: masks agree {r['mask_agreement_pct']:.3f}%, motion differs by up to "
                  f"{r['max_motion_diff']:.4g} voxels (mean {r['mean_motion_diff']:.3g})")
    if args.json:
        write_text(Path(args.json), json.dumps(figures, indent=1) + "\n")


if __name__ == "__main__":
    main()
