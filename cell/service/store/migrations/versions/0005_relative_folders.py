"""A job's folder is stored relative to its cell's job folders (its name there, the job id), no longer as
an absolute path: a data dir moved or restored elsewhere keeps its jobs' files
(:class:`cell.service.store.repository.Store` resolves it in the serving data dir's ``jobs``).

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-30
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Store each folder the service made (``<data dir>/jobs/<id>``) as ``<id>``; a folder elsewhere (none
    the service makes) stays as it is."""
    op.execute("UPDATE jobs SET folder = id WHERE folder LIKE '%/jobs/' || id")


def downgrade() -> None:
    """Refused: the data dir the relative folders were in is not in the store (on PostgreSQL each cell
    has its own), so the absolute paths cannot be written back."""
    raise NotImplementedError("job folders are stored relative to each cell's data dir since revision 0005 "
                              "and cannot be made absolute again: restore a backup taken before it")
