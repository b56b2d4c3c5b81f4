"""The Parquet catalog: table schemas (declared here once), validated writes, DuckDB queries.

Layout: ``<root>/<table>/run_id=<run_id>/<writer>-<uuid>.parquet``: hive-partitioned by run, one new
file per task, never edited in place. ``run_id`` lives in the path only, and DuckDB adds it back.
"""
from __future__ import annotations

import io
import uuid
from pathlib import Path

import duckdb
import pyarrow as pa
import pyarrow.parquet as pq

from omniscs.errors import OmniscsError
from omniscs.ids import check_id
from omniscs.storage import atomic_write_bytes

SCHEMAS: dict[str, pa.Schema] = {
    "runs": pa.schema([
        pa.field("flow", pa.string(), nullable=False),
        pa.field("status", pa.string(), nullable=False),          # completed | failed
        pa.field("started_at_us", pa.int64(), nullable=False),
        pa.field("finished_at_us", pa.int64(), nullable=False),
        pa.field("n_scenes", pa.int32(), nullable=False),
        pa.field("config_json", pa.string(), nullable=False),
        pa.field("omniscs_version", pa.string(), nullable=False),
        pa.field("error", pa.string()),
    ]),
    "scenes": pa.schema([
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("source_kind", pa.string(), nullable=False),     # synthetic | store | nuscenes | ...
        pa.field("source_json", pa.string(), nullable=False),
        pa.field("template", pa.string()),
        pa.field("lighting", pa.string()),
        pa.field("seed", pa.int64()),
        pa.field("source_scene_id", pa.string()),                 # the dataset's own scene / sequence / segment id
        pa.field("dataroot", pa.string()),                        # the dataset root a recorded scene came from
        pa.field("location", pa.string()),                        # the dataset's location name, when it has one
        pa.field("path", pa.string(), nullable=False),
        pa.field("content_hash", pa.string(), nullable=False),
        pa.field("n_frames", pa.int32(), nullable=False),
        pa.field("duration_s", pa.float64(), nullable=False),
        pa.field("cameras", pa.list_(pa.string()), nullable=False),
        pa.field("n_tracks", pa.int32(), nullable=False),
        pa.field("n_moving", pa.int32(), nullable=False),
        pa.field("has_lidar", pa.bool_(), nullable=False),
        pa.field("has_gt", pa.bool_(), nullable=False),
        pa.field("reused", pa.bool_(), nullable=False),
        pa.field("ingest_seconds", pa.float64(), nullable=False),
        pa.field("preview_path", pa.string()),
    ]),
    "agents": pa.schema([
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("track_id", pa.int64(), nullable=False),
        pa.field("category", pa.string(), nullable=False),
        pa.field("source_category", pa.string()),
        pa.field("length", pa.float64(), nullable=False),
        pa.field("width", pa.float64(), nullable=False),
        pa.field("height", pa.float64(), nullable=False),
        pa.field("first_frame", pa.int32(), nullable=False),
        pa.field("last_frame", pa.int32(), nullable=False),
        pa.field("n_frames", pa.int32(), nullable=False),
        pa.field("path_length_m", pa.float64(), nullable=False),
        pa.field("max_speed_mps", pa.float64(), nullable=False),
        pa.field("moving", pa.bool_(), nullable=False),
        pa.field("frames_visible", pa.int32()),                   # frames with any visible pixel; null if unknown
        pa.field("mean_visible_pixels", pa.float64()),
        pa.field("max_visible_pixels", pa.int64()),
        pa.field("mean_lidar_points", pa.float64()),
        pa.field("min_distance_to_ego_m", pa.float64(), nullable=False),
    ]),
    "frames": pa.schema([
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("frame_idx", pa.int32(), nullable=False),
        pa.field("timestamp_us", pa.int64(), nullable=False),
        pa.field("ego_x", pa.float64(), nullable=False),
        pa.field("ego_y", pa.float64(), nullable=False),
        pa.field("ego_z", pa.float64(), nullable=False),
        pa.field("ego_yaw", pa.float64(), nullable=False),
        pa.field("ego_speed_mps", pa.float64(), nullable=False),
        pa.field("n_boxes", pa.int32(), nullable=False),
        pa.field("n_visible_agents", pa.int32()),
    ]),
    "variants": pa.schema([                                       # behaviour-level SCS variants
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("variant_id", pa.string(), nullable=False),
        pa.field("kind", pa.string(), nullable=False),            # cut_in | head_on | rear_end | t_bone | none
        pa.field("adversary", pa.int64(), nullable=False),        # track id
        pa.field("collision_step", pa.int32()),                   # step of first contact in the variant; null = none
        pa.field("collision_time_s", pa.float64()),
        pa.field("success", pa.bool_(), nullable=False),          # ego and adversary boxes overlap (IoU > 0.02)
        pa.field("plausible", pa.bool_(), nullable=False),        # comfort, no other collision, stays on the road
        pa.field("reachable", pa.bool_(), nullable=False),        # the adversary could reach the ego path at all
        pa.field("n_violations", pa.int32(), nullable=False),
        pa.field("violations", pa.list_(pa.string()), nullable=False),
        pa.field("loss_adv", pa.float64(), nullable=False),
        pa.field("loss_beh", pa.float64(), nullable=False),
        pa.field("loss_app", pa.float64()),                       # null: no renderer (scene graph) was supplied
        pa.field("loss_restore", pa.float64(), nullable=False),
        pa.field("loss_plaus", pa.float64(), nullable=False),
        pa.field("adversary_min_accel_mps2", pa.float64(), nullable=False),
        pa.field("adversary_max_accel_mps2", pa.float64(), nullable=False),
        pa.field("adversary_max_lateral_accel_mps2", pa.float64(), nullable=False),
        pa.field("min_distance_m", pa.float64(), nullable=False),
        pa.field("planner", pa.string(), nullable=False),         # replay | rule
        pa.field("iterations", pa.int32(), nullable=False),       # Adam steps of the kept attempt
        pa.field("attempts", pa.int32(), nullable=False),         # adversaries tried for this variant
        pa.field("source", pa.string()),                          # latent | knots (the interception path itself)
        pa.field("optimisation_seconds", pa.float64(), nullable=False),  # over every attempt
        pa.field("checkpoint", pa.string(), nullable=False),      # content hash (12 hex) of the traffic model
        pa.field("variants_path", pa.string(), nullable=False),   # the variants.json holding the trajectories
        pa.field("bev_path", pa.string()),
    ]),
    "plans": pa.schema([                                          # what each scene needs modelled (plan stage)
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("plan_id", pa.string(), nullable=False),         # 12 hex of the plan stage's key
        pa.field("content_hash", pa.string(), nullable=False),    # the scene store it was made for
        pa.field("agent_nodes", pa.list_(pa.int64()), nullable=False),
        pa.field("n_agent_nodes", pa.int32(), nullable=False),
        pa.field("node_reasons_json", pa.string(), nullable=False),  # track id -> moving | edited | behavior (+)
        pa.field("n_background_tracks", pa.int32(), nullable=False),
        pa.field("needs_360", pa.list_(pa.int64()), nullable=False),
        pa.field("background_repair", pa.list_(pa.int64()), nullable=False),
        pa.field("inserted", pa.list_(pa.int64()), nullable=False),
        pa.field("cameras", pa.list_(pa.string()), nullable=False),
        pa.field("n_train_frames", pa.int32(), nullable=False),
        pa.field("n_heldout_frames", pa.int32(), nullable=False),
        pa.field("modelled_area_m2", pa.float64(), nullable=False),
        pa.field("gaussian_budget", pa.int64(), nullable=False),
        pa.field("stages", pa.list_(pa.string()), nullable=False),  # the stages this scene runs
        pa.field("plan_path", pa.string(), nullable=False),
        pa.field("reused", pa.bool_(), nullable=False),
    ]),
    "models": pa.schema([                                         # fitted scene graphs (fit stage)
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("model_id", pa.string(), nullable=False),        # nsg-<preset>-<hash of scene content + config>
        pa.field("kind", pa.string(), nullable=False),            # nsg
        pa.field("preset", pa.string(), nullable=False),          # fast | balanced | accurate
        pa.field("status", pa.string(), nullable=False),          # fitted | diverged
        pa.field("checkpoint_path", pa.string()),                 # null when the fit diverged (nothing saved)
        pa.field("reused", pa.bool_(), nullable=False),           # an identical fit was already on disk
        pa.field("n_gaussians", pa.int64()),
        pa.field("n_agent_nodes", pa.int32(), nullable=False),
        pa.field("agent_nodes", pa.list_(pa.int64()), nullable=False),
        pa.field("iterations", pa.int32(), nullable=False),
        pa.field("fit_seconds", pa.float64()),
        pa.field("train_psnr", pa.float64()),
        pa.field("heldout_psnr", pa.float64()),                   # every 4th frame, full resolution
        pa.field("heldout_ssim", pa.float64()),
        pa.field("error", pa.string()),                           # why the fit diverged
    ]),
}

def catalog_root(workspace: Path) -> Path:
    return Path(workspace) / "catalog"


def validated_table(table: str, rows: list[dict]) -> pa.Table:
    """Rows as an Arrow table of the declared schema; unknown or missing required fields are errors."""
    if table not in SCHEMAS:
        raise OmniscsError(f"unknown catalog table {table!r}; tables: {sorted(SCHEMAS)}")
    schema = SCHEMAS[table]
    for i, row in enumerate(rows):
        extra = set(row) - set(schema.names)
        if extra:
            raise OmniscsError(f"catalog table {table}: row {i} has undeclared field(s) {sorted(extra)}")
        missing = [f.name for f in schema if not f.nullable and row.get(f.name) is None]
        if missing:
            raise OmniscsError(f"catalog table {table}: row {i} lacks required field(s) {missing}")
    try:
        return pa.Table.from_pylist(rows, schema=schema)
    except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError) as exc:
        raise OmniscsError(f"catalog table {table}: a row does not fit the schema ({exc})") from None


def write_rows(root: Path, table: str, run_id: str, rows: list[dict], writer: str = "task") -> Path | None:
    """Write ``rows`` as one new Parquet file in ``table``'s partition for ``run_id``; returns its path."""
    check_id("run id", run_id)
    check_id("writer", writer)
    arrow = validated_table(table, rows)
    if arrow.num_rows == 0:
        return None
    buf = io.BytesIO()
    pq.write_table(arrow, buf)
    path = Path(root) / table / f"run_id={run_id}" / f"{writer}-{uuid.uuid4().hex[:12]}.parquet"
    return atomic_write_bytes(path, buf.getvalue())


def _glob(root: Path, table: str) -> str:
    return str(Path(root) / table / "run_id=*" / "*.parquet")


def connect(root: Path) -> duckdb.DuckDBPyConnection:
    """An in-memory DuckDB connection with one view per catalog table (empty tables when no files yet)."""
    con = duckdb.connect()
    for table, schema in SCHEMAS.items():
        if any((Path(root) / table).glob("run_id=*/*.parquet")):
            con.execute(
                f"CREATE VIEW {table} AS SELECT * FROM read_parquet('{_glob(root, table)}', "
                "hive_partitioning = true, union_by_name = true)"
            )
        else:
            empty = schema.insert(0, pa.field("run_id", pa.string())).empty_table()
            con.register(f"_{table}_empty", empty)
            con.execute(f"CREATE VIEW {table} AS SELECT * FROM _{table}_empty")
    return con


def query(root: Path, sql: str) -> pa.Table:
    """Run SQL over the catalog views; a SQL mistake is reported as an OmniscsError."""
    con = connect(root)
    try:
        return con.sql(sql).to_arrow_table()
    except duckdb.Error as exc:
        first = str(exc).strip().splitlines()[0]
        raise OmniscsError(f"catalog query failed: {first}") from None
    finally:
        con.close()


def views_sql(root: str = "omniscs-data/catalog") -> str:
    """DuckDB statements that create the catalog views, for use in the duckdb shell."""
    lines = ["-- Catalog views for the duckdb shell; generated by omniscs.catalog.views_sql()."]
    for table in SCHEMAS:
        lines.append(
            f"CREATE OR REPLACE VIEW {table} AS SELECT * FROM read_parquet('{root}/{table}/run_id=*/*.parquet', "
            "hive_partitioning = true, union_by_name = true);"
        )
    return "\n".join(lines) + "\n"
