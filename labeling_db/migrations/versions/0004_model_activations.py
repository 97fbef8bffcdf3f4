"""Which model is active: an append-only log of activations, the newest row wins.

Revision ID: 0004
Revises: 0003
Create Date: 2025-01-04
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Create model_activations (model_id NULL: nearest-neighbour ranking)."""
    op.create_table(
        "model_activations",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("model_id", sa.Integer(), nullable=True),
        sa.Column("reason", sa.String(length=200), nullable=False),
        sa.Column("activated_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["model_id"],
            ["trained_models.id"],
            name=op.f("fk_model_activations_model_id_trained_models"),
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_model_activations")),
    )


def downgrade() -> None:
    """Drop model_activations (the app then starts with its shipped default model again)."""
    op.drop_table("model_activations")
