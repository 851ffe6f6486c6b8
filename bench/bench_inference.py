"""Benchmark: full-grid DSR-Net inference on the CPU, step by step as `dsr-bench predict` runs it (issue 30 part 5).

    nice -n 5 python bench/bench_inference.py --data DIR [--split NAME] [--sequences 2] [--steps 4]
        [--repeats 3] [--timed-steps 3] [--variants eager fast ...] [--threads 2] [--model dsr] [--seed 0]
        [--end-to-end] [--json OUT.json]

The network: random weights in the authors' layout on the benchmark's 128 x 128 x 48 grid at full width
(`bench_official_protocol.random_official_state`: fan-in scaled convs, BatchNorm running statistics near
(0, 1)), loaded through `official_weights.convert_official_state` and run with BatchNorm's running statistics
(eval mode, as `predict --checkpoint` runs a dsr-bench model), our warp kernel, batch 1, the state carried
from step to step. Inputs: real sequences of a dataset (read with `SequenceReader`; `--sequences` of the split
in its order, steps 0 .. `--steps` - 1).

Variants (each a network run step by step: forward, then the warped history for the next step):

- `eager`: the network as trained, fp32: the reference every other variant is compared with;
- `eager-1-thread`: the same network on one thread: how far rounding alone (another summation order in the
  convolutions) moves the eager network's own predictions, the yardstick for the others' differences;
- `channels-last`: the same with channels_last_3d weights and inputs (`DSRNet.to_channels_last`);
- `fast`: `dsr_bench.models.fast.FastDSRNet` (BatchNorm folded into the convs, channels_last_3d, the
  restructured warp): what `predict` uses on the CPU;
- `fast-jit`: `fast`'s forward through torch.jit.trace + torch.jit.freeze (TorchScript's oneDNN fusions);
- `fast-compile`: `fast`'s forward through torch.compile (inductor, freezing; compile time printed; the warp
  compiled was slower than `fast_forward_warp`, 0.25 vs 0.12-0.16 s, so it stays eager);
- `fast-bf16`: `fast` under bf16 autocast (the softmax, pivots, blending and warp stay fp32);
- `fast-1-thread`: `fast` with torch.set_num_threads(1) (the others use `--threads`);
- `onnxruntime`: `fast`'s network (BatchNorm folded, plain layout) exported to ONNX (opset 17) and run by ONNX
  Runtime's CPU provider with `--threads` threads; the warp stays `fast_forward_warp` (needs `onnx` and
  `onnxruntime`, not dependencies of dsr-bench).

Equality, per variant: every step of every sequence run as a chain (its own history), against `eager`'s chain:
the share of voxels whose predicted slot (argmax) agrees, and the largest and mean absolute difference of the
motion (voxels). Speed: `--repeats` rounds, in each every variant in turn runs `--timed-steps` steps of the
first sequence (interleaved, so a change of the shared machine's load falls on all variants alike); per
variant the median wall time of a step over all rounds (steps/s = 1 / median) and the median process CPU
time of a step (all threads; under load it counts only the time this process ran). `--end-to-end` also times
`predict_split` over the first sequence (the network saved as a dsr-bench weights file, eager and fast in turn):
reading, predicting (with the 2D flow when the data has the front camera) and writing. The machine's load average
is printed before and after: the figures mean something only next to it, and so is OMP_WAIT_POLICY: on a
shared machine OpenMP's default spin-waiting makes two threads far slower than one whenever another process holds
a core (docs/models.md, "Inference speed on CPU"); it is read when torch loads, so set it in the environment.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_official_protocol: the random weights; machine

from machine import cpu_name  # noqa: E402

VARIANTS = ("eager", "eager-1-thread", "channels-last", "fast", "fast-jit", "fast-compile", "fast-bf16",
            "fast-1-thread", "onnxruntime")


class Runner:
    """One variant: `step(tsdf, action, state) -> (outputs, next state)` with torch's thread count set around it."""

    def __init__(self, name: str, net, threads: int, bf16: bool = False):
        self.name, self.net, self.threads, self.bf16 = name, net, threads, bf16
        self.forward = net
        self.setup_seconds = 0.0

    def step(self, tsdf, action, state):
        import torch

        previous = torch.get_num_threads()
        torch.set_num_threads(self.threads)
        try:
            with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.bf16):
                out = self.forward(tsdf, action, state)
            return out, self.net.next_state(out)
        finally:
            torch.set_num_threads(previous)


class _Forward:
    """A network's forward returning a tuple (for tracing and compiling), read back as the outputs dict."""

    keys = ("mask_logits", "mask", "representation", "motion")

    def __init__(self, net):
        import torch

        class Module(torch.nn.Module):
            def __init__(self, inner):
                super().__init__()
                self.inner = inner

            def forward(self, tsdf, action, state):
                out = self.inner(tsdf, action, state)
                return tuple(out[k] for k in _Forward.keys)

        self.module = Module(net).eval()

    def wrap(self, fn):
        return lambda tsdf, action, state: dict(zip(self.keys, fn(tsdf, action, state)))


def _onnx_forward(wrapper: _Forward, fast, threads: int, example: tuple):
    """The folded network exported to ONNX and run by ONNX Runtime: (tsdf, action, state) -> outputs dict."""
    try:
        import onnxruntime as ort
    except ImportError:
        raise SystemExit("error: the onnxruntime variant needs `pip install onnx onnxruntime`") from None
    import torch

    fast.channels_last = False  # ONNX has no memory formats: export the plain layout
    with tempfile.TemporaryDirectory(prefix="dsr-bench-onnx-") as tmp, torch.no_grad():
        path = Path(tmp) / "dsr.onnx"
        torch.onnx.export(wrapper.module, example, str(path), dynamo=False, opset_version=17,
                          input_names=["tsdf", "action", "state"], output_names=list(_Forward.keys))
        options = ort.SessionOptions()
        options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])

    def forward(tsdf, action, state):
        feeds = {"tsdf": tsdf.numpy(), "action": action.numpy(), "state": state.contiguous().numpy()}
        return dict(zip(_Forward.keys, (torch.from_numpy(a) for a in session.run(None, feeds))))

    return forward


def make_runner(name: str, net, threads: int, example: tuple):
    """The variant `name` of the eval-mode network `net` (not changed); `example` (tsdf, action, state) for
    tracing and compiling."""
    import torch

    from dsr_bench.models.fast import FastDSRNet

    if name in ("eager", "eager-1-thread"):
        return Runner(name, net, 1 if name == "eager-1-thread" else threads)
    if name == "channels-last":
        return Runner(name, copy.deepcopy(net).to_channels_last(), threads)
    fast = FastDSRNet.from_network(net, onednn=name not in ("fast-compile", "onnxruntime"))  # plain convs there
    if name in ("fast", "fast-bf16", "fast-1-thread"):
        return Runner(name, fast, 1 if name == "fast-1-thread" else threads, bf16=name == "fast-bf16")
    runner = Runner(name, fast, threads)
    wrapper = _Forward(fast)
    if name == "onnxruntime":
        start = time.perf_counter()
        runner.forward = _onnx_forward(wrapper, fast, threads, example)
        runner.step(*example)
        runner.setup_seconds = time.perf_counter() - start
        return runner
    start = time.perf_counter()
    torch.set_num_threads(threads)
    with torch.no_grad():
        if name == "fast-jit":
            traced = torch.jit.freeze(torch.jit.trace(wrapper.module, example, check_trace=False, strict=False))
            runner.forward = wrapper.wrap(traced)
        elif name == "fast-compile":
            import torch._inductor.config as inductor

            inductor.freezing = True  # weights as constants: inductor folds and prepacks them for oneDNN
            compiled = torch.compile(wrapper.module, dynamic=False)
            runner.forward = wrapper.wrap(compiled)  # the warp stays `fast_forward_warp`: compiled it was slower
        else:
            raise SystemExit(f"error: unknown variant {name!r}; choose from {', '.join(VARIANTS)}")
        runner.step(*example)  # traces / compiles here
    runner.setup_seconds = time.perf_counter() - start
    return runner


def predict_split_times(net, data: str, name: str, repeats: int) -> dict[str, list]:
    """`predict_split` of sequence `name` with `net` saved as a dsr-bench weights file and loaded as `predict
    --checkpoint` loads it, eager (fast=False) and fast in turn, `repeats` times: per run the wall time per step
    and meta.json's seconds_per_step (reading and predicting, without writing)."""
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.models.predictors import load_predictor, predict_split
    from dsr_bench.models.training.checkpoints import save_weights

    with SequenceReader(Path(data) / f"{name}.h5") as seq:
        steps = seq.num_steps
    out: dict[str, list] = {"eager": [], "fast": []}
    with tempfile.TemporaryDirectory(prefix="dsr-bench-inference-") as tmp:
        weights = save_weights(Path(tmp) / "full.pt", net.config, net.state_dict(), "weights")
        predictors = {label: load_predictor(net.config.name, weights, fast=label == "fast") for label in out}
        for _ in range(repeats):
            for label, predictor in predictors.items():
                target = Path(tmp) / label
                start = time.perf_counter()
                predict_split(predictor, data, [name], target)
                wall = time.perf_counter() - start
                meta = json.loads((target / "meta.json").read_text())
                out[label].append({"wall_per_step": wall / steps, "predict_per_step": meta["seconds_per_step"]})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="Dataset directory on the benchmark's grid.")
    parser.add_argument("--split", help="Split (default: the only one).")
    parser.add_argument("--sequences", type=int, default=2, help="Sequences of the split compared for equality.")
    parser.add_argument("--steps", type=int, default=4, help="Steps 0 .. N-1 of each sequence compared.")
    parser.add_argument("--repeats", type=int, default=3, help="Timing rounds (variants interleaved in each).")
    parser.add_argument("--timed-steps", type=int, default=3, help="Steps of the first sequence timed per round.")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--threads", type=int, default=2, help="torch threads (the aim: 2 cores).")
    parser.add_argument("--model", default="dsr", help="dsr, single, nowarp or 3dflow (gtwarp needs the truth).")
    parser.add_argument("--seed", type=int, default=0, help="Seed of the random weights.")
    parser.add_argument("--end-to-end", action="store_true",
                        help="Also time `predict_split` (what `dsr-bench predict --checkpoint` runs) over the first "
                             "sequence, eager and fast in turn, `--repeats` times: reading, predicting and writing.")
    parser.add_argument("--json", help="Also write the figures to this JSON file.")
    args = parser.parse_args()
    if args.model == "gtwarp":
        raise SystemExit("error: --model gtwarp warps with the ground truth; benchmark dsr, single, nowarp or 3dflow")

    import numpy as np
    import torch

    from bench_official_protocol import random_official_state
    from dsr_bench.atomic import write_text
    from dsr_bench.dataset.manifest import read_split
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.models import DSRNet, ModelConfig
    from dsr_bench.models.data import action_map
    from dsr_bench.models.official_weights import convert_official_state

    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    split, names = read_split(args.data, args.split)
    names = names[: max(args.sequences, 1)]
    sequences = []
    for name in names:
        with SequenceReader(Path(args.data) / f"{name}.h5") as seq:
            steps = min(max(args.steps, args.timed_steps), seq.num_steps)
            tsdf = torch.from_numpy(np.asarray(seq.read("tsdf", slice(0, steps)), np.float32))
            sequences.append((tsdf, action_map(np.asarray(seq.read("action"))[:steps], tuple(tsdf.shape[1:3]))))
    with tempfile.TemporaryDirectory(prefix="dsr-bench-inference-") as tmp:  # as a .pth file would be read
        path = Path(tmp) / "random.pth"
        torch.save(random_official_state(args.model, args.seed), path)
        state = torch.load(path, weights_only=True)
    net = DSRNet(ModelConfig.for_model(args.model))
    net.load_state_dict(convert_official_state(state, args.model))
    net.eval()
    example = (sequences[0][0][:1], sequences[0][1][:1], net.initial_state(1, "cpu"))
    names_in_order = ["eager"] + [v for v in args.variants if v != "eager"]
    runners = [make_runner(v, net, args.threads, example) for v in names_in_order]

    def chain(runner: Runner, tsdf, actions, steps: int, times: list | None = None) -> list[tuple]:
        """(slot argmax, motion) of steps 0 .. steps-1, the history carried; per-step (wall, cpu) into times."""
        history, out = net.initial_state(1, "cpu"), []
        for t in range(steps):
            wall, cpu = time.perf_counter(), time.process_time()
            outputs, history = runner.step(tsdf[t: t + 1], actions[t: t + 1], history)
            if times is not None:
                times.append((time.perf_counter() - wall, time.process_time() - cpu))
            out.append((outputs["mask"].argmax(1), outputs["motion"].float()))
        return out

    equality: dict[str, dict] = {}
    reference = [chain(runners[0], tsdf, actions, min(args.steps, len(tsdf))) for tsdf, actions in sequences]
    for runner in runners[1:]:
        preds = [chain(runner, tsdf, actions, min(args.steps, len(tsdf))) for tsdf, actions in sequences]
        agree = total = 0
        worst, mean_sum, count = 0.0, 0.0, 0
        for ref_chain, pred_chain in zip(reference, preds):
            for (ref_mask, ref_motion), (mask, motion) in zip(ref_chain, pred_chain):
                agree += int((ref_mask == mask).sum())
                total += ref_mask.numel()
                diff = (ref_motion - motion).abs()
                worst, mean_sum, count = max(worst, float(diff.max())), mean_sum + float(diff.mean()), count + 1
        equality[runner.name] = {"mask_agreement_pct": 100.0 * agree / total, "motion_max_abs_diff": worst,
                                 "motion_mean_abs_diff": mean_sum / count}
    times: dict[str, list] = {runner.name: [] for runner in runners}
    tsdf, actions = sequences[0]
    for _ in range(args.repeats):
        for runner in runners:
            chain(runner, tsdf, actions, min(args.timed_steps, len(tsdf)), times[runner.name])
    end_to_end: dict[str, list] = {"eager": [], "fast": []}
    if args.end_to_end:
        end_to_end = predict_split_times(net, args.data, names[0], args.repeats)
    load_after = os.getloadavg()

    print(f"DSR-Net ({args.model}) on the 128 x 128 x 48 grid, full width, random weights in the authors' layout "
          f"(seed {args.seed}), BatchNorm running statistics, batch 1")
    print(f"machine: {cpu_name()}, {os.cpu_count()} cores, torch {torch.__version__}, {args.threads} threads, "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '(unset)')}; "
          f"load average (1, 5, 15 min) before {tuple(round(x, 2) for x in load_before)}, "
          f"after {tuple(round(x, 2) for x in load_after)}")
    print(f"equality: {len(sequences)} sequences of {args.data} ({split}), steps 0-{args.steps - 1}, chained; "
          f"timing: {args.repeats} rounds x {args.timed_steps} steps of {names[0]}, variants interleaved")
    print(f"{'variant':14s} {'steps/s':>8s} {'median s':>9s} {'cpu s':>7s} {'setup s':>8s} {'masks agree %':>14s} "
          f"{'motion max':>11s} {'motion mean':>12s}")
    rows = []
    for runner in runners:
        wall = statistics.median(t[0] for t in times[runner.name])
        cpu = statistics.median(t[1] for t in times[runner.name])
        eq = equality.get(runner.name, {"mask_agreement_pct": 100.0, "motion_max_abs_diff": 0.0,
                                        "motion_mean_abs_diff": 0.0})
        rows.append({"variant": runner.name, "steps_per_s": 1 / wall, "median_step_s": wall, "median_cpu_s": cpu,
                     "setup_s": runner.setup_seconds, "step_times_s": [t[0] for t in times[runner.name]], **eq})
        print(f"{runner.name:14s} {1 / wall:8.2f} {wall:9.3f} {cpu:7.2f} {runner.setup_seconds:8.1f} "
              f"{eq['mask_agreement_pct']:14.4f} {eq['motion_max_abs_diff']:11.3g} {eq['motion_mean_abs_diff']:12.3g}")
    for label, runs in end_to_end.items():
        if runs:
            wall = statistics.median(r["wall_per_step"] for r in runs)
            predicting = statistics.median(r["predict_per_step"] for r in runs)
            print(f"predict_split, {label}: {1 / wall:.2f} steps/s end to end ({wall:.3f} s a step, median of "
                  f"{len(runs)}), of which {predicting:.3f} s reading and predicting and {wall - predicting:.3f} s "
                  "writing the predictions")
    if args.json:
        figures = {"end_to_end": end_to_end,
                   "model": args.model, "seed": args.seed, "data": str(args.data), "split": split, "sequences": names,
                   "steps": args.steps, "repeats": args.repeats, "timed_steps": args.timed_steps,
                   "threads": args.threads, "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
                   "machine": cpu_name(), "cores": os.cpu_count(),
                   "torch": torch.__version__, "load_before": load_before, "load_after": load_after, "rows": rows}
        write_text(Path(args.json), json.dumps(figures, indent=1) + "\n")


if __name__ == "__main__":
    from dsr_bench.errors import UserError

    try:
        main()
    except UserError as exc:  # a missing dataset or split: one line, not a traceback
        raise SystemExit(f"error: {exc}") from None
