"""Alembic environment for the labelling database.

The store (``labeling_db.store``) runs migrations on a connection it already holds inside a
write transaction (``config.attributes["connection"]``), so a migration is all-or-nothing on
both SQLite and PostgreSQL. Running ``alembic`` by hand with ``sqlalchemy.url`` set also works.
"""

from __future__ import annotations

from alembic import context
from sqlalchemy import create_engine

from knotlab.labeling_db.models import Base

config = context.config
target_metadata = Base.metadata


def _run(connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",
        compare_type=True,
    )
    with context.begin_transaction():
        context.run_migrations()


if context.is_offline_mode():
    context.configure(
        url=config.get_main_option("sqlalchemy.url"),
        target_metadata=target_metadata,
        literal_binds=True,
    )
    with context.begin_transaction():
        context.run_migrations()
else:
    given = config.attributes.get("connection")
    if given is not None:
        _run(given)
    else:
        engine = create_engine(config.get_main_option("sqlalchemy.url") or "")
        try:
            with engine.begin() as conn:
                _run(conn)
        finally:
            engine.dispose()
