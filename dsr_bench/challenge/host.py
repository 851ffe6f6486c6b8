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

from dsr_bench.challenge.layout import (CONFIG_FORMAT, DEFAULTS, HIDDEN_SPLIT, INPUTS_SPLIT, PARTS, Layout,
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
    count = min(len(names) - 1, max(1, round(len(names) * public_fraction)))
    public = sorted(secrets.SystemRandom().sample(names, count))
    parts = {"public": public, "private": sorted(set(names) - set(public))}
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
        for key, value in _input_attrs(seq).items():
            out.attrs[key] = _encode_attr(value)
        out.attrs[DERIVED_ATTR] = json.dumps([points_name(c) for c in seq.cameras])
        names = list(INPUT_ARRAYS) + [f"cameras/{c}/{a}" for c in seq.cameras for a in INPUT_CAMERA_ARRAYS]
        for name in names:
            ds = write_array(out, name, np.ascontiguousarray(seq.read(name)))
            ds.attrs["units"] = seq.dataset(name).attrs.get("units", "")


def export_inputs(layout: Layout, out: str | Path, progress: Callable[[], None] | None = None) -> Path:
    """Write the participants' inputs of every hidden sequence to the new directory `out`: one inputs file per
    sequence (`write_inputs_file`), splits/challenge.txt listing them, and digests.json ({file: sha256}). Built in a
    temporary directory beside `out` and renamed when complete: `out` appears whole or not at all."""
    from dsr_bench.dataset.manifest import file_sha256, read_split

    out = Path(out)
    if out.exists():
        raise UserError(f"{out} exists; give a new directory to export the inputs into (or delete it)")
    _, names = read_split(layout.hidden, HIDDEN_SPLIT)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{secrets.token_hex(6)}"
    tmp.mkdir()
    try:
        digests = {}
        for name in names:
            write_inputs_file(layout.hidden / f"{name}.h5", tmp / f"{name}.h5")
            digests[f"{name}.h5"] = file_sha256(tmp / f"{name}.h5")
            if progress:
                progress()
        (tmp / "splits").mkdir()
        (tmp / "splits" / f"{INPUTS_SPLIT}.txt").write_text("".join(f"{n}\n" for n in names))
        (tmp / DIGESTS_NAME).write_text(json.dumps(digests, indent=1, sort_keys=True) + "\n")
        _fsync_tree(tmp)
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _fsync_tree(root: Path) -> None:
    for path in root.rglob("*"):
        if path.is_file():
            with open(path, "rb") as f:
                os.fsync(f.fileno())
