"""Indexes for the labelling app's hot queries: next unlabelled start state, a labeller's labels.

Revision ID: 0002
Revises: 0001
Create Date: 2025-01-02
"""

from __future__ import annotations

from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    """Add the composite indexes (role, id) on rope_states and (labeller_id, id) on labels."""
    op.create_index("ix_rope_states_role_id", "rope_states", ["role", "id"])
    op.create_index("ix_labels_labeller_id_id", "labels", ["labeller_id", "id"])


def downgrade() -> None:
    """Drop the composite indexes."""
    op.drop_index("ix_labels_labeller_id_id", table_name="labels")
    op.drop_index("ix_rope_states_role_id", table_name="rope_states")
