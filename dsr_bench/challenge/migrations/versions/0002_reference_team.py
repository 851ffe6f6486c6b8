"""Reference rows scored by the server: a team flagged `reference` holds the host's reference submissions
(`dsr-bench challenge add-references`); it has no usable token and is never ranked.

Revision ID: 0002
Revises: 0001
"""

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # a plain ALTER TABLE ... ADD COLUMN (SQLite has it): a batch copy would drop `teams`, which the submissions'
    # foreign keys refuse once there are any
    op.add_column("teams", sa.Column("reference", sa.Boolean, nullable=False, server_default=sa.false()))


def downgrade() -> None:
    with op.batch_alter_table("teams") as batch:
        batch.drop_column("reference")
