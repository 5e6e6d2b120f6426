"""Why to trust a number less: a leaf's confidence reasons, a plant's quality reasons.

The measurer says why a leaf's confidence is low (``traits.csv``'s
``confidence_reasons``, reason codes) and why a plant is flagged
(``plant_traits.json``'s ``quality_reasons``, messages); the store keeps both
beside the confidence and the flags it already held.  Runs stored before this
revision have neither (NULL).

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-02
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("leaves", sa.Column("confidence_reasons", sa.Text))
    op.add_column("runs", sa.Column("quality_reasons", sa.Text))


def downgrade() -> None:
    # plain ALTER TABLE ... DROP COLUMN (SQLite >= 3.35), not alembic's batch mode: its
    # copy-and-drop of ``runs`` would cascade to every leaf (foreign keys are on)
    op.drop_column("runs", "quality_reasons")
    op.drop_column("leaves", "confidence_reasons")
