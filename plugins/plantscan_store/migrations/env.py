"""Alembic environment of the results store: migrates the connection ``Store`` hands over.

Run by ``plantscan_store.store.Store`` (never by the ``alembic`` command line, though
``alembic -x url=...`` works too: see docs/experiments.md).
"""

from __future__ import annotations

from alembic import context
from sqlalchemy import create_engine

from plantscan_store.schema import metadata

connection = context.config.attributes.get("connection")
if connection is None:  # the alembic command line: alembic -x url=sqlite:///results.sqlite
    url = context.get_x_argument(as_dictionary=True)["url"]
    with create_engine(url).begin() as connection:
        context.configure(connection=connection, target_metadata=metadata, render_as_batch=True)
        context.run_migrations()
else:
    context.configure(connection=connection, target_metadata=metadata, render_as_batch=True)
    with context.begin_transaction():
        context.run_migrations()
