"""The docs site's generated parts, made at build time (an MkDocs hook): nothing here is copied by hand.

- Results pages: every table under results/ is rendered from ``reports/<bench>/report.json`` (and the folder's
  other ``<part>.json`` files), so a rerun of a benchmark updates its page. ``BENCHMARKS`` is the one list of
  benchmark folders: tests/docs/test_reports.py checks reports/ against it.
- Knob tables: a line ``<!-- knobs omniscs/background RepairConfig -->`` in a page becomes the table of that config
  dataclass's fields, defaults and the first sentence of each field's docstring, read from the source (``ast``, no
  import), so option names and defaults in the guide are the code's.
- The fit guide's preset table: a line ``<!-- fit-presets -->`` becomes each preset's settings beside what
  ``omniscs bench fit`` measured for it (``reports/fit/report.json``), with the ratios against the baseline revision
  when the run had one (``--baseline``).
- Catalog columns (from ``omniscs.catalog.SCHEMAS``) and the READMEs kept beside catalogs/ and infra/.
"""
from __future__ import annotations

import ast
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
REPORTS = REPO / "reports"
INCLUDED = {"formats/catalog.md": "catalogs/README.md", "deployment/infra.md": "infra/README.md"}
"""Pages whose text lives beside the files it documents, copied into the site at build time."""
PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".gif", ".svg", ".webp")
MAX_ROWS = 60
"""Longest table a page shows; longer lists say how many rows the JSON holds."""
NOT_HEADLINES = {"machine", "python", "cpu_count", "benchmark", "label", "checkpoint", "note", "command"}
"""Top-level scalars of a report that describe the run rather than measure it (or are a machine's path)."""


@dataclass(frozen=True)
class Section:
    """One table of a results page."""

    title: str
    """Heading above the table."""
    path: str
    """Dotted key path into the JSON (``summary``, ``fault_injection.kills``, ``runs.0.render_ms_per_frame``)."""
    part: str = "report"
    """Which JSON file of the folder: ``report`` or another ``<part>.json``."""
    columns: tuple[str, ...] = ()
    """Dotted columns to show (all scalar columns when empty)."""
    per_key: bool = False
    """A dict of tables (``{split: {arm: {...}}}``): one table per outer key."""


@dataclass(frozen=True)
class Benchmark:
    """One benchmark folder under reports/ and its results page."""

    name: str
    """Folder name, the same as its ``omniscs bench`` command."""
    title: str
    """Page title."""
    command: str
    """The command that writes the folder."""
    about: str
    """One or two sentences: what it measures."""
    sections: tuple[Section, ...] = field(default_factory=tuple)
    """Tables, in page order."""


BENCHMARKS: tuple[Benchmark, ...] = (
    Benchmark("world", "Procedural world rendering", "omniscs bench world",
              "Time to generate and ray-cast a 40-frame, 3-camera 480x270 procedural log with LiDAR.",
              (Section("Runs", "runs"), Section("Ray casters compared", "ray_caster_comparison"))),
    Benchmark("sources", "Reading recorded-dataset formats", "omniscs bench sources",
              "A synthetic log written as nuScenes, KITTI and Waymo v2 and read back: milliseconds per frame.",
              (Section("Readers", "results"),)),
    Benchmark("render", "Gaussian rasterizer", "omniscs bench render --out reports",
              "Forward and forward+backward time of the CPU backend and the float64 reference, per resolution and "
              "Gaussian count.",
              (Section("Targets", "targets"), Section("Speed-up of cpu over reference", "speedups"),
               Section("Timings", "rows", columns=("width", "height", "count", "backend", "skipped", "forward_s",
                                                    "forward_backward_s", "forward_hz", "forward_backward_hz")))),
    Benchmark("fit", "Scene-graph fit presets", "omniscs bench fit --seeds 0 --out reports",
              "Each fit preset on the same log: wall time, Gaussians, held-out PSNR/SSIM and peak memory, against "
              "a previous revision measured in the same run (--baseline), and the speed/accuracy curve.",
              (Section("Per preset (medians)", "summary"),
               Section("Against the baseline revision (medians; speed-up = its time / ours)", "baseline.comparison"),
               Section("Issue 55's targets against the baseline", "baseline.targets"),
               Section("Speed/accuracy curve", "curve"),
               Section("Fits", "rows", columns=("scene_id", "side", "turn", "preset", "point", "iterations", "status",
                                                "wall_s", "n_gaussians", "heldout_psnr", "heldout_ssim", "train_psnr",
                                                "peak_rss_bytes", "load_1min_before", "load_1min_after")),
               Section("Targets", "targets"))),
    Benchmark("edits", "Edit fidelity", "omniscs bench edits --seeds 0 --out reports",
              "Translate and rotate edits of a fitted graph against the world's exact re-render.",
              (Section("Per edit", "summary"), Section("Fits", "fits"))),
    Benchmark("plan", "The scene plan", "omniscs bench plan",
              "The pipeline with the scene's plan against every track an agent node.",
              (Section("Per mode (medians)", "summary"),
               Section("Scenes", "rows", columns=("mode", "scene_id", "status", "wall_s", "fit_s", "behavior_s",
                                                   "n_agent_nodes", "n_tracks", "n_gaussians", "heldout_psnr",
                                                   "edited_masked_psnr", "variant_success")))),
    Benchmark("agents", "Agents: model pool, matching, dual strategy", "omniscs bench agents",
              "The paper's Table 4 (edited-agent masked PSNR per arm), the limits of the pool arm, pool build time and "
              "matching under degradation.",
              (Section("Table 4: edited-agent masked PSNR (dB)", "table4"),
               Section("What limits the pool arm (masked PSNR, dB)", "limits"),
               Section("Targets", "targets"),
               Section("Scene-graph fits", "fits", columns=("scene_id", "source", "heldout_psnr")),
               Section("Pool growth", "pool.growth"),
               Section("Matching alone (matching.json): top-1 / top-5", "matching", part="matching",
                       columns=("embedder", "cue", "level", "degradation", "queries", "top1", "top5")),
               Section("Matching target (matching.json)", "target", part="matching"))),
    Benchmark("background", "Background repair", "omniscs bench background --no-ablations",
              "A large parked truck or trailer removed from held-out logs; every arm against the world re-rendered "
              "without it, at held-out logged views and novel views. report.json is the current default's run; "
              "ablations.json an older run with every ablation arm, whose planes row is an earlier default "
              "(see the design notes). The current run leaves the full refit out, so its RoI-against-full time "
              "ratio is empty and `roi_time_met` reads no for that reason alone; the older run's targets hold the "
              "measured ratio.",
              (Section("Arms (current default's run)", "summary",
                       columns=("arm", "views", "scenes", "hole_psnr", "hole_ssim", "depth_absrel", "depth_delta",
                                "full_psnr", "hole_psnr_lit", "seconds")),
               Section("Targets", "targets"),
               Section("Scenes", "scenes", columns=("scene_id", "category", "heldout_psnr", "hole_views", "seeds",
                                                     "dropped_gaussians", "observed_pixels", "inpainted_pixels",
                                                     "unfilled_pixels", "hole_pixels")),
               Section("Every ablation arm (ablations.json, older run)", "summary", part="ablations",
                       columns=("arm", "views", "scenes", "hole_psnr", "hole_ssim", "depth_absrel", "depth_delta",
                                "full_psnr", "seconds")),
               Section("Targets of the older run (ablations.json)", "targets", part="ablations"),
               Section("A large parked object replaced by a smaller one, without and with the repair "
                       "(replacement.json, `omniscs bench background --replacement --quick`)", "summary",
                       part="replacement", columns=("arm", "views", "n_views", "region_pixels", "ghost_pixels",
                                                    "ghost_share", "hole_psnr")))),
    Benchmark("behavior", "Behaviour-level SCS", "omniscs bench behavior",
              "Adversarial success and plausibility per configuration on the fixed scene set, and the traffic "
              "model's held-out ADE/FDE.",
              (Section("Per configuration", "summary",
                       columns=("variants", "variant_success_rate", "successful_and_plausible_rate",
                                "scene_success_rate_feasible", "scene_success_rate_any_variant", "feasible_scenes",
                                "reachable_scenes", "knot_variants", "violation_rate_successful",
                                "adversary_lateral_accel_max", "seconds_per_variant_median")),
               Section("With L_app (appearance scenes)", "appearance.summary",
                       columns=("variants", "variant_success_rate", "successful_and_plausible_rate",
                                "appearance_drift_psnr_db_mean", "seconds_per_variant_median")),
               Section("Traffic model, held-out (3 s)", "traffic_model_heldout"))),
    Benchmark("appearance", "Appearance-level SCS", "omniscs bench appearance",
              "Pool objects inserted and replacing vehicles in fitted graphs, against the world's exact ground truth.",
              (Section("Per case and arm", "summary"), Section("Targets", "targets"),
               Section("Sampler rejections", "rejections"))),
    Benchmark("dataset", "Render + annotate throughput", "omniscs bench dataset",
              "Annotated variants per hour after fitting, with and without fidelity measurement; then every variant "
              "exported as OpenSCENARIO + OpenDRIVE and checked with ASAM's checkers.",
              (Section("Summary", "summary"),
               Section("Scenes", "scenes", columns=("scene", "scene_id", "fit_seconds", "heldout_psnr",
                                                     "behavior_seconds", "variants", "replay_seconds")),
               Section("OpenSCENARIO + OpenDRIVE export, ASAM checkers (openscenario.json)", "summary",
                       part="openscenario"),
               Section("ASAM checker results per file (openscenario.json)", "files", part="openscenario",
                       columns=("file", "checker", "passed", "errors", "warnings", "information",
                                "checks_completed", "checks_skipped", "checks_failed")),
               Section("Round trip per variant (openscenario.json)", "variants", part="openscenario",
                       columns=("store", "refused", "position_m", "rotation", "time_s")))),
    Benchmark("downstream", "Downstream models", "omniscs bench downstream  /  omniscs bench downstream --detection",
              "The planning protocol (report.json) and the detection protocol (detection.json) with the proxy "
              "planner and detector: base against fine-tuned with SCS data.",
              (Section("Planning: summary", "summary"),
               Section("Planning: 95 % intervals (resampled test scenes)", "intervals"),
               Section("Planning: test sets", "rows", per_key=True,
                       columns=("n", "L2.1s", "L2.2s", "L2.3s", "collision.1s", "collision.2s", "collision.3s")),
               Section("Planning: fine-tuning settings tried on the validation scenes", "finetune_selection"),
               Section("Detection: summary", "summary", part="detection"),
               Section("Detection: fine-tuning candidates (validation sets)", "candidates", part="detection"),
               Section("Detection: test sets (boxes a camera sees)", "rows", part="detection", per_key=True,
                       columns=("mAP", "NDS", "AP.bus", "AP.car", "AP.construction_vehicle", "AP.trailer",
                                "AP.truck")))),
    Benchmark("closedloop", "Closed loop", "omniscs bench closedloop",
              "Steps per second, the shipped policies' PDMS, EPDMS and HD-Score on logs and behaviour-SCS variants, "
              "and 20 HUGSIM clients at once.",
              (Section("Speed", "speed"),
               Section("Scores per policy", "summary",
                       columns=tuple(f"{kind}.{k}" for kind in ("log", "behavior")
                                     for k in ("n", "pdms", "epdms", "epdms_navsim_ttc", "hd_score",
                                               "route_completion", "collision_rate"))
                       + ("scs_penalty.pdms", "scs_penalty.epdms", "scs_penalty.hd_score")),
               Section("EPDMS sub-scores per policy", "epdms_sub_scores", per_key=True,
                       columns=("n", "nc", "dac", "ddc", "tlc", "ep", "ttc", "lk", "hc", "ec", "with_lanes")),
               Section("Load", "load"))),
    Benchmark("view", "Viewer", "omniscs bench view",
              "`omniscs view` in Debian's headless chromium, whose WebGL is software (SwiftShader, on the CPU): time "
              "to first frame and frame rate of the splat view while the camera orbits, for 50k / 200k / 500k "
              "Gaussians (a floor for a machine with a GPU), and the time from an edit to the new camera image in "
              "the browser at 640x360 against the 1 s target.",
              (Section("Splat view", "splat_view",
                       columns=("gaussians", "drawn_splats", "densified_copies", "server_setup_s", "page_load_s",
                                "first_draw_s", "first_frame_after_s", "first_frame_s", "settled_s", "orbit_fps",
                                "orbit_frames")),
               Section("Edit to camera image", "edit_latency"),
               Section("World", "world", columns=("scene", "scene_id", "fitted_gaussians", "agent_nodes", "frame",
                                                  "fit_seconds", "heldout_psnr")))),
    Benchmark("scaleout", "Scale-out", "omniscs bench scaleout",
              "generate_dataset on 8 scenes with 1 and 2 Dask workers, a worker killed mid-fit, a projection.",
              (Section("Runs", "runs", columns=("workers", "killed", "wall_s", "scenes", "failed", "scenes_per_hour")),
               Section("Resume after a killed worker", "resume",
                       columns=("workers", "wall_s", "scenes", "failed", "scenes_per_hour")),
               Section("Projection", "projection"))),
    Benchmark("reliability", "Reliability", "omniscs bench reliability",
              "`omniscs generate` killed at random moments and rerun; several runs at once on one workspace.",
              (Section("Kills", "fault_injection.kills",
                       columns=("kill_after_s", "ended_before_kill", "orphaned_processes", "temporaries_after_kill",
                                "rerun_exit", "rerun_s", "catalog_equal", "files_equal", "temporaries_after_rerun")),
               Section("Concurrent runs", "concurrency"))),
    Benchmark("bad-inputs", "Bad inputs", "omniscs bench bad-inputs",
              "Every bad input of the table over every command: one clear line, traceback, silently wrong, left "
              "files.",
              (Section("By category", "summary"),)),
    Benchmark("gpu-check", "GPU checks", "infra/gpu_check/run.sh (on a CUDA machine)",
              "gsplat parity, render timing and a CUDA fit on a lent H200 (parsed from the run logs).",
              (Section("2026-11-26: render, ms per frame", "runs.0.render_ms_per_frame"),
               Section("2026-11-26: fast preset, 300 iterations", "runs.0.fit_fast_300_iterations"),
               Section("2026-11-26: three behaviour variants", "runs.0.behavior_variants_3_fast"),
               Section("2026-11-27: render, ms per frame", "runs.1.render_ms_per_frame"),
               Section("2026-11-27: fast preset, 300 iterations", "runs.1.fit_fast_300_iterations"),
               Section("2026-11-27: three behaviour variants", "runs.1.behavior_variants_3_fast"))),
)
BENCHMARK_NAMES = tuple(b.name for b in BENCHMARKS)


def fmt(value) -> str:
    """One table cell: numbers to 4 significant digits, booleans as yes/no, short lists joined."""
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}" if abs(value) >= 10_000 else str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        if value != 0 and abs(value) < 1e-3:
            return f"{value:.3g}"
        return f"{value:,.4g}" if abs(value) < 1e4 else f"{value:,.0f}"
    if isinstance(value, list):
        return ", ".join(fmt(v) for v in value)
    return str(value).replace("|", "\\|").replace("\n", " ")


def flatten(record: dict, prefix: str = "") -> dict:
    """Nested dicts as dotted keys; lists of up to 8 scalars kept; other lists left out."""
    out = {}
    for key, value in record.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, name + "."))
        elif isinstance(value, list):
            if len(value) <= 8 and all(not isinstance(v, (dict, list)) for v in value):
                out[name] = value
        else:
            out[name] = value
    return out


def lookup(data, path: str):
    """The value at a dotted path (integer parts index lists); None where it is missing."""
    for part in path.split("."):
        if isinstance(data, list) and part.isdigit() and int(part) < len(data):
            data = data[int(part)]
        elif isinstance(data, dict) and part in data:
            data = data[part]
        else:
            return None
    return data


def table(rows: list[dict], columns: tuple[str, ...] = (), first: str | None = None) -> list[str]:
    """A Markdown table of flattened rows (``first`` names a leading key column)."""
    flat = [flatten(r) for r in rows]
    if not columns:
        seen: dict[str, None] = {}
        for r in flat:
            seen.update(dict.fromkeys(r))
        columns = tuple(c for c in seen if c != "__key__")
    columns = tuple(c for c in columns if any(c in r for r in flat))
    head = ([first] if first is not None else []) + list(columns)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, r in enumerate(flat[:MAX_ROWS]):
        cells = ([fmt(rows[i].get("__key__"))] if first is not None else []) + [fmt(r.get(c)) for c in columns]
        lines.append("| " + " | ".join(cells) + " |")
    if len(flat) > MAX_ROWS:
        lines += ["", f"(first {MAX_ROWS} of {len(flat)} rows; all of them are in the JSON)"]
    return lines


def render_value(value, columns: tuple[str, ...] = ()) -> list[str]:
    """A list of records, a dict of records or a dict of values, as a Markdown table."""
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        return table(value, columns)
    if isinstance(value, dict) and value and all(isinstance(v, dict) for v in value.values()):
        rows = [{"__key__": k, **v} for k, v in value.items()]
        return table(rows, columns or (), first="")
    if isinstance(value, dict):
        flat = flatten(value)
        lines = ["| key | value |", "|---|---|"]
        lines += [f"| {k} | {fmt(v)} |" for k, v in flat.items() if not columns or k in columns]
        return lines
    return [fmt(value)]


def machine_line(report: dict) -> str:
    """Where the benchmark ran, as the report states it."""
    m = report.get("machine")
    if isinstance(m, dict):
        load = m.get("load_average_start")
        parts = [f"{m.get('cpus', '?')} CPUs", str(m.get("platform", m.get("machine", ""))),
                 f"Python {m.get('python', '?')}", f"torch {m.get('torch', '?')}"]
        if "gpu" in m:
            parts = [f"{m['gpu']} (driver {m.get('driver', '?')})", f"{m.get('cpus', '?')} CPUs",
                     f"torch {m.get('torch', '?')}", f"gsplat {m.get('gsplat', '?')}"]
        if load:
            parts.append(f"1-min load {fmt(load[0])} at start")
        return "Machine: " + ", ".join(p for p in parts if p) + "."
    if "cpu_count" in report or "python" in report:
        return f"Machine: {report.get('cpu_count', '?')} CPUs, {report.get('machine', '')}, Python {report.get('python', '?')}."
    return ""


def load_parts(folder: Path) -> dict[str, dict]:
    """Every JSON file of a benchmark folder, by stem."""
    return {p.stem: json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))}


def pictures(folder: Path) -> list[Path]:
    """The folder's pictures, report.* first."""
    found = [p for p in sorted(folder.iterdir()) if p.suffix.lower() in PICTURE_SUFFIXES]
    return sorted(found, key=lambda p: (p.stem != "report", p.name))


def render_page(bench: Benchmark, folder: Path) -> str:
    """The Markdown of one results page."""
    parts = load_parts(folder)
    report = parts.get("report", {})
    lines = [f"# {bench.title}", "", bench.about, "",
             f"Written by `{bench.command}` into `reports/{bench.name}/`; this page is generated from its JSON "
             f"({', '.join(f'`{p}.json`' for p in parts)}) when the site is built. The benchmark's own write-up, "
             f"with its protocol and notes, is `reports/{bench.name}/report.md`.", ""]
    line = machine_line(report)
    if line:
        lines += [line + " Machines are shared: compare rows of one run, not runs.", ""]
    headline = {k: v for k, v in report.items()
                if not isinstance(v, (dict, list)) and k not in NOT_HEADLINES}
    if headline:
        lines += ["## Headline figures", ""] + render_value(headline) + [""]
    for section in bench.sections:
        value = lookup(parts.get(section.part, {}), section.path)
        if value is None or value == [] or value == {}:
            continue
        lines += [f"## {section.title}", ""]
        if section.per_key and isinstance(value, dict):
            for key, inner in value.items():
                lines += [f"**{key}**", ""] + render_value(inner, section.columns) + [""]
        else:
            lines += render_value(value, section.columns) + [""]
    images = pictures(folder)
    if images:
        lines += ["## Pictures", ""]
        lines += [f"![{p.stem}]({bench.name}/{p.name})" + "\n" for p in images]
    return "\n".join(lines) + "\n"


def render_index(present: list[Benchmark]) -> str:
    """results/index.md: one line per benchmark."""
    lines = ["# Results", "",
             "Every page here is generated from `reports/<bench>/report.json` when the site is built "
             "(`docs/gen_results.py`); a rerun of `omniscs bench <bench>` replaces its folder and so its page. "
             "Benchmarks run on a shared 2-core CPU machine unless a page says otherwise.", "",
             "| benchmark | what it measures |", "|---|---|"]
    lines += [f"| [{b.title}]({b.name}.md) | {b.about} |" for b in present]
    return "\n".join(lines) + "\n"


def included_page(source: Path) -> str:
    """A README kept beside its files, with links to those files turned into repository paths (the site holds
    only the docs)."""
    folder = source.parent.relative_to(REPO).as_posix()
    return re.sub(r"\[([^\]]+)\]\((?!https?:)([^)#]+)\)", lambda m: f"{m.group(1)} (`{folder}/{m.group(2)}`)",
                  source.read_text())


def catalog_columns() -> str:
    """formats/catalog-columns.md: every catalog table's columns, from ``omniscs.catalog.SCHEMAS``."""
    import sys

    if str(REPO) not in sys.path:  # the checkout being documented, before any installed copy
        sys.path.insert(0, str(REPO))
    from omniscs.catalog import KEYS, SCHEMAS

    lines = ["# Catalog columns", "",
             "Generated from `omniscs.catalog.SCHEMAS` (the one declaration every write is validated against) when "
             "the site is built. Every table also has `run_id` (its hive partition). What the tables hold and how to "
             "query them: [Catalog tables](catalog.md).", ""]
    for table_name, schema in SCHEMAS.items():
        lines += [f"## `{table_name}`", "", f"Logical key: `{', '.join(KEYS[table_name])}`.", "",
                  "| column | type | nullable |", "|---|---|---|"]
        lines += [f"| `{f.name}` | {f.type} | {'yes' if f.nullable else 'no'} |" for f in schema]
        lines.append("")
    return "\n".join(lines)


def generate(reports: Path = REPORTS) -> dict[str, str | bytes]:
    """Every generated file of the site, by its path under docs/ (``results/...``)."""
    files: dict[str, str | bytes] = {}
    present = [b for b in BENCHMARKS if (reports / b.name / "report.json").is_file()]
    for bench in present:
        folder = reports / bench.name
        files[f"results/{bench.name}.md"] = render_page(bench, folder)
        for picture in pictures(folder):
            files[f"results/{bench.name}/{picture.name}"] = picture.read_bytes()
    files["results/index.md"] = render_index(present)
    for page, source in INCLUDED.items():
        files[page] = included_page(REPO / source)
    files["formats/catalog-columns.md"] = catalog_columns()
    return files


KNOBS_MARKER = re.compile(r"^<!-- knobs (\S+) (\w+) -->$", re.M)


def first_sentence(doc: str) -> str:
    """A field docstring's first sentence, on one line (the rest of a docstring is for the code's readers)."""
    text = " ".join(doc.split())
    # when a default changed belongs to the design notes, not to the table of what the knob does
    text = re.sub(r"[;:]\s*the default until[^)]*?\d{4}-\d\d-\d\d", "", text)
    match = re.search(r"\.\s+(?=[A-Z0-9(`])", text)
    return text[: match.start() + 1] if match else text


def find_class(package: str, name: str) -> tuple[Path, ast.ClassDef]:
    """The one class ``name`` defined under the folder ``package`` (e.g. ``omniscs/background``)."""
    root = REPO / package
    files = [root] if root.suffix == ".py" else sorted(root.rglob("*.py"))
    found = [(f, node) for f in files for node in ast.parse(f.read_text()).body
             if isinstance(node, ast.ClassDef) and node.name == name]
    if len(found) != 1:
        raise ValueError(f"knobs: {len(found)} classes named {name} under {package}; name a folder or file "
                         "that holds exactly one")
    return found[0]


def knobs_table(package: str, name: str) -> str:
    """The fields of a documented config dataclass: name, type, default and meaning."""
    path, cls = find_class(package, name)
    rows = []
    body = cls.body
    for i, node in enumerate(body):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        if "ClassVar" in ast.unparse(node.annotation):
            continue
        default = ast.unparse(node.value) if node.value is not None else "(required)"
        default = re.sub(r"^field\(default_factory=(\w+)\)$", r"\1()", default)
        doc = ""
        if i + 1 < len(body) and isinstance(body[i + 1], ast.Expr) and isinstance(body[i + 1].value, ast.Constant) \
                and isinstance(body[i + 1].value.value, str):
            doc = first_sentence(body[i + 1].value.value)
        rows.append(f"| `{node.target.id}` | `{fmt(default)}` | {fmt(doc)} |")
    source = path.relative_to(REPO).as_posix()
    return "\n".join([f"`{name}` (`{source}`; every field is documented there):", "",
                      "| field | default | meaning |", "|---|---|---|", *rows])


PRESETS_MARKER = re.compile(r"^<!-- fit-presets -->$", re.M)


def schedule_text(schedule: list) -> str:
    """A resolution schedule ``[(fraction, factor), ...]`` in words: ``1/4, 1/2 from 25 %, full from 60 %``."""
    steps = []
    for start, factor in schedule:
        size = "full" if factor == 1 else f"1/{factor}"
        steps.append(size if start == 0 else f"{size} from {start * 100:.0f} %")
    return ", ".join(steps)


def code_preset_settings() -> dict[str, dict]:
    """The presets' settings as the code defines them (for reports written before the benchmark recorded them)."""
    import sys

    if str(REPO) not in sys.path:  # the checkout being documented, before any installed copy
        sys.path.insert(0, str(REPO))
    from omniscs.nsg.config import PRESETS

    return {name: {"iterations": c.iterations, "resolution_schedule": [list(s) for s in c.resolution_schedule],
                   "sh_degree": c.sh_degree, "gaussians_per_m2": c.plan.gaussians_per_m2,
                   "max_gaussians": c.plan.max_gaussians} for name, c in PRESETS.items()}


def preset_table(reports: Path = REPORTS) -> str:
    """The fit guide's preset table: each measured preset's settings (as the report records them) and its medians
    from ``reports/fit/report.json``; the time and PSNR against the baseline revision where the run had one."""
    path = reports / "fit" / "report.json"
    if not path.is_file():
        return "(no fit benchmark report yet: run `omniscs bench fit --out reports`)"
    report = json.loads(path.read_text())
    settings = report.get("preset_settings") or code_preset_settings()
    base = report.get("baseline") or {}
    against = {c["preset"]: c for c in base.get("comparison", [])}
    head = ["preset", "iterations", "resolution schedule", "SH degree", "Gaussian budget", "time", "held-out PSNR",
            "held-out SSIM", "Gaussians", "peak memory"]
    if against:
        head += [f"speed-up vs {base['ref']}", f"PSNR vs {base['ref']}"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in report.get("summary", []):
        given = settings.get(s["preset"], {})
        measured = [r["iterations"] for r in report.get("rows", []) if r.get("preset") == s["preset"]
                    and r.get("point", "preset") == "preset" and r.get("side", "current") == "current"]
        iterations = measured[0] if measured else given.get("iterations", s.get("iterations"))
        memory = s.get("median_peak_rss_bytes")
        cells = [f"`{s['preset']}`", "—" if iterations is None else f"{iterations:,}",
                 schedule_text(given["resolution_schedule"]) if "resolution_schedule" in given else "—",
                 fmt(given.get("sh_degree")),
                 f"{given['gaussians_per_m2']:g} /m² (max {given['max_gaussians'] / 1000:g}k)"
                 if "gaussians_per_m2" in given else "—",
                 f"{s['median_wall_s']:,.0f} s", f"{s['median_heldout_psnr']:.2f} dB", f"{s['median_heldout_ssim']:.3f}",
                 f"{s['median_gaussians']:,}", "—" if memory is None else f"{memory / 2**30:.2f} GiB"]
        if against:
            c = against.get(s["preset"])
            cells += ["—", "—"] if c is None else [f"{c['speedup']:.2f}x", f"{c['psnr_difference_db']:+.2f} dB"]
        lines.append("| " + " | ".join(cells) + " |")
    measured_presets = {s["preset"] for s in report.get("summary", [])}
    for name, given in code_preset_settings().items():  # a preset the run left out: its settings, no figures
        if name in measured_presets:
            continue
        cells = [f"`{name}`", f"{given['iterations']:,}", schedule_text(given["resolution_schedule"]),
                 fmt(given.get("sh_degree")), f"{given['gaussians_per_m2']:g} /m² (max {given['max_gaussians'] / 1000:g}k)",
                 "not measured in this run"] + ["—"] * (len(head) - 6)
        lines.append("| " + " | ".join(cells) + " |")
    machine = report.get("machine", {})
    load = machine.get("load_average_start") or [None]
    source = "as the report records them" if report.get("preset_settings") else "the code's (`PRESETS`)"
    fits = max((s["fits"] for s in report.get("summary", [])), default=0)
    note = (f"Measured by `omniscs bench fit` on {report.get('label', 'its scene')}: medians of {fits} fit(s) per "
            f"preset, {machine.get('cpus', '?')} CPUs, 1-min load "
            f"{'?' if load[0] is None else f'{load[0]:.1f}'} at start (generated from `reports/fit/report.json`; settings {source}).")
    if against:
        note += (f" Against {base['ref']} ({base['commit'][:12]}): the same scenes fitted by that revision in "
                 "alternating turns of the same run; speed-up = its time / ours, PSNR difference = ours - its.")
    return "\n".join(lines + ["", note])


def on_page_markdown(markdown, page, config, files):
    """MkDocs hook: expand the knob-table and preset-table markers of a page."""
    markdown = KNOBS_MARKER.sub(lambda m: knobs_table(m.group(1), m.group(2)), markdown)
    return PRESETS_MARKER.sub(lambda m: preset_table(), markdown)


def on_files(files, config):
    """MkDocs hook: add the generated results pages and their pictures to the site."""
    from mkdocs.structure.files import File

    for src_uri, content in generate().items():
        files.append(File.generated(config, src_uri, content=content))
    return files
