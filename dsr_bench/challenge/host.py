"""The host's side of a challenge directory: pinning the generated hidden set, splitting it into a public and a
private part, and exporting what participants may have.

The hidden sequences are a dataset directory (`Layout.hidden`) generated from the secret seed by
`generators.challenge`; the pins (`pins.json`) hold each sequence's scored ground-truth digests
(`dsr_bench.dataset.scored`), which every evaluation recomputes while it reads the ground truth and compares
(`expected_truth_checksum`): a hidden file changed after `create` is never scored silently.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import secrets
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from dsr_bench.challenge.layout import (CONFIG_FORMAT, DEFAULTS, HIDDEN_SPLIT, INPUTS_SPLIT, PARTS,
                                        SET_NAME_PATTERN, SIMULATED, Layout, hidden_sets, open_challenge,
                                        write_config)
from dsr_bench.errors import UserError

#: the arrays a model takes, copied into the inputs: the TSDF, the actions and each camera's colour and depth
INPUT_ARRAYS = ("tsdf", "action")
INPUT_CAMERA_ARRAYS = ("color", "depth")
#: the root attributes copied from a hidden sequence into its inputs file; the others (seeds, generator
#: arguments, objects, digests of the ground truth) are left out or blanked
INPUT_ATTRS = ("format", "schema_version", "sequence", "num_steps", "object_set", "policy", "toolkit_version",
               "grid_bounds", "grid_shape", "voxel_size", "axis_order", "flow_components", "cameras")
DIGESTS_NAME = "digests.json"


def finish_hidden_set(layout: Layout, parameters: Mapping[str, Any], public_fraction: float = 0.5) -> dict:
    """After the hidden sequences are generated into `layout.hidden` (split HIDDEN_SPLIT): draw the public part
    (`public_fraction` of them, at least one, chosen with `secrets`), write the part splits and the manifest, pin
    every sequence's scored digests and write challenge.json; returns the configuration. `parameters`: how the
    sequences were made (split, objects, steps, ...; never the seed)."""
    from dsr_bench import __version__
    from dsr_bench.atomic import write_text
    from dsr_bench.dataset.manifest import build_manifest, file_sha256, read_split, write_manifest
    from dsr_bench.dataset.scored import file_scored_digests

    if not 0.0 < public_fraction < 1.0:
        raise UserError(f"--public-fraction {public_fraction}: give a fraction between 0 and 1 (e.g. 0.5)")
    _, names = read_split(layout.hidden, HIDDEN_SPLIT)
    if len(names) < 2:
        raise UserError(f"{len(names)} hidden sequence(s): a challenge needs at least 2 (a public and a private "
                        "part); give --num-sequences 2 or more")
    parts = _draw_parts(names, public_fraction)
    for part in PARTS:
        write_text(layout.hidden / "splits" / f"{part}.txt", "".join(f"{n}\n" for n in parts[part]))
    write_manifest(layout.hidden, build_manifest(layout.hidden))
    pins = {"sequences": {name: {"scored": file_scored_digests(layout.hidden / f"{name}.h5"),
                                 "sha256": file_sha256(layout.hidden / f"{name}.h5")} for name in names}}
    write_text(layout.pins, json.dumps(pins, indent=1, sort_keys=True) + "\n")
    config = {**DEFAULTS, "format": CONFIG_FORMAT, "version": 1, **dict(parameters), "num_sequences": len(names),
              "sequences": names, **parts, "toolkit_version": __version__,
              "created": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")}
    write_config(layout, config)
    return config


def _draw_parts(names: list[str], public_fraction: float) -> dict[str, list[str]]:
    """{"public": ..., "private": ...}: `public_fraction` of `names` (at least one, at most all but one) drawn with
    `secrets` for the public part, the rest private."""
    count = min(len(names) - 1, max(1, round(len(names) * public_fraction)))
    public = sorted(secrets.SystemRandom().sample(names, count))
    return {"public": public, "private": sorted(set(names) - set(public))}


def _annotated_files(source: Path) -> list[Path]:
    """The annotated sequence files of `source` (each a file of `dsr-bench annotate --export` that a real split takes:
    complete, not flagged, passing `validate`; `dsr_bench.dataset.real_build.export_problem`), or a UserError naming
    the first that is not."""
    from dsr_bench.dataset.real_build import export_problem

    if not source.is_dir():
        raise UserError(f"{source} is not a directory; give the folder of the annotator's exports "
                        "(`dsr-bench annotate CAPTURE --export FOLDER/seq_0000.h5`)")
    files = sorted(p for p in source.glob("*.h5") if p.is_file() and not p.is_symlink())
    if len(files) < 2:
        raise UserError(f"{source} holds {len(files)} sequence file(s) (.h5); a hidden set needs at least 2 (a "
                        "public and a private part): export more annotated captures into it")
    for path in files:
        # the real track's own test (`dsr-bench real-split`): an annotated export, complete, none of its poses
        # flagged, passing validate; so the challenge hides what a real split's table would score, and nothing else
        problem = export_problem(path)
        if problem:
            raise UserError(f"{path}: {problem}")
    return files


def add_hidden_set(layout: Layout, source: str | Path, name: str = "real", public_fraction: float = 0.5) -> dict:
    """Add the annotated sequences of folder `source` (the annotator's exports: root attribute source ==
    "annotated", each passing `validate`) as the challenge's hidden set `name`: copied, as `seq_<name>_0000.h5`, ...
    (sorted by file name), into `layout.hidden_set(name)` (built beside it and renamed) with its splits and
    manifest, split at random into a public and a private part, pinned (scored digests and file SHA-256 in
    pins.json) and recorded in challenge.json; the participants' inputs (DIR/inputs) are written again to hold
    its inputs beside the simulated ones. Returns the set's entry in challenge.json."""
    from dsr_bench.atomic import atomic_directory, write_text
    from dsr_bench.dataset.manifest import build_manifest, file_sha256, write_manifest
    from dsr_bench.dataset.scored import file_scored_digests

    layout, config = open_challenge(layout.root)
    source = Path(source)
    if not SET_NAME_PATTERN.fullmatch(name) or name == SIMULATED:
        raise UserError(f"--name {name!r}: give 1-8 lower-case letters or digits, starting with a letter, other "
                        f"than {SIMULATED!r} (e.g. real)")
    if name in (config.get("hidden_sets") or {}):
        raise UserError(f"hidden set {name!r} is already in {layout.root}; give another --name")
    if not 0.0 < public_fraction < 1.0:
        raise UserError(f"--public-fraction {public_fraction}: give a fraction between 0 and 1 (e.g. 0.5)")
    files = _annotated_files(source)
    pins_all = json.loads(layout.pins.read_text())
    known = {pin["sha256"]: seq for seq, pin in pins_all["sequences"].items()}
    digests = {path: file_sha256(path) for path in files}
    for path, digest in digests.items():
        if digest in known:
            raise UserError(f"{path} is already hidden in this challenge (as {known[digest]}); give sequences that "
                            "are not in it yet")
    names = [f"seq_{name}_{i:04d}" for i in range(len(files))]  # datasets hold seq_*.h5
    target = layout.hidden_set(name)
    with atomic_directory(target, fsync=True) as tmp:  # replaces a stopped earlier run's, never in challenge.json
        (tmp / "splits").mkdir()
        for path, seq in zip(files, names):
            shutil.copyfile(path, tmp / f"{seq}.h5")
        parts = _draw_parts(names, public_fraction)
        for split, members in ((HIDDEN_SPLIT, names), *parts.items()):
            (tmp / "splits" / f"{split}.txt").write_text("".join(f"{n}\n" for n in members))
        write_manifest(tmp, build_manifest(tmp))
        _fsync_tree(tmp)
    for path, seq in zip(files, names):
        pins_all["sequences"][seq] = {"scored": file_scored_digests(target / f"{seq}.h5"), "sha256": digests[path]}
    write_text(layout.pins, json.dumps(pins_all, indent=1, sort_keys=True) + "\n")
    entry = {"source": "annotated", "sequences": names, **parts, "num_sequences": len(names),
             "files": {seq: path.name for path, seq in zip(files, names)},
             "added": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")}
    config = open_challenge(layout.root)[1]
    config["hidden_sets"] = {**(config.get("hidden_sets") or {}), name: entry}
    write_config(layout, config)  # the set exists from here on
    if layout.inputs.exists():
        refresh_inputs(layout)
    return entry


def load_pins(layout: Layout) -> dict[str, dict]:
    """{sequence: {"scored": {field: digest}, "sha256": file digest}} of the hidden set."""
    try:
        return json.loads(layout.pins.read_text())["sequences"]
    except (OSError, ValueError, KeyError) as exc:
        raise UserError(f"{layout.pins}: unreadable ({exc}); the hidden set cannot be verified") from None


def expected_truth_checksum(pins: Mapping[str, dict], names: list[str], metrics: Mapping[str, float]) -> str:
    """The `ground_truth_sha256` an evaluation of `names` with these metrics has when it scored the pinned
    hidden sequences (`dsr_bench.scoring.evaluate.scored_checksum` of the pinned digests)."""
    from dsr_bench.scoring.evaluate import scored_checksum, scored_fields

    fields = scored_fields(metrics)
    return scored_checksum({name: {f: pins[name]["scored"][f] for f in fields if f in pins[name]["scored"]}
                            for name in names})


def _input_attrs(seq) -> dict[str, Any]:
    """The root attributes of an inputs file: the sequence's public ones, the rest blanked."""
    attrs = {key: seq.attrs[key] for key in INPUT_ATTRS if key in seq.attrs}
    attrs.update({"seed": 0, "num_objects": 0, "objects": [], "generator_args": {}, "source": "challenge-inputs",
                  "challenge_inputs": 1})
    return attrs


def write_inputs_file(src: Path, dst: Path) -> None:
    """Write the inputs of hidden sequence `src` to `dst`: the TSDF, actions and each camera's colour and depth
    (world points derived from depth on reading), with the blanked attributes of `_input_attrs`; no masks, flow,
    poses, objects, 2D ground truth or seeds. A dsr-bench sequence file that `dsr-bench predict` reads."""
    from dsr_bench.dataset.sequence import DERIVED_ATTR, SequenceReader, _encode_attr, points_name
    from dsr_bench.dataset.storage import write_array

    with SequenceReader(src) as seq, h5py.File(dst, "w", track_order=True) as out:
        attrs = {**_input_attrs(seq), "sequence": Path(dst).stem}  # a renamed set's file: its name in the inputs
        for key, value in attrs.items():
            out.attrs[key] = _encode_attr(value)
        out.attrs[DERIVED_ATTR] = json.dumps([points_name(c) for c in seq.cameras])
        names = list(INPUT_ARRAYS) + [f"cameras/{c}/{a}" for c in seq.cameras for a in INPUT_CAMERA_ARRAYS]
        for name in names:
            ds = write_array(out, name, np.ascontiguousarray(seq.read(name)))
            ds.attrs["units"] = seq.dataset(name).attrs.get("units", "")


def export_inputs(layout: Layout, out: str | Path, progress: Callable[[], None] | None = None) -> Path:
    """Write the participants' inputs of every hidden sequence (of every hidden set: the simulated one's and, e.g.,
    the real captures' `seq_real_0000`, ...) to the new directory `out`: one inputs file per sequence
    (`write_inputs_file`), splits/challenge.txt listing them, and digests.json ({file: sha256}). Built in a
    temporary directory beside `out` and renamed when complete (`atomic_directory`): `out` appears whole or not at
    all."""
    from dsr_bench.atomic import atomic_directory

    out = Path(out)
    if out.exists():
        raise UserError(f"{out} exists; give a new directory to export the inputs into (or delete it)")
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_directory(out, fsync=True) as tmp:
        _write_inputs(layout, tmp, progress)
    return out


def refresh_inputs(layout: Layout) -> Path:
    """Write DIR/inputs again (after a hidden set was added): the new inputs are exported beside it and swapped in
    by two renames (`atomic_directory`: the server finds no inputs for that instant, never a mix)."""
    from dsr_bench.atomic import atomic_directory

    with atomic_directory(layout.inputs, fsync=True) as tmp:
        _write_inputs(layout, tmp)
    return layout.inputs


def _write_inputs(layout: Layout, into: Path, progress: Callable[[], None] | None = None) -> None:
    """Fill the empty directory `into` with the inputs `export_inputs` describes, flushed to the device."""
    from dsr_bench.dataset.manifest import file_sha256

    sources = {n: layout.hidden_set(hset.name) / f"{n}.h5" for hset in hidden_sets(open_challenge(layout.root)[1])
               for n in hset.sequences}
    digests = {}
    for name, source in sources.items():
        write_inputs_file(source, into / f"{name}.h5")
        digests[f"{name}.h5"] = file_sha256(into / f"{name}.h5")
        if progress:
            progress()
    (into / "splits").mkdir()
    (into / "splits" / f"{INPUTS_SPLIT}.txt").write_text("".join(f"{n}\n" for n in sources))
    (into / DIGESTS_NAME).write_text(json.dumps(digests, indent=1, sort_keys=True) + "\n")
    _fsync_tree(into)


def _fsync_tree(root: Path) -> None:
    for path in root.rglob("*"):
        if path.is_file():
            with open(path, "rb") as f:
                os.fsync(f.fileno())
