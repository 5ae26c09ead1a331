"""Alembic environment of the job store.

It is run programmatically only, by :func:`cell.service.store.engine.open_engine`, which opens the
connection (holding PostgreSQL's migration lock), passes it in ``config.attributes["connection"]`` and
commits; there is no ``alembic.ini`` and no offline (``--sql``) mode.
"""

from __future__ import annotations

from alembic import context

from cell.service.store.models import Base

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=Base.metadata,
                  render_as_batch=connection.dialect.name == "sqlite")
with context.begin_transaction():
    context.run_migrations()
