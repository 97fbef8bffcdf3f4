"""The task of each demo library (the knot its labels are for); old rows are the overhand knot's.

Revision ID: 0003
Revises: 0002
Create Date: 2025-01-03
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Add demo_libraries.task, NOT NULL with server default 'overhand' (batch mode on SQLite)."""
    with op.batch_alter_table("demo_libraries") as batch:
        batch.add_column(
            sa.Column("task", sa.String(length=64), nullable=False, server_default="overhand")
        )


def downgrade() -> None:
    """Drop demo_libraries.task."""
    with op.batch_alter_table("demo_libraries") as batch:
        batch.drop_column("task")
