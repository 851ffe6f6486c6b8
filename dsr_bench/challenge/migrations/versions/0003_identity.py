"""What a host must never lose: the challenge's identity (`challenge_identity`, one row whose id is also in the
challenge directory's challenge.json, so a directory is never served with another challenge's database), and
submissions the host hid from the tables (`submissions.hidden`).

Revision ID: 0003
Revises: 0002
"""

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "challenge_identity",
        sa.Column("slot", sa.Integer, primary_key=True),
        sa.Column("challenge_id", sa.String(32), nullable=False, unique=True),
        sa.Column("bound_at", sa.DateTime, nullable=False),
        sa.Column("directory", sa.Text, nullable=False),
    )
    # a plain ALTER TABLE ... ADD COLUMN (as 0002): a batch copy would drop `submissions`, which the scores' foreign
    # keys refuse once there are any
    op.add_column("submissions", sa.Column("hidden", sa.Boolean, nullable=False, server_default=sa.false()))


def downgrade() -> None:
    with op.batch_alter_table("submissions") as batch:
        batch.drop_column("hidden")
    op.drop_table("challenge_identity")
