"""Reference rows scored on the hidden set by the server itself (`dsr-bench challenge add-references`).

The host's reference models (the static yardstick, predicting no motion; the push yardstick; the CPU-track
learned models whose weights ship with the toolkit) predict on the challenge's inputs (every hidden set's, as
`export-inputs` writes them for participants: observations and actions only), and their predictions are stored
as submissions of the challenge's reference team (a team flagged `reference`: no usable token, never ranked), so
the same workers score them as they score the teams', part by part. The leaderboard shows each model's newest
scored one as a reference row: the public part's scores during the challenge, the private part's once revealed.
"""

from __future__ import annotations

import os
import secrets
import shutil
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import sessionmaker

from dsr_bench.challenge import auth
from dsr_bench.challenge.db import Submission, Team, utcnow
from dsr_bench.challenge.layout import INPUTS_SPLIT, Layout, all_sequences
from dsr_bench.errors import UserError

#: the reference team's name on no page (its rows are shown as reference rows); a team of that name is refused
REFERENCE_TEAM = "(reference rows)"
DEFAULT_MODELS = ("static",)
#: models that read the ground truth, which the inputs do not hold (and which would score themselves perfect)
GROUND_TRUTH_MODELS = ("oracle", "gtwarp")


def check_models(models: Sequence[str]) -> list[str]:
    """The reference models named (deduplicated, in order), or a UserError naming the first one that cannot be a
    reference row here: unknown, reading the ground truth, or a learned model without shipped CPU-track weights."""
    from dsr_bench.models import registry
    from dsr_bench.models.predictors import shipped_weights

    chosen = list(dict.fromkeys(m.strip() for m in models if m.strip()))
    if not chosen:
        raise UserError("--models is empty; give e.g. --models static,push")
    for model in chosen:
        if model not in registry.names():
            raise UserError(f"--models {model!r}: not a model; choose from {', '.join(registry.names())}")
        if model in GROUND_TRUTH_MODELS:
            raise UserError(f"--models {model!r} reads the ground truth, which the challenge's inputs do not hold; "
                            "choose static, push or a learned model")
        if registry.model_entry(model).kind != registry.REFERENCE and shipped_weights(model) is None:
            raise UserError(f"--models {model!r}: no shipped CPU-track weights for it; choose static, push or a "
                            "model with weights under dsr_bench/models/weights/cpu-track")
    return chosen


def reference_team(session_factory: sessionmaker) -> int:
    """The id of the challenge's reference team, made on first use (a random token that nobody is given, revoked at
    once: it can never sign in)."""
    with session_factory.begin() as session:
        team = session.scalar(select(Team).where(Team.name == REFERENCE_TEAM))
        if team is not None and not team.reference:
            raise UserError(f"a team named {REFERENCE_TEAM!r} exists; revoke it (`challenge revoke-team`) and add "
                            "it under another name before adding reference rows")
        if team is None:
            key, token = auth.new_token()
            team = Team(name=REFERENCE_TEAM, key=key, token_hash=auth.hash_token(token), created_at=utcnow(),
                        revoked_at=utcnow(), reference=True)
            session.add(team)
            session.flush()
        return team.id


def store_reference(layout: Layout, session_factory: sessionmaker, team_id: int, method: str, archive: Path,
                    config: dict) -> str:
    """Check the archive of a reference model's predictions as an upload is checked, move it into
    submissions/<id>.tar and queue it (its row written last); returns the submission's id."""
    from dsr_bench.atomic import fsync_path
    from dsr_bench.challenge.storage import check_archive
    from dsr_bench.dataset.manifest import file_sha256

    allowed = {f"{name}.h5" for name in all_sequences(config)} | {"meta.json"}
    problems = check_archive(archive, allowed, int(config["max_extracted_bytes"]), float(config["max_ratio"]))
    if problems:
        raise UserError(f"reference {method}: {problems[0]}")
    sid = secrets.token_hex(16)
    layout.submissions.mkdir(parents=True, exist_ok=True)
    target = layout.archive(sid)
    with open(archive, "rb") as f:
        os.fsync(f.fileno())
    os.rename(archive, target)
    fsync_path(layout.submissions)
    try:
        with session_factory.begin() as session:
            session.add(Submission(id=sid, team_id=team_id, method=method, phase=None, state="queued",
                                   created_at=utcnow(), attempts=0, archive_sha256=file_sha256(target),
                                   archive_bytes=target.stat().st_size, messages="[]", final=False, rescore=False))
    except BaseException:
        target.unlink(missing_ok=True)
        raise
    return sid


def add_references(layout: Layout, config: dict, session_factory: sessionmaker, models: Sequence[str],
                   echo: Callable[[str], None] = lambda line: None) -> dict[str, str]:
    """Predict with each reference model on the challenge's inputs (exported afresh from every hidden set into a
    temporary folder: what participants get) and queue the predictions for the server's workers as reference
    submissions; returns {model: submission id}."""
    from dsr_bench.challenge.client import pack
    from dsr_bench.challenge.host import export_inputs
    from dsr_bench.models.predictors import load_predictor, predict_split

    chosen = check_models(models)
    team_id = reference_team(session_factory)
    queued: dict[str, str] = {}
    # beside submissions/ (one file system: the archive is renamed into it), not in work/ (a starting server
    # empties that)
    tmp = Path(tempfile.mkdtemp(prefix=".references-", dir=layout.root))
    try:
        inputs = export_inputs(layout, tmp / "inputs")
        names = (inputs / "splits" / f"{INPUTS_SPLIT}.txt").read_text().split()
        for model in chosen:
            echo(f"{model}: predicting {len(names)} sequences")
            predict_split(load_predictor(model), inputs, names, tmp / model)
            pack(tmp / model, tmp / f"{model}.tar")
            queued[model] = store_reference(layout, session_factory, team_id, model, tmp / f"{model}.tar", config)
            shutil.rmtree(tmp / model, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return queued
