"""Alembic environment: the service passes its connection in `config.attributes["connection"]`; the `alembic`
command line (with -x url=...) works too."""

from alembic import context
from sqlalchemy import create_engine

from bench.service.db import Base, normalize_url

config = context.config
target_metadata = Base.metadata


def run(connection) -> None:
    context.configure(connection=connection, target_metadata=target_metadata,
                      render_as_batch=connection.dialect.name == "sqlite")
    with context.begin_transaction():
        context.run_migrations()


connection = config.attributes.get("connection")
if connection is not None:
    run(connection)
else:
    url = context.get_x_argument(as_dictionary=True).get("url") or config.get_main_option("sqlalchemy.url")
    with create_engine(normalize_url(url)).connect() as conn:
        run(conn)
