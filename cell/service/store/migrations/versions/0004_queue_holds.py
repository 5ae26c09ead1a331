"""A held queue survives a restart: ``queue_holds`` (why and since when, one row per cell).

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-30
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Create ``queue_holds``, empty: a hold of the service that ran before lived in its memory only."""
    op.create_table(
        "queue_holds",
        sa.Column("cell", sa.String(64), nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.Column("held_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("cell", name="pk_queue_holds"),
    )


def downgrade() -> None:
    """Drop ``queue_holds``."""
    op.drop_table("queue_holds")
