"""The packing line: ``line_transitions`` (every PackML transition) and ``line_state`` (mode, counters,
last stop reason and result of each cell's line).

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-24
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Create both tables; transitions are read per cell in the order they were recorded."""
    op.create_table(
        "line_transitions",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("cell", sa.String(64), nullable=False),
        sa.Column("at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("from_state", sa.Integer(), nullable=False),
        sa.Column("to_state", sa.Integer(), nullable=False),
        sa.Column("mode", sa.Integer(), nullable=False),
        sa.Column("cause", sa.Text(), nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_line_transitions"),
    )
    op.create_index("ix_line_transitions_cell_id", "line_transitions", ["cell", "id"])
    op.create_table(
        "line_state",
        sa.Column("cell", sa.String(64), nullable=False),
        sa.Column("mode", sa.Integer(), nullable=False),
        sa.Column("processed", sa.BigInteger(), nullable=False),
        sa.Column("defective", sa.BigInteger(), nullable=False),
        sa.Column("stop_reason_id", sa.Integer(), nullable=False),
        sa.Column("stop_reason", sa.Text(), nullable=False),
        sa.Column("last_result", sa.JSON(), nullable=True),
        sa.PrimaryKeyConstraint("cell", name="pk_line_state"),
    )


def downgrade() -> None:
    """Drop both tables."""
    op.drop_table("line_state")
    op.drop_table("line_transitions")
