"""Alembic's environment: runs the migrations on the connection `dsr_bench.challenge.db.migrate` passes."""

from alembic import context

from dsr_bench.challenge.db import Base

connection = context.config.attributes.get("connection")
if connection is None:
    raise RuntimeError("run the challenge migrations through dsr_bench.challenge.db.migrate")
context.configure(connection=connection, target_metadata=Base.metadata, render_as_batch=True)
with context.begin_transaction():
    context.run_migrations()
