"""A job marked ``keep``: retention (``service.retention``) never deletes it.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-24
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Add ``jobs.keep`` (false for every job so far)."""
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("keep", sa.Boolean(), nullable=False, server_default=sa.false()))


def downgrade() -> None:
    """Drop ``jobs.keep``."""
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("keep")
