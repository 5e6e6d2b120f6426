"""The first schema: experiments, plants, scans, runs, leaves, plant traits, warnings, traits.

Revision ID: 0001
Revises:
Create Date: 2026-11-20
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

ID = 200


def upgrade() -> None:
    op.create_table(
        "experiments",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("investigation_id", sa.String(ID), nullable=False),
        sa.Column("study_id", sa.String(ID), nullable=False),
        sa.Column("investigation_title", sa.Text, nullable=False),
        sa.Column("study_title", sa.Text, nullable=False),
        sa.Column("description", sa.Text, nullable=False),
        sa.Column("location", sa.Text, nullable=False),
        sa.Column("start_date", sa.Date),
        sa.Column("extra", sa.JSON, nullable=False),
        sa.UniqueConstraint("investigation_id", "study_id", name="uq_experiments_study"),
    )
    op.create_table(
        "plants",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("experiment_ref", sa.Integer,
                  sa.ForeignKey("experiments.id", ondelete="CASCADE",
                                name="fk_plants_experiment_ref_experiments"), nullable=False),
        sa.Column("plant_id", sa.String(ID), nullable=False),
        sa.Column("species", sa.String(ID), nullable=False),
        sa.Column("genotype", sa.String(ID), nullable=False),
        sa.Column("accession", sa.String(ID), nullable=False),
        sa.Column("biological_material_id", sa.String(ID), nullable=False),
        sa.Column("treatment", sa.String(ID), nullable=False),
        sa.Column("factors", sa.JSON, nullable=False),
        sa.Column("replicate", sa.Integer),
        sa.Column("sowing_date", sa.Date),
        sa.Column("extra", sa.JSON, nullable=False),
        sa.UniqueConstraint("experiment_ref", "plant_id", name="uq_plants_plant"),
    )
    op.create_table(
        "scans",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("plant_ref", sa.Integer,
                  sa.ForeignKey("plants.id", ondelete="CASCADE",
                                name="fk_scans_plant_ref_plants"), nullable=False),
        sa.Column("scan_uid", sa.String(64), nullable=False),
        sa.Column("path", sa.Text, nullable=False),
        sa.Column("acquired_at", sa.DateTime, nullable=False),
        sa.Column("protocol", sa.String(ID), nullable=False),
        sa.Column("views", sa.Integer, nullable=False),
        sa.UniqueConstraint("scan_uid", name="uq_scans_scan_uid"),
    )
    op.create_index("ix_scans_plant_ref", "scans", ["plant_ref"])
    op.create_table(
        "runs",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("scan_ref", sa.Integer,
                  sa.ForeignKey("scans.id", ondelete="CASCADE", name="fk_runs_scan_ref_scans"),
                  nullable=False),
        sa.Column("run_key", sa.String(64), nullable=False),
        sa.Column("run_dir", sa.Text, nullable=False),
        sa.Column("recipe_name", sa.String(ID), nullable=False),
        sa.Column("recipe_hash", sa.String(64), nullable=False),
        sa.Column("plantscan_version", sa.String(64), nullable=False),
        sa.Column("plugins", sa.JSON, nullable=False),
        sa.Column("provenance", sa.JSON, nullable=False),
        sa.Column("quality_flag", sa.String(8)),
        sa.Column("leaf_count", sa.Integer),
        sa.Column("stored_at", sa.DateTime, nullable=False),
        sa.UniqueConstraint("run_key", name="uq_runs_run_key"),
    )
    op.create_index("ix_runs_scan_ref", "runs", ["scan_ref"])
    op.create_table(
        "leaves",
        sa.Column("run_ref", sa.Integer,
                  sa.ForeignKey("runs.id", ondelete="CASCADE", name="fk_leaves_run_ref_runs"),
                  nullable=False),
        sa.Column("leaf_id", sa.Integer, nullable=False),
        *(sa.Column(c, sa.Float) for c in ("length_mm", "width_mm", "area_mm2", "perimeter_mm",
                                          "thick_share", "confidence")),
        sa.Column("quality_flag", sa.String(8)),
        *(sa.Column(f"centroid_{a}_mm", sa.Float) for a in "xyz"),
        sa.PrimaryKeyConstraint("run_ref", "leaf_id", name="pk_leaves"),
    )
    op.create_table(
        "plant_traits",
        sa.Column("run_ref", sa.Integer,
                  sa.ForeignKey("runs.id", ondelete="CASCADE",
                                name="fk_plant_traits_run_ref_runs"), nullable=False),
        sa.Column("trait", sa.String(ID), nullable=False),
        sa.Column("value", sa.Float),
        sa.PrimaryKeyConstraint("run_ref", "trait", name="pk_plant_traits"),
    )
    op.create_table(
        "run_warnings",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("run_ref", sa.Integer,
                  sa.ForeignKey("runs.id", ondelete="CASCADE",
                                name="fk_run_warnings_run_ref_runs"), nullable=False),
        sa.Column("stage", sa.String(ID), nullable=False),
        sa.Column("code", sa.String(ID), nullable=False),
        sa.Column("message", sa.Text, nullable=False),
        sa.Column("leaf_id", sa.Integer),
    )
    op.create_index("ix_run_warnings_run_ref", "run_warnings", ["run_ref"])
    op.create_table(
        "trait_definitions",
        sa.Column("name", sa.String(ID), primary_key=True),
        sa.Column("level", sa.String(16), nullable=False),
        sa.Column("unit", sa.String(64), nullable=False),
        sa.Column("description", sa.Text, nullable=False),
        sa.Column("method", sa.Text, nullable=False),
    )


def downgrade() -> None:
    for table in ("trait_definitions", "run_warnings", "plant_traits", "leaves", "runs", "scans",
                  "plants", "experiments"):
        op.drop_table(table)
