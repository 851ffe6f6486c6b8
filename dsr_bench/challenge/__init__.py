"""The challenge server: a hidden test set made from a secret seed, team tokens, uploads, evaluation workers and a
live leaderboard (docs/challenge.md).

- `layout`: what a challenge directory holds, its configuration and its secret seed (never read by a route).
- `host`: pinning a generated hidden set, splitting it into public and private parts, exporting the inputs.
- `auth`: team tokens (argon2 hashes, constant-time checks) and the slowing of failed attempts.
- `db`: the database (SQLAlchemy: SQLite in WAL mode by default, PostgreSQL by URL), migrated by Alembic.
- `storage`: uploads streamed to disk under a size limit, archive members checked before anything is extracted.
- `worker`: evaluation processes that claim queued submissions, score them with `dsr_bench.scoring.evaluate` and
  keep aggregate scores only.
- `rules`: every rule in one place (names, phases and the end, the daily quota, final choices, one track), counted
  under the team's lock (`db.team_transaction`) where requests sent at once could race.
- `server`: the FastAPI app, its routers by concern in `routes/` (uploads, submissions, teams, pages, admin); `pages`
  and `team_pages`: the HTML; `client`: `dsr-bench submit`, `challenge final` and `challenge download`; `cli`: the
  commands.
- `binding`: DIR and its database bound by one id, checked before either is written; `recovery`: what a start
  recovers (strays moved aside, never deleted) and what a job leaves; `admin`: the host's hand on one submission and
  on a lost database (restore); `host_commands`: their commands and `challenge worker` (workers on other machines).

The library never imports `generators`: `dsr-bench challenge create` (which runs the simulator) lives in
`generators/challenge.py` and calls `host.finish_hidden_set` here.
"""
