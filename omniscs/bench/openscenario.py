"""The OpenSCENARIO step of ``omniscs bench dataset``: every variant store the benchmark annotated is exported as
``.xosc`` + ``.xodr`` (``omniscs.export.openscenario``), ASAM's checkers run on every file (their versions and issue
counts reported), and each scenario is read back and compared with its store (the round trip: largest box-centre,
rotation and time difference over every track and frame). Written as ``reports/dataset/openscenario.json`` and
``.md``."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from omniscs.bench.harness import write_report
from omniscs.errors import OmniscsError
from omniscs.export import export_scenes
from omniscs.export.asam_checks import check_file, checker_versions
from omniscs.export.opendrive import road_network_of
from omniscs.export.openscenario import OpenScenarioConfig, check_on_network, read_scenario, scenario_entities
from omniscs.geometry import rotmat_from_euler
from omniscs.scene import load_scene

#: The part of the dataset benchmark's report folder this step writes.
PART = "openscenario"
#: The issue's round-trip tolerance on positions (metres).
ROUND_TRIP_M = 0.01


def round_trip(store: Path, xosc: Path, config: OpenScenarioConfig = OpenScenarioConfig()) -> dict:
    """How far the scenario read back from ``xosc`` (with xml.etree) lies from the store it was written from:
    entities missing or extra, and over every track and frame the largest difference of the box centre (the read
    reference point plus its BoundingBox Center, turned by the read h, p, r; metres) and rotation (largest element of
    the rotation matrices' difference) from the store's boxes, and of time from the store's timestamps; the ego's
    reference point against the store's ego poses."""
    from omniscs.quaternions import quat_to_rotmat

    scene = load_scene(store)
    names = {e.track_id: e.name for e in scenario_entities(scene, config)}
    read = read_scenario(xosc)
    ts = scene.frames["timestamp_us"].to_numpy(np.int64)
    frame_times = (ts - ts[0]) / 1e6

    def track_poses(entity, n: int) -> tuple[np.ndarray, np.ndarray]:  # -> times [n], poses [n, 6] as read
        if len(entity.times_s):
            return entity.times_s, entity.poses
        return None, np.repeat(entity.initial[None], n, axis=0)  # standing still: placed once

    missing = sorted(set(names.values()) - set(read))
    position = rotation = time = 0.0
    ego = read.get("ego")
    if ego is not None:
        times, poses = track_poses(ego, len(ts))
        position = float(np.abs(poses[:, :3] - scene.world_from_ego_all[:, :3, 3]).max())
        time = 0.0 if times is None else float(np.abs(times - frame_times).max())
    for track_id, rows in scene.boxes.groupby("track_id"):
        entity = read.get(names[int(track_id)])
        if entity is None:
            continue
        rows = rows.sort_values("frame_idx")
        times, poses = track_poses(entity, len(rows))
        if len(poses) != len(rows):
            return {"missing": missing, "extra": [], "vertex_count_mismatch": entity.name, "position_m": None,
                    "rotation": None, "time_s": None}
        R_read = np.stack([rotmat_from_euler(r, p, h) for h, p, r in poses[:, 3:]])
        centres = poses[:, :3] + R_read @ entity.centre
        R_store = quat_to_rotmat(rows[["qw", "qx", "qy", "qz"]].to_numpy(np.float64))
        position = max(position, float(np.abs(centres - rows[["cx", "cy", "cz"]].to_numpy(np.float64)).max()))
        rotation = max(rotation, float(np.abs(R_read - R_store).max()))
        if times is not None:
            time = max(time, float(np.abs(times - frame_times[rows.frame_idx.to_numpy(np.int64)]).max()))
    return {"missing": missing, "extra": sorted(set(read) - set(names.values())), "position_m": position,
            "rotation": rotation, "time_s": time}


def openscenario_step(stores: list[Path], export_dir: Path, config: OpenScenarioConfig = OpenScenarioConfig()
                      ) -> dict:
    """Export ``stores`` into ``export_dir`` (replaced), check every file and read every scenario back."""
    versions = checker_versions()
    refused, exportable = {}, []
    for store in stores:  # a variant the exporter refuses (e.g. it leaves the roads) is reported, not fatal
        scene = load_scene(store)
        try:
            check_on_network(scenario_entities(scene, config), road_network_of(scene), f"scene {scene.scene_id}",
                             config.road_tolerance_m)
            exportable.append(store)
        except OmniscsError as exc:
            refused[scene.scene_id] = str(exc)
    if exportable:
        export_scenes(exportable, "openscenario", export_dir, overwrite=Path(export_dir).exists(), config=config)
    files = []
    for path in sorted(export_dir.glob("*.xodr")) + sorted(export_dir.glob("*.xosc")):
        report = check_file(path)
        files.append({"file": path.name, "checker": report.checker, "passed": report.passed,
                      "errors": report.issues["error"], "warnings": report.issues["warning"],
                      "information": report.issues["information"], "checks_completed": report.checkers["completed"],
                      "checks_skipped": report.checkers["skipped"], "checks_failed": report.checkers["error"],
                      "messages": list(report.messages)})
    variants = [{"store": scene_id, "refused": reason, "missing": [], "extra": [], "position_m": None}
                for scene_id, reason in refused.items()]
    for store in exportable:
        scene_id = load_scene(store).scene_id
        variants.append({"store": scene_id, "refused": None,
                         **round_trip(store, export_dir / f"{scene_id}.xosc", config)})
    worst = max((v["position_m"] for v in variants if v.get("position_m") is not None), default=None)
    summary = {
        "variants": len(stores), "refused": len(refused), "xosc_files": sum(f["file"].endswith(".xosc") for f in files),
        "xodr_files": sum(f["file"].endswith(".xodr") for f in files),
        "files_passed": sum(f["passed"] for f in files), "files": len(files),
        "errors": sum(f["errors"] for f in files), "warnings": sum(f["warnings"] for f in files),
        "information": sum(f["information"] for f in files),
        "round_trip_max_position_m": worst,
        "round_trip_holds": bool(variants) and all(_round_trip_holds(v) for v in variants),
        **{f"{name} version": version for name, version in versions.items()},
    }
    summary["all_passed"] = summary["files_passed"] == summary["files"] and summary["round_trip_holds"]
    return {"summary": summary, "files": files, "variants": variants}


def _round_trip_holds(variant: dict) -> bool:
    return variant["refused"] is None and not variant["missing"] and not variant["extra"] and \
        variant.get("position_m") is not None and variant["position_m"] <= ROUND_TRIP_M


def markdown(result: dict) -> str:
    s = result["summary"]
    versions = ", ".join(f"{k.removesuffix(' version')} {v}" for k, v in s.items() if k.endswith(" version"))
    lines = ["# OpenSCENARIO + OpenDRIVE export of the benchmark's variants", "",
             f"{s['variants']} variant(s), {s['refused']} refused by the exporter -> {s['xosc_files']} .xosc and "
             f"{s['xodr_files']} .xodr file(s); checked with {versions}: {s['files_passed']} of {s['files']} "
             "file(s) pass (no ERROR issue, no failed check, schema checked); "
             f"{s['errors']} error(s), {s['warnings']} warning(s), {s['information']} information issue(s) in all.",
             "",
             f"Round trip (box centres read back from the .xosc against the stores): largest difference "
             f"{_number(s['round_trip_max_position_m'])} m; holds within {ROUND_TRIP_M} m: {s['round_trip_holds']}.",
             "",
             "| file | checker | passed | errors | warnings | information | checks run | skipped | failed |",
             "|---|---|---|---|---|---|---|---|---|"]
    for f in result["files"]:
        lines.append(f"| {f['file']} | {f['checker']} | {f['passed']} | {f['errors']} | {f['warnings']} | "
                     f"{f['information']} | {f['checks_completed']} | {f['checks_skipped']} | {f['checks_failed']} |")
    lines += ["", "| store | position error (m) | rotation error | time error (s) | missing | extra | refused |",
              "|---|---|---|---|---|---|---|"]
    for v in result["variants"]:
        lines.append(f"| {v['store']} | {_number(v.get('position_m'))} | {_number(v.get('rotation'))} | "
                     f"{_number(v.get('time_s'))} | "
                     f"{', '.join(v['missing']) or '-'} | {', '.join(v['extra']) or '-'} | {v['refused'] or '-'} |")
    return "\n".join(lines) + "\n"


def _number(value) -> str:
    """A measured difference for the table: three significant digits, '-' when there is none."""
    return "-" if value is None else f"{float(value):.3g}"


def write_openscenario_report(reports_root: str | Path, stores: list[Path], export_dir: Path,
                              bench: str = "dataset") -> dict:
    """Run the step and write ``<reports_root>/<bench>/openscenario.json`` and ``.md``."""
    result = openscenario_step(stores, Path(export_dir))
    write_report(reports_root, bench, result, markdown(result), part=PART)
    return result
