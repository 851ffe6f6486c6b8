"""The real track's protocol end to end, on simulated captures whose true poses are known (issue 46).

    python scripts/real_track_evidence.py --work WORK [--fine-tune 50] [--test 100] [--seed 46000] [--epochs 20]
        [--objects procedural-novel] [--steps 10] [--models dsr single nowarp gtwarp 3dflow 2dflow se3net se3posenet]
        [--out docs/evidence/real-track.json]

1. `dsr-bench generate-captures`: two-camera captures of novel objects through the RealSense-like sensor model
   (depth noise, missing pixels, calibration error; the true poses kept aside in truth.json), as many as the parts
   need (more where an annotation is refused);
2. `dsr-bench annotate CAPTURE --place STEP0.json --auto --export`: step 0 placed at the true poses (then snapped to
   the cloud, as a person's picks would be), every later step carried and snapped by the annotator itself; every pose
   is then compared with the capture's true pose (translation mm, rotation deg up to a continuous symmetry), and the
   captures a real split refuses (an incomplete or flagged annotation) are counted and replaced;
3. `dsr-bench real-split`: the exports as a pinned split, `--fine-tune` to fine-tune on, `--test` held out, then
   `dsr-bench validate`;
4. the metrics' floor from annotation noise alone: the ground truth of the capture's true poses (exported the same
   way, the same observations) scored as predictions against the annotated test part: what a perfect model scores;
5. every model, zero-shot (the shipped CPU-track weights, trained in simulation) and fine-tuned on the fine-tune part
   (`dsr-bench train --finetune`), and the yardsticks (static, push), predicted and scored on the test part, added to a
   leaderboard of its own (WORK/leaderboard: the real track's table with its paired standard errors);
6. the sim-to-real gap: the same scenes generated as benchmark sequences (`dsr-bench generate --seed`: the same
   episodes, ideal observation, exact ground truth) scored with the same zero-shot models, paired scene by scene.

Every command is recorded as run, with its wall time; the summary (JSON) holds the counts, the pose errors, the floor,
every score with paired differences (mean and standard error over the test sequences) and the gap. Resumable: what a
step already made is reused (captures, annotations, exports, fine-tuned weights). Figures only, never asserted.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dsr_bench.cli import main as dsr_bench  # noqa: E402

MODELS_3D = ("dsr", "single", "nowarp", "gtwarp", "3dflow")
MODELS_2D = ("2dflow", "se3net", "se3posenet")
METRICS_3D = ("motion_visible", "motion_full", "iou_unordered", "iou_ordered")
COMMANDS: list[dict] = []


def run(*argv: str) -> None:
    """Run `dsr-bench ARGV` in this process, recorded with its wall time; SystemExit on a failure."""
    started = time.time()
    rc = dsr_bench([str(a) for a in argv])
    COMMANDS.append({"command": "dsr-bench " + " ".join(str(a) for a in argv), "seconds": round(time.time() - started,
                                                                                                 1), "rc": rc})
    print(f"[{time.time() - started:7.1f} s] dsr-bench {' '.join(map(str, argv))}", flush=True)
    if rc != 0:
        raise SystemExit(f"dsr-bench {' '.join(map(str, argv))} failed ({rc})")


# --- annotation --------------------------------------------------------------------------------------------------
def place_file(capture: Path, out: Path) -> Path:
    """A `--place` file of step 0 at the capture's true poses (4x4, object -> table)."""
    from dsr_bench.dataset.capture import load_capture
    from dsr_bench.geometry import pose_to_matrix

    truth = load_capture(capture).truth_poses()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"objects": {str(k + 1): pose_to_matrix(truth[0, k]).tolist()
                                           for k in range(truth.shape[1])}}))
    return out


def annotate_one(job: tuple[Path, Path, Path]) -> tuple[str | None, list[dict]]:
    """`dsr-bench annotate CAPTURE --place TRUE_POSES --auto --export EXPORT` (a worker process): None or why the
    export was refused, and the command's record."""
    capture, work, export = job
    try:
        run("annotate", capture, "--work", work / "annotation" / capture.name, "--place",
            place_file(capture, work / "annotation" / f"{capture.name}.place.json"), "--auto", "--export", export)
        return None, COMMANDS[-1:]
    except SystemExit as exc:
        return f"export refused: {exc}", COMMANDS[-1:]


def annotate_all(captures: list[Path], work: Path, exports: Path, workers: int):
    """(capture, None or why refused) for each capture, annotated in `workers` processes; the commands recorded."""
    from dsr_bench.parallel import as_finished

    for position, (outcome, commands) in as_finished(annotate_one, [(c, work, exports / f"{c.name}.h5")
                                                                    for c in captures], workers):
        if workers > 1 and len(captures) > 1:
            COMMANDS.extend(commands)
        yield captures[position], outcome


def pose_errors(capture: Path, export: Path) -> list[dict]:
    """Every exported pose against the capture's true pose: translation (mm), rotation up to a continuous symmetry
    (deg), per step and object (`bench/bench_annotate.py`'s measure)."""
    sys.path.insert(0, str(ROOT / "bench"))
    from bench_annotate import ObjectInfo, pose_errors as measure

    from dsr_bench.dataset.capture import load_capture
    from dsr_bench.dataset.sequence import SequenceReader

    cap = load_capture(capture)
    truth = cap.truth_poses()
    with SequenceReader(export) as seq:
        poses = seq.read("object_poses")
    infos = [ObjectInfo(*cap.mesh(k)) for k in range(cap.num_objects)]
    return [{"step": t, "object": cap.objects[k].name, **measure(poses[t, k], truth[t, k], infos[k])}
            for t in range(len(truth)) for k in range(cap.num_objects)]


def truth_export(capture: Path, work: Path, out: Path) -> Path:
    """The capture's ground truth from its true poses, exported as the annotator exports (the same observations,
    meshes, renderer and checks): every true pose committed as confirmed, as bench/bench_annotate_errors.py does."""
    from dsr_bench.annotator.export import export_sequence
    from dsr_bench.annotator.session import Session

    if out.is_file():
        return out
    session = Session.open(capture, work)
    try:
        truth = session.capture.truth_poses()
        session._commit("confirm", {(t, k): (truth[t, k], "confirmed", None) for t in range(len(truth))
                                    for k in range(session.num_objects)})
        return export_sequence(session, out)
    finally:
        session.close()


def truth_predictions(truth_file: Path, out: Path) -> Path:
    """A prediction file of a truth export: its amodal masks, 3D flow and front-camera 2D flow as a model's
    predictions (4 slots), named like the sequence `out` is for."""
    from dsr_bench.dataset.sequence import SequenceReader
    from dsr_bench.scoring.predictions import write_predictions

    with SequenceReader(truth_file) as seq:
        steps = seq.num_steps
        mask = seq.read("mask_3d")[:steps]
        flow = seq.read("scene_flow_3d").astype(np.float32)
        flow_2d = seq.read("cameras/front/scene_flow_2d").astype(np.float32)
    return write_predictions(out, mask, flow, num_slots=4, motion_2d=flow_2d)


# --- scores -------------------------------------------------------------------------------------------------------
def paired(a: dict, b: dict, metric: str) -> dict:
    """a - b over the sequences both scored (`per_sequence`), mean and standard error."""
    from dsr_bench.scoring.spread import paired_difference, unit_values

    d = paired_difference(unit_values(a["per_sequence"], metric), unit_values(b["per_sequence"], metric))
    return {"mean": d.mean, "se": d.se, "n": d.n}


def renamed(results: dict, names: dict[str, str]) -> dict:
    """Results whose per-sequence values are keyed by `names[sequence]` (a simulated scene -> its capture's name)."""
    return {**results, "per_sequence": {names[k]: v for k, v in results["per_sequence"].items() if k in names}}


def score(model: str, data: Path, split: str, out: Path, checkpoint: Path | None = None) -> dict:
    """`dsr-bench predict` then `evaluate --out`; the results (reused where they exist)."""
    results = out.with_suffix(".json")
    if not results.is_file():
        if out.exists():
            shutil.rmtree(out)
        run("predict", "--model", model, "--data", data, "--split", split, "--out", out,
            *(["--checkpoint", checkpoint] if checkpoint else []))
        run("evaluate", out, "--out", results)
    return json.loads(results.read_text())


def summary_of(results: dict) -> dict:
    return {k: v for k, v in results["metrics"].items() if k in (*METRICS_3D, "motion_2d")}


def main() -> None:
    args = parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    started = time.time()
    captures, exports = work / "captures", work / "exports"
    exports.mkdir(exist_ok=True)
    need = args.fine_tune + args.test
    annotated: dict[str, dict] = {}
    refused_file = work / "refused.json"  # kept across runs: a refused capture is not annotated again
    refused: dict[str, str] = json.loads(refused_file.read_text()) if refused_file.is_file() else {}
    count = need
    times = {}
    while True:  # generate and annotate until enough captures pass the real split's checks
        t0 = time.time()
        run("generate-captures", "--out", captures, "-n", count, "--objects", args.objects, "--steps", args.steps,
            "--seed", args.seed, "--noise", "realistic", "--workers", args.workers)
        times["generate-captures"] = times.get("generate-captures", 0) + time.time() - t0
        t0 = time.time()
        pending = [c for c in sorted(captures.glob("seq_*"))[:count]
                   if c.name not in annotated and c.name not in refused and not (exports / f"{c.name}.h5").is_file()]
        for capture, outcome in annotate_all(pending, work, exports, args.workers):
            if outcome is not None:
                refused[capture.name] = outcome
        for capture in sorted(captures.glob("seq_*"))[:count]:
            if capture.name in annotated or capture.name in refused:
                continue
            export = exports / f"{capture.name}.h5"
            from dsr_bench.dataset.real_build import export_problem

            problem = export_problem(export)
            if problem:
                refused[capture.name] = problem
                (work / "refused").mkdir(exist_ok=True)
                shutil.move(str(export), work / "refused" / export.name)  # kept aside: the real split refuses it
                continue
            annotated[capture.name] = {"errors": pose_errors(capture, export)}
        times["annotate"] = times.get("annotate", 0) + time.time() - t0
        refused_file.write_text(json.dumps(refused, indent=1))
        if len(annotated) >= need:
            break
        # the next round: enough new captures for what is missing at the share annotated so far (about 60%)
        share = max(0.25, len(annotated) / max(1, len(annotated) + len(refused)))
        count += int(np.ceil((need - len(annotated)) / share)) + 2
    errors = [e for a in annotated.values() for e in a["errors"]]
    trans, rot = np.array([e["translation_mm"] for e in errors]), np.array([e["rotation_deg"] for e in errors])
    gross = int(np.sum((trans > 10) | (rot > 10)))

    def spread_of(values: np.ndarray) -> dict:
        return {"mean": float(values.mean()), "median": float(np.median(values)),
                "p95": float(np.percentile(values, 95)), "max": float(values.max())}

    pose_summary = {"poses": len(errors), "translation_mm": spread_of(trans), "rotation_deg": spread_of(rot),
                    "gross (> 10 mm or 10 deg)": gross}
    print(f"poses: {len(errors)}, translation mean {trans.mean():.2f} mm (p95 {np.percentile(trans, 95):.2f}), "
          f"rotation mean {rot.mean():.2f} deg, gross {gross}; refused captures {len(refused)}", flush=True)

    # the real split (only the annotated exports that pass; the first `need` of them by name)
    usable = exports / "usable"
    if usable.exists():
        shutil.rmtree(usable)
    usable.mkdir()
    for name in sorted(annotated)[:need]:
        shutil.copyfile(exports / f"{name}.h5", usable / f"{name}.h5")
    real = work / "real"
    t0 = time.time()
    if not (real / "real_split.json").is_file():
        run("real-split", usable, "--out", real, "--fine-tune", args.fine_tune, "--test", args.test, "--seed",
            args.seed)
    run("validate", real, "--workers", args.workers)
    times["real-split + validate"] = time.time() - t0
    record = json.loads((real / "real_split.json").read_text())
    test_split, ft_split = record["parts"]["test"], record["parts"]["finetune"]
    capture_of = {seq: p["capture"] for seq, p in record["sequences"].items()}

    # the floor: the true poses' ground truth as predictions
    t0 = time.time()
    floor_dir = work / "floor" / "predictions"
    if not (work / "floor" / "results.json").is_file():
        floor_dir.mkdir(parents=True, exist_ok=True)
        for seq in record["pins"][test_split]["sequences"]:
            cap = capture_of[seq]
            truth = truth_export(captures / cap, work / "floor" / "annotation" / cap, work / "floor" / f"{cap}.h5")
            truth_predictions(truth, floor_dir / f"{seq}.h5")
        (floor_dir / "meta.json").write_text(json.dumps({"name": "true-poses", "description": "the ground truth of "
                                                         "the captures' true poses", "parameters": {}}))
        run("evaluate", floor_dir, "--data", real, "--split", test_split, "--out", work / "floor" / "results.json")
    floor = json.loads((work / "floor" / "results.json").read_text())
    oracle = score("oracle", real, test_split, work / "scores" / "oracle")
    times["floor"] = time.time() - t0

    # the models, zero-shot and fine-tuned, and the yardsticks, on the test part; their leaderboard
    board = work / "leaderboard"
    board.mkdir(exist_ok=True)
    rows: dict[str, dict] = {}
    t0 = time.time()
    for ref in ("static", "push"):
        rows[ref] = score(ref, real, test_split, work / "scores" / ref)
    times["references"] = time.time() - t0
    from dsr_bench.models.predictors import shipped_weights

    for model in args.models:
        t0 = time.time()
        rows[model] = score(model, real, test_split, work / "scores" / model)
        tuned = work / "finetuned" / f"{model}-ft.pt"
        if not tuned.is_file():
            run("train", "--finetune", "--track", "cpu", "--model", model, "--init", shipped_weights(model), "--data",
                real, "--split", ft_split, "--epochs", args.epochs, "--out", tuned, "--quiet")
        rows[f"{model}-ft"] = score(model, real, test_split, work / "scores" / f"{model}-ft", checkpoint=tuned)
        times[f"{model} (zero-shot, fine-tune, ft)"] = time.time() - t0
    on_board = {json.loads(p.read_text())["method"] for p in board.glob("entries/*.json")}
    for name in rows:
        if rows[name]["method"] not in on_board:
            run("leaderboard", "add", (work / "scores" / name).with_suffix(".json"), "--predictions",
                work / "scores" / name, "--root", board)
    readme = (board / "README.md").read_text()

    # the gap: the same scenes as simulated benchmark sequences (the captures' episodes, ideal observation)
    t0 = time.time()
    sim = work / "sim"
    test_captures = sorted(capture_of[s] for s in record["pins"][test_split]["sequences"])
    if not (sim / "manifest.json").is_file():
        last = max(int(c.split("_")[1]) for c in test_captures) + 1
        run("generate", "--objects", args.objects, "-n", last, "--steps", args.steps, "--seed", args.seed, "--out",
            sim, "--workers", args.workers)
    (sim / "splits").mkdir(exist_ok=True)
    (sim / "splits" / "sim-test.txt").write_text("".join(f"{c}\n" for c in test_captures))
    run("manifest", sim)
    same_episodes = _same_episodes(sim, captures, test_captures)
    seq_of = {c: s for s, c in capture_of.items()}
    gap = {}
    for model in ("static", *args.models):
        sim_results = score(model, sim, "sim-test", work / "scores" / f"sim-{model}")
        sim_keyed = renamed(sim_results, seq_of)
        keys = ("motion_2d",) if model in MODELS_2D else METRICS_3D
        gap[model] = {"sim": summary_of(sim_results), "real": summary_of(rows[model]),
                      "real - sim (paired by scene)": {k: paired(rows[model], sim_keyed, k) for k in keys}}
    times["sim-to-real gap"] = time.time() - t0

    scores = {}
    for name, results in rows.items():
        keys = ("motion_2d",) if name.split("-")[0] in MODELS_2D else METRICS_3D
        entry = {"method": results["method"], "metrics": summary_of(results),
                 "vs static": {k: paired(results, rows["static"], k) for k in keys},
                 "vs push": {k: paired(results, rows["push"], k) for k in keys}}
        if name.endswith("-ft"):
            entry["ft - zero-shot"] = {k: paired(results, rows[name[:-3]], k) for k in keys}
        scores[name] = entry
    out = {"issue": 46, "args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
           "command": "python " + " ".join(sys.argv), "real_split": {"parts": record["parts"], "checksums": {
               s: p["checksum"] for s, p in record["pins"].items()}},
           "captures": {"annotated": len(annotated), "refused": refused}, "pose_errors": pose_summary,
           "floor (true poses scored against the annotated test part)": summary_of(floor),
           "oracle (the annotated ground truth itself)": summary_of(oracle), "scores": scores, "sim_to_real_gap": gap,
           "same_episodes": same_episodes, "seconds": {k: round(v, 1) for k, v in times.items()},
           "total_seconds": round(time.time() - started, 1), "commands": COMMANDS, "leaderboard": readme}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1, default=float) + "\n")
    print(readme[readme.find("## "):] if "## " in readme else readme)
    print(json.dumps({k: out[k] for k in ("pose_errors", "floor (true poses scored against the annotated test part)",
                                          "seconds", "total_seconds")}, indent=1))
    print(f"wrote {args.out}")


def _same_episodes(sim: Path, captures: Path, names: list[str]) -> dict:
    """Whether each simulated sequence is its capture's episode: the largest difference of their true poses."""
    from dsr_bench.dataset.capture import load_capture
    from dsr_bench.dataset.sequence import SequenceReader

    worst = 0.0
    for name in names:
        with SequenceReader(sim / f"{name}.h5") as seq:
            poses = seq.read("object_poses")
        truth = load_capture(captures / name).truth_poses()
        worst = max(worst, float(np.abs(poses - truth).max()) if poses.shape == truth.shape else float("inf"))
    return {"max_pose_difference": worst, "same": worst < 1e-9}


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", type=Path, required=True, help="Working directory (captures, exports, runs; resumable).")
    p.add_argument("--fine-tune", type=int, default=50, help="Sequences to fine-tune on (the paper's 50).")
    p.add_argument("--test", type=int, default=100, help="Sequences held out (the paper's 100).")
    p.add_argument("--seed", type=int, default=46000, help="Base seed of the captures and of the split's draw.")
    p.add_argument("--steps", type=int, default=10, help="Pushes per capture (the paper's 10).")
    p.add_argument("--objects", default="procedural-novel", help="Object set (novel objects: procedural-novel).")
    p.add_argument("--epochs", type=int, default=20, help="Fine-tuning epochs (the paper's 20).")
    p.add_argument("--models", nargs="+", default=[*MODELS_3D, *MODELS_2D], help="Models (shipped CPU-track weights).")
    p.add_argument("--workers", type=int, default=2, help="Worker processes (generate, validate).")
    p.add_argument("--out", type=Path, default=None, help="Summary JSON (default WORK/real-track.json).")
    args = p.parse_args()
    args.out = args.out or args.work / "real-track.json"
    return args


if __name__ == "__main__":
    main()
