"""The dataset stage: a run's annotated variants gathered into one dataset (variant stores, BEVs, preview, card)
with its ``datasets``, ``samples`` and ``annotations`` rows."""
from __future__ import annotations

import json
import time
from pathlib import Path

from omniscs import catalog
from omniscs.annotate.dataset import CARD_JSON, CARD_MD, PREVIEW_PNG, assemble_dataset
from omniscs.errors import OmniscsError
from omniscs.ids import check_id
from omniscs.locks import output_lock
from omniscs.pipeline import layout
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.reuse import StageKey, produce, reusable
from omniscs.storage import atomic_write_json
from omniscs.untrusted import read_own_json

#: Bump when the code changes what the stage writes (older outputs are then not reused).
DATASET_VERSION = 1


def dataset_stage(annotated: list[StageRecord], workspace: str | Path, dataset_id: str | None = None,
                  facts: dict | None = None, reuse: bool = True, keep_failed: bool = False) -> StageRecord:
    """Gather the annotate stages' outputs of a run into ``datasets/<dataset_id>/`` (variant stores, BEVs,
    preview, card; ``omniscs.annotate.dataset``) with its ``datasets``, ``samples`` and ``annotations`` rows.
    Variants that failed the quality gates stay out unless ``keep_failed``. ``dataset_id`` defaults to
    ``ds-<key>``: the same annotated inputs give the same dataset, reused."""
    started = time.perf_counter()
    done = [r for r in annotated if r is not None and not r.skipped and r.path]
    if not done:
        raise OmniscsError("no scene of this run has annotated variants; a dataset needs at least one")
    facts = dict(facts or {})
    key = StageKey.of("dataset", DATASET_VERSION, sorted(r.key for r in done),
                      {**facts, **({"keep_failed": True} if keep_failed else {})})
    dataset_id = check_id("dataset id", dataset_id or f"ds-{key.short}")
    out = layout.dataset_folder(workspace, dataset_id)
    with output_lock(out):
        manifest = reusable(out, key) if reuse else None
        if manifest is None:
            produce(out, key, lambda tmp: _assemble(tmp, out, done, dataset_id, facts, keep_failed))
    rows = read_own_json(out / "rows.json", "the dataset is damaged; build it again", expect=dict)
    card = read_own_json(out / CARD_JSON, "the dataset card is damaged; build the dataset again", expect=dict)
    c, fid, gates = card["counts"], card["fidelity"], card["gates"]

    def mean(stat):
        return None if stat is None else stat["mean"]

    dataset_row = {"dataset_id": dataset_id, "path": str(out), "content_hash": key.digest,
                   "reused": manifest is not None, "scene_ids": sorted({r.scene_id for r in done}),
                   "n_scenes": c["scenes"], "n_variants": c["variants"], "n_frames": c["frames"],
                   "n_samples": c["images"], "n_annotations": c["annotations"], "n_ego_solved": c["ego_solved"],
                   "fidelity_psnr": mean(fid["variant_psnr"]), "fidelity_ssim": mean(fid["variant_ssim"]),
                   "fidelity_masked_psnr": mean(fid["variant_masked_psnr"]),
                   "feature_drift": mean(fid.get("variant_feature_drift")), "card_path": str(out / CARD_JSON),
                   "preview_path": str(out / PREVIEW_PNG),
                   "config_json": json.dumps(facts.get("config"), sort_keys=True, default=str),
                   "n_requested": sum(gates["requested"].values()), "n_rejected": gates["rejected_total"],
                   "n_failed_kept": gates["failed_kept"], "warnings": list(card["warnings"])}
    return StageRecord("dataset", dataset_id, str(out), reused=manifest is not None,
                       seconds=time.perf_counter() - started, key=key.digest,
                       rows={"datasets": [dataset_row], "samples": rows["samples"],
                             "annotations": rows["annotations"]},
                       info={"dataset_id": dataset_id, "counts": c, "warnings": list(card["warnings"]),
                             "gates": {k: gates[k] for k in ("requested", "produced", "rejected", "tried")}})


def _assemble(tmp: Path, final: Path, annotated: list[StageRecord], dataset_id: str, facts: dict,
              keep_failed: bool) -> dict:
    made = assemble_dataset([r.path for r in annotated], tmp, final, dataset_id, facts, keep_failed)
    atomic_write_json(tmp / "rows.json", {"samples": made["samples"], "annotations": made["annotations"]})
    return {"card": CARD_JSON, "readme": CARD_MD, "preview": PREVIEW_PNG, "rows": "rows.json"}


def catalog_dataset_stage(run_id: str, workspace: str | Path, record: StageRecord) -> list[str]:
    """The dataset's rows (``datasets``, ``samples``, ``annotations``), one new Parquet file per table."""
    root = layout.catalog_root(workspace)
    writer = f"dataset-{record.scene_id}"
    written = [catalog.write_rows(root, table, run_id, rows, writer=writer) for table, rows in record.rows.items()]
    return [str(p) for p in written if p is not None]


