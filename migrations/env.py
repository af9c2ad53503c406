"""Alembic environment. The service passes its open connection in ``config.attributes``;
from the command line the URL comes from the same settings as the service."""

from __future__ import annotations

from alembic import context

from services.db.models import Base

target_metadata = Base.metadata


def _run(connection) -> None:
    context.configure(connection=connection, target_metadata=target_metadata, render_as_batch=True)
    with context.begin_transaction():
        context.run_migrations()


connection = context.config.attributes.get("connection")
if connection is not None:
    _run(connection)
else:
    from services.db.engine import make_engine
    from services.settings import Settings

    engine = make_engine(Settings().sqlalchemy_url)
    with engine.begin() as conn:
        _run(conn)
