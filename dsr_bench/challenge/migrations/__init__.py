"""Alembic migrations of the challenge database (`dsr_bench.challenge.db.migrate` runs them)."""
