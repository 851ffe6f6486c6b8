"""What a challenge directory holds, and its configuration.

DIR/ (mode 0700, made by `dsr-bench challenge create`):
- `secret_seed` (0600): the base seed of the hidden sequences; read by no route, written once.
- `challenge.json`: the configuration (split parameters, public and private sequence names, daily quota, upload
  limits, ranking metrics); `pins.json`: each hidden sequence's scored ground-truth digests.
- `hidden/`: the hidden sequences (a dataset directory, ground truth included; never served).
- `hidden-<name>/`: a further hidden set, e.g. real annotated captures (`challenge add-hidden-set`), its sequences
  renamed `seq_<name>_0000`, ...; challenge.json's "hidden_sets" names its sequences and parts.
- `inputs/`: what participants may download (`host.export_inputs`).
- `challenge.db`: the default SQLite database; `submissions/<id>.tar`: accepted uploads; `uploads/`: uploads being
  received (temporaries); `work/`: submissions being scored (temporaries).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dsr_bench.atomic import write_text
from dsr_bench.errors import UserError

CONFIG_FORMAT = "dsr-bench-challenge"
CONFIG_NAME, PINS_NAME, SEED_NAME = "challenge.json", "pins.json", "secret_seed"
#: the split of the hidden dataset holding every hidden sequence, and its two parts
HIDDEN_SPLIT, PARTS = "hidden", ("public", "private")
#: the generated hidden set's name; further sets (`host.add_hidden_set`) are named by the host
SIMULATED = "simulated"
#: a further hidden set's name: short (its parts' score rows are "<name>-public", "<name>-private")
SET_NAME_PATTERN = re.compile(r"[a-z][a-z0-9]{0,7}")
#: the split name of the exported inputs (participants see neither part's membership)
INPUTS_SPLIT = "challenge"
#: team and method names: shown on pages (escaped anyway) and used in no path
#: names of files a submission or the inputs may hold: flat, no separators, no leading dot
FILE_PATTERN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}")
DEFAULTS: dict[str, Any] = {
    "daily_limit": 5,  # submissions per team per UTC day
    "max_upload_bytes": 1 << 30,  # an upload's bytes, enforced while it streams
    "max_extracted_bytes": 4 << 30,  # an archive's members' bytes together, enforced while they are read
    "max_ratio": 100.0,  # extracted / uploaded bytes beyond which a compressed archive is refused (a bomb)
    "max_final": 2,  # submissions a team may select for the final ranking
    "rank_by": {"3D": "iou_ordered", "2D": "motion_2d"},
    "reveal_private": False,  # the private part's scores shown (the final ranking): set by `challenge reveal`
}


@dataclass(frozen=True)
class Layout:
    """The paths of a challenge directory `root`."""

    root: Path

    @property
    def config(self) -> Path:
        return self.root / CONFIG_NAME

    @property
    def pins(self) -> Path:
        return self.root / PINS_NAME

    @property
    def seed(self) -> Path:
        return self.root / SEED_NAME

    @property
    def hidden(self) -> Path:
        return self.root / "hidden"

    @property
    def inputs(self) -> Path:
        return self.root / "inputs"

    @property
    def submissions(self) -> Path:
        return self.root / "submissions"

    @property
    def uploads(self) -> Path:
        return self.root / "uploads"

    @property
    def work(self) -> Path:
        return self.root / "work"

    def hidden_set(self, name: str) -> Path:
        """The dataset directory of hidden set `name` (the simulated one: `hidden`)."""
        return self.hidden if name == SIMULATED else self.root / f"hidden-{name}"

    def archive(self, submission_id: str) -> Path:
        """The stored upload of a submission (its id is 32 hex digits, checked by the caller)."""
        return self.submissions / f"{submission_id}.tar"

    def default_db_url(self) -> str:
        """The embedded default database: DIR/challenge.db (SQLite)."""
        return f"sqlite:///{(self.root / 'challenge.db').absolute()}"


@dataclass(frozen=True)
class HiddenSet:
    """One hidden set of a challenge: its name, sequence names and their public and private parts, and where its
    sequences come from ("simulated", "annotated"); its dataset directory is `Layout.hidden_set(name)`."""

    name: str
    sequences: tuple[str, ...]
    public: tuple[str, ...]
    private: tuple[str, ...]
    source: str

    def part(self, part: str) -> tuple[str, ...]:
        """The sequence names of `part` ("public" or "private")."""
        return self.public if part == "public" else self.private

    def part_key(self, part: str) -> str:
        """The score rows' name of `part`: "public" / "private" for the simulated set, "<name>-public" for others."""
        return part if self.name == SIMULATED else f"{self.name}-{part}"


def hidden_sets(config: dict) -> list[HiddenSet]:
    """The challenge's hidden sets (from its configuration): the simulated one first, then the others by name."""
    sets = [HiddenSet(SIMULATED, tuple(config["sequences"]), tuple(config["public"]), tuple(config["private"]),
                      "simulated")]
    for name, entry in sorted((config.get("hidden_sets") or {}).items()):
        sets.append(HiddenSet(name, tuple(entry["sequences"]), tuple(entry["public"]), tuple(entry["private"]),
                              str(entry.get("source", ""))))
    return sets


def all_sequences(config: dict) -> list[str]:
    """Every hidden sequence's name, of every hidden set (what a submission may hold predictions of)."""
    return list(config["sequences"]) + [n for entry in (config.get("hidden_sets") or {}).values()
                                        for n in entry["sequences"]]


def part_title(key: str) -> str:
    """How a score rows' part is named on pages: "public part", "hidden set real, public part"."""
    name, _, part = key.rpartition("-")
    return f"{part} part" if not name else f"hidden set {name}, {part} part"


def open_challenge(root: str | Path) -> tuple[Layout, dict]:
    """The layout and configuration of an existing challenge directory, or a UserError naming what is missing."""
    layout = Layout(Path(root))
    if not layout.config.is_file():
        raise UserError(f"{root} is not a challenge directory (no {CONFIG_NAME}); make one with "
                        f"`dsr-bench challenge create {root} --split procedural-novel-test`")
    try:
        config = json.loads(layout.config.read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"{layout.config}: unreadable ({exc}); restore it from a backup") from None
    if config.get("format") != CONFIG_FORMAT:
        raise UserError(f"{layout.config}: not a {CONFIG_FORMAT} file; restore it from a backup")
    return layout, {**DEFAULTS, **config}


def write_config(layout: Layout, config: dict) -> None:
    """Write challenge.json atomically."""
    write_text(layout.config, json.dumps(config, indent=1, sort_keys=True) + "\n")


def write_secret_seed(layout: Layout, seed: int) -> None:
    """Write the secret seed once, readable by its owner only (0600); refuses to replace one."""
    try:
        fd = os.open(layout.seed, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise UserError(f"{layout.seed} exists: {layout.root} already holds a challenge; choose another DIR") from None
    with os.fdopen(fd, "w") as f:
        f.write(f"{seed}\n")
        f.flush()
        os.fsync(f.fileno())
