"""The results store's one schema (SQLAlchemy Core), the same on SQLite and PostgreSQL.

::

    experiments  1─n  plants  1─n  scans  1─n  runs  1─n  leaves
    (MIAPPE           (observation  (one         (one       plant_traits  (long: trait, value)
     investigation     unit + its    acquisition, processing  run_warnings  (what the stages said)
     + study)          material)     UTC time)    of a scan)
    trait_definitions (name, level, unit, description): the observed variables

A run is identified by ``run_key`` (its scan and recipe, ``records.run_key``):
storing it again replaces it.  Times are UTC, stored without a zone (SQLite
has none), dates as dates.  The tables are created and upgraded by the alembic
migrations in ``migrations/versions``; this module is what they build, and a
test checks that the two agree.
"""

from __future__ import annotations

from sqlalchemy import (
    JSON,
    Column,
    Date,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    MetaData,
    PrimaryKeyConstraint,
    String,
    Table,
    Text,
    UniqueConstraint,
)

NAMING = {"ix": "ix_%(column_0_label)s", "uq": "uq_%(table_name)s_%(column_0_name)s",
          "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
          "pk": "pk_%(table_name)s"}
metadata = MetaData(naming_convention=NAMING)

ID = 200  # length of identifiers (plant ids, study ids, genotypes...)
QUALITY_FLAGS = ("ok", "check", "fail")

experiments = Table(
    "experiments", metadata,
    Column("id", Integer, primary_key=True),
    Column("investigation_id", String(ID), nullable=False),
    Column("study_id", String(ID), nullable=False),
    Column("investigation_title", Text, nullable=False, default=""),
    Column("study_title", Text, nullable=False, default=""),
    Column("description", Text, nullable=False, default=""),
    Column("location", Text, nullable=False, default=""),
    Column("start_date", Date),
    Column("extra", JSON, nullable=False, default=dict),
    UniqueConstraint("investigation_id", "study_id", name="uq_experiments_study"),
)

plants = Table(
    "plants", metadata,
    Column("id", Integer, primary_key=True),
    Column("experiment_ref", ForeignKey("experiments.id", ondelete="CASCADE"), nullable=False),
    Column("plant_id", String(ID), nullable=False),
    Column("species", String(ID), nullable=False, default=""),
    Column("genotype", String(ID), nullable=False, default=""),
    Column("accession", String(ID), nullable=False, default=""),
    Column("biological_material_id", String(ID), nullable=False, default=""),
    Column("treatment", String(ID), nullable=False, default=""),
    Column("factors", JSON, nullable=False, default=dict),
    Column("replicate", Integer),
    Column("sowing_date", Date),
    Column("extra", JSON, nullable=False, default=dict),
    UniqueConstraint("experiment_ref", "plant_id", name="uq_plants_plant"),
)

scans = Table(
    "scans", metadata,
    Column("id", Integer, primary_key=True),
    Column("plant_ref", ForeignKey("plants.id", ondelete="CASCADE"), nullable=False, index=True),
    Column("scan_uid", String(64), nullable=False, unique=True),
    Column("path", Text, nullable=False),
    Column("acquired_at", DateTime, nullable=False),
    Column("protocol", String(ID), nullable=False, default=""),
    Column("views", Integer, nullable=False, default=0),
)

runs = Table(
    "runs", metadata,
    Column("id", Integer, primary_key=True),
    Column("scan_ref", ForeignKey("scans.id", ondelete="CASCADE"), nullable=False, index=True),
    Column("run_key", String(64), nullable=False, unique=True),
    Column("run_dir", Text, nullable=False, default=""),
    Column("recipe_name", String(ID), nullable=False, default=""),
    Column("recipe_hash", String(64), nullable=False),
    Column("plantscan_version", String(64), nullable=False, default=""),
    Column("plugins", JSON, nullable=False, default=dict),
    Column("provenance", JSON, nullable=False, default=dict),
    Column("quality_flag", String(8)),
    Column("quality_reasons", Text),  # why the plant is flagged: "; "-separated messages
    Column("leaf_count", Integer),
    Column("stored_at", DateTime, nullable=False),
)

leaves = Table(
    "leaves", metadata,
    Column("run_ref", ForeignKey("runs.id", ondelete="CASCADE"), nullable=False),
    Column("leaf_id", Integer, nullable=False),
    Column("length_mm", Float),
    Column("width_mm", Float),
    Column("area_mm2", Float),
    Column("perimeter_mm", Float),
    Column("thick_share", Float),
    Column("confidence", Float),
    Column("quality_flag", String(8)),
    Column("confidence_reasons", Text),  # reason codes behind a low confidence, ";"-separated
    Column("centroid_x_mm", Float),
    Column("centroid_y_mm", Float),
    Column("centroid_z_mm", Float),
    PrimaryKeyConstraint("run_ref", "leaf_id", name="pk_leaves"),
)

plant_traits = Table(
    "plant_traits", metadata,
    Column("run_ref", ForeignKey("runs.id", ondelete="CASCADE"), nullable=False),
    Column("trait", String(ID), nullable=False),
    Column("value", Float),
    PrimaryKeyConstraint("run_ref", "trait", name="pk_plant_traits"),
)

run_warnings = Table(
    "run_warnings", metadata,
    Column("id", Integer, primary_key=True),
    Column("run_ref", ForeignKey("runs.id", ondelete="CASCADE"), nullable=False, index=True),
    Column("stage", String(ID), nullable=False),
    Column("code", String(ID), nullable=False, default=""),
    Column("message", Text, nullable=False),
    Column("leaf_id", Integer),
)

trait_definitions = Table(
    "trait_definitions", metadata,
    Column("name", String(ID), primary_key=True),
    Column("level", String(16), nullable=False),
    Column("unit", String(64), nullable=False),
    Column("description", Text, nullable=False, default=""),
    Column("method", Text, nullable=False, default=""),
)

RUN_CHILDREN = (leaves, plant_traits, run_warnings)
"""Tables whose rows belong to one run (deleted with it when a run is stored again)."""
