"""Initial schema: labellers, demo libraries, rope states, episodes, labels, dead ends, models.

Revision ID: 0001
Revises:
Create Date: 2025-01-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: str | None = None
branch_labels = None
depends_on = None

TS = sa.DateTime(timezone=True)


def upgrade() -> None:
    """Create every table of the labelling database."""
    op.create_table(
        "demo_libraries",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("library_hash", sa.String(length=128), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=True),
        sa.Column("demo_keys", sa.JSON(), nullable=True),
        sa.Column("created_at", TS, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_demo_libraries")),
        sa.UniqueConstraint("library_hash", name=op.f("uq_demo_libraries_library_hash")),
    )
    op.create_table(
        "labellers",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("kind", sa.String(length=16), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.CheckConstraint("kind IN ('oracle', 'human')", name=op.f("ck_labellers_kind")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_labellers")),
        sa.UniqueConstraint("name", name=op.f("uq_labellers_name")),
    )
    op.create_table(
        "rope_states",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("role", sa.String(length=16), nullable=False),
        sa.Column("cloud", sa.LargeBinary(), nullable=False),
        sa.Column("rope_nodes", sa.LargeBinary(), nullable=True),
        sa.Column("task_id", sa.String(length=200), nullable=True),
        sa.Column("episode_step", sa.Integer(), nullable=True),
        sa.Column("seed", sa.Integer(), nullable=True),
        sa.Column("created_at", TS, nullable=False),
        sa.CheckConstraint(
            "role IN ('start', 'step', 'dead_end')", name=op.f("ck_rope_states_role")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_rope_states")),
    )
    op.create_table(
        "episodes",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("execution_key", sa.String(length=200), nullable=False),
        sa.Column("start_state_id", sa.Integer(), nullable=True),
        sa.Column("labeller_id", sa.Integer(), nullable=False),
        sa.Column("library_id", sa.Integer(), nullable=True),
        sa.Column("source", sa.String(length=16), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("ended_in_knot", sa.Boolean(), nullable=False),
        sa.Column("task_id", sa.String(length=200), nullable=True),
        sa.Column("metadata", sa.JSON(), nullable=False),
        sa.Column("started_at", TS, nullable=False),
        sa.Column("finished_at", TS, nullable=True),
        sa.CheckConstraint("source IN ('oracle', 'human')", name=op.f("ck_episodes_source")),
        sa.CheckConstraint(
            "status IN ('in_progress', 'completed', 'abandoned')", name=op.f("ck_episodes_status")
        ),
        sa.ForeignKeyConstraint(
            ["labeller_id"], ["labellers.id"], name=op.f("fk_episodes_labeller_id_labellers")
        ),
        sa.ForeignKeyConstraint(
            ["library_id"],
            ["demo_libraries.id"],
            name=op.f("fk_episodes_library_id_demo_libraries"),
        ),
        sa.ForeignKeyConstraint(
            ["start_state_id"],
            ["rope_states.id"],
            name=op.f("fk_episodes_start_state_id_rope_states"),
            ondelete="RESTRICT",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_episodes")),
        sa.UniqueConstraint("execution_key", name=op.f("uq_episodes_execution_key")),
    )
    op.create_index(op.f("ix_episodes_labeller_id"), "episodes", ["labeller_id"])
    op.create_index(op.f("ix_episodes_start_state_id"), "episodes", ["start_state_id"])
    op.create_table(
        "trained_models",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("version", sa.String(length=200), nullable=False),
        sa.Column("library_id", sa.Integer(), nullable=True),
        sa.Column("hyperparameters", sa.JSON(), nullable=False),
        sa.Column("feature_spec", sa.JSON(), nullable=False),
        sa.Column("params", sa.JSON(), nullable=False),
        sa.Column("metrics", sa.JSON(), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.ForeignKeyConstraint(
            ["library_id"],
            ["demo_libraries.id"],
            name=op.f("fk_trained_models_library_id_demo_libraries"),
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_trained_models")),
        sa.UniqueConstraint("version", name=op.f("uq_trained_models_version")),
    )
    op.create_table(
        "dead_end_states",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("episode_id", sa.Integer(), nullable=False),
        sa.Column("state_id", sa.Integer(), nullable=False),
        sa.Column("ordinal", sa.Integer(), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.ForeignKeyConstraint(
            ["episode_id"],
            ["episodes.id"],
            name=op.f("fk_dead_end_states_episode_id_episodes"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["state_id"], ["rope_states.id"], name=op.f("fk_dead_end_states_state_id_rope_states")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_dead_end_states")),
        sa.UniqueConstraint("episode_id", "ordinal", name="uq_dead_end_states_ordinal"),
    )
    op.create_index(op.f("ix_dead_end_states_state_id"), "dead_end_states", ["state_id"])
    op.create_table(
        "labels",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("episode_id", sa.Integer(), nullable=False),
        sa.Column("state_id", sa.Integer(), nullable=False),
        sa.Column("labeller_id", sa.Integer(), nullable=False),
        sa.Column("step_index", sa.Integer(), nullable=False),
        sa.Column("chosen_demo", sa.String(length=200), nullable=False),
        sa.Column("candidates", sa.JSON(), nullable=False),
        sa.Column("candidate_scores", sa.LargeBinary(), nullable=True),
        sa.Column("ranked_by_model", sa.String(length=200), nullable=True),
        sa.Column("outcome", sa.String(length=16), nullable=False),
        sa.Column("source", sa.String(length=16), nullable=False),
        sa.Column("labelled_at", TS, nullable=False),
        sa.CheckConstraint(
            "outcome IN ('progressed', 'knot', 'dead_end', 'misgrasp', 'skipped')",
            name=op.f("ck_labels_outcome"),
        ),
        sa.CheckConstraint("source IN ('oracle', 'human')", name=op.f("ck_labels_source")),
        sa.CheckConstraint("step_index >= 0", name=op.f("ck_labels_step_index")),
        sa.ForeignKeyConstraint(
            ["episode_id"],
            ["episodes.id"],
            name=op.f("fk_labels_episode_id_episodes"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["labeller_id"], ["labellers.id"], name=op.f("fk_labels_labeller_id_labellers")
        ),
        sa.ForeignKeyConstraint(
            ["state_id"], ["rope_states.id"], name=op.f("fk_labels_state_id_rope_states")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_labels")),
        sa.UniqueConstraint("episode_id", "step_index", name="uq_labels_episode_step"),
    )
    op.create_index(op.f("ix_labels_state_id"), "labels", ["state_id"])
    op.create_table(
        "model_arrays",
        sa.Column("model_id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=100), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(
            ["model_id"],
            ["trained_models.id"],
            name=op.f("fk_model_arrays_model_id_trained_models"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("model_id", "name", name=op.f("pk_model_arrays")),
    )
    op.create_table(
        "model_training_labels",
        sa.Column("model_id", sa.Integer(), nullable=False),
        sa.Column("label_id", sa.Integer(), nullable=False),
        sa.ForeignKeyConstraint(
            ["label_id"],
            ["labels.id"],
            name=op.f("fk_model_training_labels_label_id_labels"),
            ondelete="RESTRICT",
        ),
        sa.ForeignKeyConstraint(
            ["model_id"],
            ["trained_models.id"],
            name=op.f("fk_model_training_labels_model_id_trained_models"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("model_id", "label_id", name=op.f("pk_model_training_labels")),
    )
    op.create_index(
        op.f("ix_model_training_labels_label_id"), "model_training_labels", ["label_id"]
    )


def downgrade() -> None:
    """Drop every table (this deletes all labels: only for development)."""
    for table in (
        "model_training_labels",
        "model_arrays",
        "labels",
        "dead_end_states",
        "trained_models",
        "episodes",
        "rope_states",
        "labellers",
        "demo_libraries",
    ):
        op.drop_table(table)
