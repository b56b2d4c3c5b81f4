"""``omniscs bench bad-inputs``: a table of bad inputs over every command, each run as a user would and classified.

Every case is a mistake (a bad source, option, file, id, path, checkpoint, edit or query). The expected outcome is
always the same: exit code 2, exactly one ``error:`` line on stderr, no traceback, and nothing new on disk (in the
case's folder, which is also its working directory and holds its workspace). Each outcome is classified as one of
``one clear line`` (expected), ``traceback``, ``silently wrong`` (exit 0: the mistake was accepted), ``left files``
or ``other`` (e.g. several lines, or another exit code).

The report has a second section, server abuse: hostile requests to the closed-loop render server, run by
``omniscs.bench.server_abuse`` against in-thread servers (they are requests, not command lines).
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import traceback
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from typing import Iterator

import pyarrow as pa
import pyarrow.parquet as pq
import torch

from omniscs.agents.ply import write_gaussian_ply
from omniscs.bench.harness import finish, load_line, machine_info, write_report
from omniscs.bench.server_abuse import run_server_abuse, server_markdown
from omniscs.export.common import export_scenes
from omniscs.gaussians import GaussianParams
from omniscs.pipeline.stages import catalog_run_stage
from omniscs.progress import Progress, no_progress
from omniscs.scene import SyntheticSource
from omniscs.scene.synthetic import write_synthetic_scene
from omniscs.scs.behavior.checkpoint import DEFAULT_CHECKPOINT

OUTCOMES = ("one clear line", "traceback", "silently wrong", "left files", "other")


@dataclass(frozen=True)
class Case:
    """One bad input: ``argv`` after ``omniscs``; ``{name}`` placeholders are fixtures (see ``Fixtures``)."""

    category: str
    name: str
    argv: tuple[str, ...]

    @property
    def id(self) -> str:
        return f"{self.category}: {self.name}"


def _c(category: str, name: str, *argv: str) -> Case:
    return Case(category, name, tuple(argv))


REMOVE_99 = '{"op": "remove", "track_id": 99}'
HUGE_TRACK = '{"op": "remove", "track_id": ' + "7" * 5000 + "}"
DEEP = b"[" * 100_000
NUS_VERSION = "v1.0-trainval"  # what the fixture dataroot holds (named, so eval prints no note about it)
NUS_EVAL = ("--dataroot", "{nus}", "--version", NUS_VERSION)
GEN = ("generate", "syn:straight:0")

CASES: tuple[Case, ...] = (
    # --------------------------------------------------------------- generate: sources
    _c("sources", "unknown template", "generate", "syn:nope:1"),
    _c("sources", "negative seed", "generate", "syn:straight:-1"),
    _c("sources", "seed beyond 2^32", "generate", "syn:straight:99999999999"),
    _c("sources", "unknown lighting", "generate", "syn:straight:0:purple"),
    _c("sources", "seed missing", "generate", "syn:straight"),
    _c("sources", "seed not a number", "generate", "syn:straight:abc"),
    _c("sources", "one part too many", "generate", "syn:straight:0:day:extra"),
    _c("sources", "bare syn:", "generate", "syn:"),
    _c("sources", "empty source", "generate", ""),
    _c("sources", "markup in the source", "generate", "syn:[bold]x[/]:1"),
    _c("sources", "emoji code in the source", "generate", "syn::x::1"),
    _c("sources", "store that does not exist", "generate", "/nonexistent/store"),
    _c("sources", "a file as store", "generate", "{file}"),
    _c("sources", "an empty folder as store", "generate", "{empty}"),
    _c("sources", "one bad among good", "generate", "syn:straight:0", "syn:straight:0:purple"),
    _c("sources", "nuscenes root that does not exist", "generate", "nuscenes:/nonexistent"),
    _c("sources", "nuscenes scene that does not exist", "generate", "nuscenes:{nus}:scene-nope"),
    _c("sources", "nuscenes root without tables", "generate", "nuscenes:{empty}"),
    _c("sources", "nuscenes without a root", "generate", "nuscenes:"),
    _c("sources", "kitti root without sequences", "generate", "kitti:{empty}"),
    _c("sources", "waymo root without segments", "generate", "waymo-v2:{empty}"),
    # --------------------------------------------------------------- scene stores (as generate sources)
    _c("scene stores", "scene_id ../../x", "generate", "{badid}"),
    _c("scene stores", "corrupt PNG (same size)", "generate", "{badpng}"),
    _c("scene stores", "truncated LiDAR file", "generate", "{trunclidar}"),
    _c("scene stores", "manifest is a list", "generate", "{mlist}"),
    _c("scene stores", "manifest not JSON", "generate", "{mgarbage}"),
    _c("scene stores", "wrong column type", "generate", "{wrongcol}"),
    _c("scene stores", "missing image", "generate", "{noimage}"),
    # --------------------------------------------------------------- generate: options
    _c("generate options", "--frames 0", *GEN, "--frames", "0"),
    _c("generate options", "--frames negative", *GEN, "--frames", "-5"),
    _c("generate options", "--frames huge", *GEN, "--frames", "1000000"),
    _c("generate options", "--frames not a number", *GEN, "--frames", "abc"),
    _c("generate options", "--cameras 0", *GEN, "--cameras", "0"),
    _c("generate options", "--cameras 7", *GEN, "--cameras", "7"),
    _c("generate options", "--width 1", *GEN, "--width", "1"),
    _c("generate options", "--height 0", *GEN, "--height", "0"),
    _c("generate options", "--width huge", *GEN, "--width", "100000"),
    _c("generate options", "unknown fit preset", *GEN, "--fit-preset", "best"),
    _c("generate options", "negative variants", *GEN, "--behavior-variants", "-1"),
    _c("generate options", "a million variants", *GEN, "--behavior-variants", "1000000"),
    _c("generate options", "unknown behaviour preset", *GEN, "--behavior-preset", "ultra"),
    _c("generate options", "missing checkpoint", *GEN, "--behavior-variants", "1", "--behavior-checkpoint",
       "/nonexistent"),
    _c("generate options", "truncated checkpoint", *GEN, "--behavior-variants", "1", "--behavior-checkpoint",
       "{bckpt_trunc}"),
    _c("generate options", "a folder that is no checkpoint", *GEN, "--behavior-variants", "1",
       "--behavior-checkpoint", "{empty}"),
    _c("generate options", "unknown device", *GEN, "--device", "tpu"),
    _c("generate options", "CUDA device that is not here", *GEN, "--device", "cuda:9"),
    _c("generate options", "unknown option", *GEN, "--bogus"),
    _c("ids", "run id ../x", *GEN, "--run-id", "../x"),
    _c("ids", "run id a/b", *GEN, "--run-id", "a/b"),
    _c("ids", "empty run id", *GEN, "--run-id", ""),
    _c("ids", "run id with a quote", *GEN, "--run-id", "it's"),
    _c("paths", "workspace is a file", *GEN, "--workspace", "{file}"),
    _c("paths", "workspace under a file", *GEN, "--workspace", "{file}/ws"),
    _c("paths", "workspace with a quote, bad source", "generate", "syn:nope:0", "--workspace", "{tmp}/it's here"),
    _c("paths", "demo workspace is a file", "demo", "--workspace", "{file}"),
    # --------------------------------------------------------------- edit specs
    _c("edit specs", "a number", *GEN, "--edit", "5"),
    _c("edit specs", "track_id true", *GEN, "--edit", '{"op": "remove", "track_id": true}'),
    _c("edit specs", "string amount", *GEN, "--edit", '{"op": "translate", "track_id": 1, "longitudinal": "3"}'),
    _c("edit specs", "NaN amount", *GEN, "--edit", '{"op": "translate", "track_id": 1, "longitudinal": NaN}'),
    _c("edit specs", "huge amount", *GEN, "--edit", '{"op": "translate", "track_id": 1, "longitudinal": 1e9}'),
    _c("edit specs", "unknown op", *GEN, "--edit", '{"op": "explode", "track_id": 1}'),
    _c("edit specs", "missing track", *GEN, "--edit", '[{"op": "remove"}]'),
    _c("edit specs", "negative track", *GEN, "--edit", '{"op": "remove", "track_id": -1}'),
    _c("edit specs", "unknown field", *GEN, "--edit", '{"op": "remove", "track_id": 1, "extra": 2}'),
    _c("edit specs", "not JSON", *GEN, "--edit", "remove track 1"),
    _c("edit specs", "edit file that does not exist", *GEN, "--edit", "@/nonexistent.json"),
    _c("edit specs", "edit file of garbage", *GEN, "--edit", "@{file}"),
    _c("edit specs", "a list of numbers", *GEN, "--edit", "[1, 2]"),
    _c("edit specs", "null", *GEN, "--edit", "null"),
    _c("edit specs", "fit: edit of a track the scene lacks", "fit", "{store}", "--out", "m", "--edit", REMOVE_99),
    _c("edit specs", "world render: a number", "world", "render", "{store}", "--out", "x.png", "--edit", "5"),
    _c("edit specs", "render: string amount", "render", "{notckpt}", "--out", "r.png", "--edit",
       '{"op": "translate", "track_id": 1, "longitudinal": "3"}'),
    # --------------------------------------------------------------- world
    _c("world", "make: unknown template", "world", "make", "--out", "s", "--template", "nope"),
    _c("world", "make: negative seed", "world", "make", "--out", "s", "--seed", "-1"),
    _c("world", "make: zero frames", "world", "make", "--out", "s", "--frames", "0"),
    _c("world", "make: nine cameras", "world", "make", "--out", "s", "--cameras", "9"),
    _c("world", "make: width 2", "world", "make", "--out", "s", "--width", "2"),
    _c("world", "make: unknown lighting", "world", "make", "--out", "s", "--lighting", "purple"),
    _c("world", "make: --out under a file", "world", "make", "--out", "{file}/s"),
    _c("world", "make: --overwrite of a user's folder", "world", "make", "--out", "{userdir}", "--overwrite"),
    _c("world", "make: --overwrite of a file", "world", "make", "--out", "{file}", "--overwrite"),
    _c("world", "make: --out exists", "world", "make", "--out", "{store}"),
    _c("world", "make: no --out", "world", "make"),
    _c("world", "render: not a store", "world", "render", "{file}", "--out", "x.png"),
    _c("world", "render: store that does not exist", "world", "render", "/nonexistent", "--out", "x.png"),
    _c("world", "render: --out not a PNG", "world", "render", "{store}", "--out", "x.jpg"),
    _c("world", "render: unknown camera", "world", "render", "{store}", "--out", "x.png", "--camera", "CAM_NOPE"),
    _c("world", "render: frame beyond the log", "world", "render", "{store}", "--out", "x.png", "--frame", "99"),
    _c("world", "render: negative frame", "world", "render", "{store}", "--out", "x.png", "--frame", "-1"),
    _c("world", "render: --out under a file", "world", "render", "{store}", "--out", "{file}/x.png"),
    _c("world", "render: manifest is a list", "world", "render", "{mlist}", "--out", "x.png"),
    _c("world", "export: unknown format", "world", "export", "{store}", "--format", "nope", "--out", "ex"),
    _c("world", "export: --overwrite of a user's folder", "world", "export", "{store}", "--format", "nuscenes",
       "--out", "{userdir}", "--overwrite"),
    _c("world", "export: store that does not exist", "world", "export", "/nonexistent", "--format", "kitti",
       "--out", "ex"),
    _c("world", "export: unknown KITTI camera", "world", "export", "{store}", "--format", "kitti", "--out", "ex",
       "--camera", "CAM_NOPE"),
    _c("world", "export: keyframe every 0", "world", "export", "{store}", "--format", "nuscenes", "--out", "ex",
       "--keyframe-every", "0"),
    _c("world", "export: version ../x", "world", "export", "{store}", "--format", "nuscenes", "--out", "ex",
       "--version", "../x"),
    _c("world", "export: --out under a file", "world", "export", "{store}", "--format", "waymo-v2", "--out",
       "{file}/x"),
    _c("world", "export: damaged store", "world", "export", "{trunclidar}", "--format", "kitti", "--out", "ex"),
    # --------------------------------------------------------------- ingest
    _c("ingest", "unknown format", "ingest", "--source", "nope", "--dataroot", "{nus}", "--out", "o"),
    _c("ingest", "root that does not exist", "ingest", "--source", "nuscenes", "--dataroot", "/nonexistent",
       "--out", "o"),
    _c("ingest", "scene that does not exist", "ingest", "--source", "nuscenes", "--dataroot", "{nus}", "--out",
       "o", "--scenes", "scene-nope"),
    _c("ingest", "nuscenes root without tables", "ingest", "--source", "nuscenes", "--dataroot", "{empty}",
       "--out", "o"),
    _c("ingest", "kitti root without sequences", "ingest", "--source", "kitti", "--dataroot", "{empty}", "--out",
       "o"),
    _c("ingest", "waymo root without segments", "ingest", "--source", "waymo-v2", "--dataroot", "{empty}", "--out",
       "o"),
    _c("ingest", "--out under a file", "ingest", "--source", "nuscenes", "--dataroot", "{nus}", "--out",
       "{file}/o"),
    _c("ingest", "unknown camera", "ingest", "--source", "nuscenes", "--dataroot", "{nus}", "--out", "o",
       "--cameras", "CAM_NOPE"),
    _c("ingest", "unknown version", "ingest", "--source", "nuscenes", "--dataroot", "{nus}", "--out", "o",
       "--version", "v9.9"),
    _c("ingest", "a file as root", "ingest", "--source", "kitti", "--dataroot", "{file}", "--out", "o"),
    # --------------------------------------------------------------- fit / render
    _c("fit/render", "fit: not a store", "fit", "{file}", "--out", "m"),
    _c("fit/render", "fit: store that does not exist", "fit", "/nonexistent", "--out", "m"),
    _c("fit/render", "fit: unknown preset", "fit", "{store}", "--out", "m", "--preset", "best"),
    _c("fit/render", "fit: zero iterations", "fit", "{store}", "--out", "m", "--iterations", "0"),
    _c("fit/render", "fit: negative iterations", "fit", "{store}", "--out", "m", "--iterations", "-3"),
    _c("fit/render", "fit: --threads 0", "fit", "{store}", "--out", "m", "--threads", "0"),
    _c("fit/render", "fit: --threads negative", "fit", "{store}", "--out", "m", "--threads", "-1"),
    _c("fit/render", "fit: negative variants", "fit", "{store}", "--out", "m", "--behavior-variants", "-1"),
    _c("fit/render", "fit: unknown device", "fit", "{store}", "--out", "m", "--device", "tpu"),
    _c("fit/render", "fit: --overwrite of a user's folder", "fit", "{store}", "--out", "{userdir}", "--overwrite"),
    _c("fit/render", "fit: --out under a file", "fit", "{store}", "--out", "{file}/m"),
    _c("fit/render", "fit: manifest is a list", "fit", "{mlist}", "--out", "m"),
    _c("fit/render", "fit: scene_id ../../x", "fit", "{badid}", "--out", "m"),
    _c("fit/render", "fit: workspace is a file", "fit", "{store}", "--out", "m", "--workspace", "{file}"),
    _c("fit/render", "render: not a checkpoint", "render", "{notckpt}", "--out", "r.png"),
    _c("fit/render", "render: checkpoint that does not exist", "render", "/nonexistent", "--out", "r.png"),
    _c("fit/render", "render: --out not a PNG", "render", "{notckpt}", "--out", "r.jpg"),
    _c("fit/render", "render: ego pose of two numbers", "render", "{notckpt}", "--out", "r.png", "--ego-pose",
       "1,2"),
    _c("fit/render", "render: ego pose of words", "render", "{notckpt}", "--out", "r.png", "--ego-pose",
       "a,b,c,d"),
    _c("fit/render", "render: a file as checkpoint", "render", "{file}", "--out", "r.png"),
    # --------------------------------------------------------------- scs
    _c("scs", "train: unknown preset", "scs", "train-behavior", "--out", "t", "--preset", "best"),
    _c("scs", "train: zero worlds", "scs", "train-behavior", "--out", "t", "--worlds", "0"),
    _c("scs", "train: negative steps", "scs", "train-behavior", "--out", "t", "--steps", "-1"),
    _c("scs", "train: --threads 0", "scs", "train-behavior", "--out", "t", "--threads", "0"),
    _c("scs", "train: --overwrite of a user's folder", "scs", "train-behavior", "--out", "{userdir}",
       "--overwrite"),
    _c("scs", "train: scene that does not exist", "scs", "train-behavior", "--out", "t", "--scene",
       "/nonexistent"),
    _c("scs", "train: negative seed", "scs", "train-behavior", "--out", "t", "--seed", "-1"),
    _c("scs", "behavior: unknown template", "scs", "behavior", "syn:nope:1", "--out", "v"),
    _c("scs", "behavior: zero variants", "scs", "behavior", "{store}", "--out", "v", "--variants", "0"),
    _c("scs", "behavior: negative variants", "scs", "behavior", "{store}", "--out", "v", "--variants", "-2"),
    _c("scs", "behavior: unknown preset", "scs", "behavior", "{store}", "--out", "v", "--preset", "ultra"),
    _c("scs", "behavior: unknown planner", "scs", "behavior", "{store}", "--out", "v", "--planner", "psychic"),
    _c("scs", "behavior: --threads 0", "scs", "behavior", "{store}", "--out", "v", "--threads", "0"),
    _c("scs", "behavior: truncated checkpoint", "scs", "behavior", "{store}", "--out", "v", "--checkpoint",
       "{bckpt_trunc}"),
    _c("scs", "behavior: --nsg not a checkpoint", "scs", "behavior", "{store}", "--out", "v", "--nsg",
       "{notckpt}"),
    _c("scs", "behavior: zero app frames", "scs", "behavior", "{store}", "--out", "v", "--app-frames", "0"),
    _c("scs", "behavior: zero app downscale", "scs", "behavior", "{store}", "--out", "v", "--app-downscale", "0"),
    _c("scs", "behavior: zero frames of a syn log", "scs", "behavior", "syn:straight:0", "--out", "v", "--frames",
       "0"),
    _c("scs", "behavior: --out under a file", "scs", "behavior", "{store}", "--out", "{file}/v"),
    _c("scs", "behavior: damaged store", "scs", "behavior", "{wrongcol}", "--out", "v"),
    # --------------------------------------------------------------- scene info / preview
    _c("scene", "info: does not exist", "scene", "info", "/nonexistent"),
    _c("scene", "info: a file", "scene", "info", "{file}"),
    _c("scene", "info: manifest is a list", "scene", "info", "{mlist}"),
    _c("scene", "info: wrong column type", "scene", "info", "{wrongcol}"),
    _c("scene", "info: scene_id ../../x", "scene", "info", "{badid}"),
    _c("scene", "info: truncated LiDAR", "scene", "info", "{trunclidar}"),
    _c("scene", "preview: --out under a file", "scene", "preview", "{store}", "--out", "{file}/p"),
    _c("scene", "preview: does not exist", "scene", "preview", "/nonexistent"),
    # --------------------------------------------------------------- catalog
    _c("catalog", "empty SQL", "catalog", "query", "", "--workspace", "{ws}"),
    _c("catalog", "blank SQL", "catalog", "query", "   ", "--workspace", "{ws}"),
    _c("catalog", "COPY ... TO", "catalog", "query", "COPY (SELECT 1) TO 'x.csv'", "--workspace", "{ws}"),
    _c("catalog", "ATTACH", "catalog", "query", "ATTACH 'x.db'", "--workspace", "{ws}"),
    _c("catalog", "read_csv('/etc/passwd')", "catalog", "query", "SELECT * FROM read_csv('/etc/passwd')",
       "--workspace", "{ws}"),
    _c("catalog", "glob('/root/*')", "catalog", "query", "SELECT * FROM glob('/root/*')", "--workspace", "{ws}"),
    _c("catalog", "two statements", "catalog", "query", "SELECT 1; SELECT 2", "--workspace", "{ws}"),
    _c("catalog", "DROP VIEW", "catalog", "query", "DROP VIEW scenes", "--workspace", "{ws}"),
    _c("catalog", "INSTALL", "catalog", "query", "INSTALL httpfs", "--workspace", "{ws}"),
    _c("catalog", "SET", "catalog", "query", "SET enable_external_access = true", "--workspace", "{ws}"),
    _c("catalog", "unknown table", "catalog", "query", "SELECT * FROM nope", "--workspace", "{ws}"),
    _c("catalog", "syntax error", "catalog", "query", "SELEC 1", "--workspace", "{ws}"),
    _c("catalog", "markup in a bad query", "catalog", "query", "SELECT [bold] FROM :x:", "--workspace", "{ws}"),
    _c("catalog", "workspace that does not exist", "catalog", "query", "SELECT 1", "--workspace", "{tmp}/nope"),
    _c("catalog", "default workspace missing", "catalog", "query", "SELECT 1"),
    _c("catalog", "views: workspace that does not exist", "catalog", "views", "--workspace", "{tmp}/nope"),
    # --------------------------------------------------------------- hostile JSON (on the command line and in files)
    _c("hostile JSON", "edit nested 100,000 deep", *GEN, "--edit", "[" * 100_000),
    _c("hostile JSON", "edit with a 5000-digit track id", *GEN, "--edit", HUGE_TRACK),
    _c("hostile JSON", "edit amount 1e400", *GEN, "--edit", '{"op": "translate", "track_id": 1, "lateral": 1e400}'),
    _c("hostile JSON", "world render: edit yaw -Infinity", "world", "render", "{store}", "--out", "x.png", "--edit",
       '{"op": "rotate", "track_id": 1, "yaw_deg": -Infinity}'),
    _c("hostile JSON", "fit: edit file nested deep", "fit", "{store}", "--out", "m", "--edit", "@{deepjson}"),
    _c("hostile JSON", "edit file not UTF-8", *GEN, "--edit", "@{latin1json}"),
    _c("hostile JSON", "scene info: manifest nested deep", "scene", "info", "{mdeep}"),
    _c("hostile JSON", "generate: manifest with a 5000-digit number", "generate", "{mbigint}"),
    _c("hostile JSON", "fit: manifest not UTF-8", "fit", "{mlatin1}", "--out", "m"),
    _c("hostile JSON", "world render: world.json nested deep", "world", "render", "{worlddeep}", "--out", "x.png"),
    _c("hostile JSON", "eval detection: results nested deep", "eval", "detection", *NUS_EVAL,
       "--results", "{deepjson}"),
    _c("hostile JSON", "eval detection: results with an Infinity velocity", "eval", "detection", *NUS_EVAL,
       "--results", "{infjson}"),
    _c("hostile JSON", "eval planning: results with a 5000-digit number", "eval", "planning", *NUS_EVAL,
       "--results", "{bigintjson}"),
    _c("hostile JSON", "ingest: nuScenes table nested deep", "ingest", "--source", "nuscenes", "--dataroot",
       "{nusdeep}", "--out", "o"),
    _c("hostile JSON", "eval: nuScenes sample chain that loops", "eval", "detection", "--dataroot", "{nusloop}",
       "--version", NUS_VERSION, "--results", "{emptyresults}"),
    _c("hostile JSON", "generate: nuScenes sample chain that loops", "generate", "nuscenes:{nusloop}"),
    _c("hostile JSON", "dataset info: card nested deep", "dataset", "info", "{dsdeep}"),
    # --------------------------------------------------------------- hostile files (not regular, junk, foreign)
    _c("hostile files", "eval detection: results are /dev/zero", "eval", "detection", *NUS_EVAL,
       "--results", "/dev/zero"),
    _c("hostile files", "eval planning: results are a FIFO", "eval", "planning", *NUS_EVAL,
       "--results", "{fifo}"),
    _c("hostile files", "eval detection: results are a folder", "eval", "detection", *NUS_EVAL,
       "--results", "{empty}"),
    _c("hostile files", "edit file is /dev/zero", *GEN, "--edit", "@/dev/zero"),
    _c("hostile files", "world render: edit file is a FIFO", "world", "render", "{store}", "--out", "x.png",
       "--edit", "@{fifo}"),
    _c("hostile files", "scene info: manifest is a FIFO", "scene", "info", "{mfifo}"),
    _c("hostile files", "eval: nuScenes table is a FIFO", "eval", "detection", "--dataroot", "{nusfifo}",
       "--version", NUS_VERSION, "--results", "{emptyresults}"),
    _c("hostile files", "ingest: nuScenes table is a FIFO", "ingest", "--source", "nuscenes", "--dataroot",
       "{nusfifo}", "--out", "o"),
    _c("hostile files", "catalog: junk Parquet file", "catalog", "query", "SELECT * FROM runs", "--workspace",
       "{wsjunk}"),
    _c("hostile files", "catalog: truncated Parquet file", "catalog", "query", "SELECT count(*) FROM runs_raw",
       "--workspace", "{wstrunc}"),
    _c("hostile files", "catalog: foreign Parquet file", "catalog", "query", "SELECT * FROM runs_raw",
       "--workspace", "{wsforeign}"),
    _c("hostile files", "pool list: junk Parquet index file", "pool", "list", "{pooljunk}"),
    _c("hostile files", "pool list: foreign Parquet index file", "pool", "list", "{poolforeign}"),
    # --------------------------------------------------------------- bench (option errors only)
    _c("bench", "world: seeds not numbers", "bench", "world", "--seeds", "abc", "--out", "r"),
    _c("bench", "world: no seeds", "bench", "world", "--seeds", ",", "--out", "r"),
    _c("bench", "plan: scene without seed", "bench", "plan", "--scenes", "straight", "--out", "r"),
    _c("bench", "plan: negative variants", "bench", "plan", "--variants", "-1", "--out", "r"),
    _c("bench", "plan: unknown preset", "bench", "plan", "--preset", "best", "--out", "r"),
    _c("bench", "reliability: zero kills", "bench", "reliability", "--kills", "0", "--out", "r"),
    _c("bench", "reliability: one process", "bench", "reliability", "--processes", "1", "--out", "r"),
    _c("bench", "unknown benchmark", "bench", "nope"),
)

#: Paths (links, names, writability) and the benchmarks' counts: cases of their own, after the table above.
CASES += (
    # --------------------------------------------------------------- paths: links, names, writability
    _c("paths", "--out is a link to nothing", "world", "make", "--out", "{dangling}"),
    _c("paths", "--out under a link to nothing", "world", "make", "--out", "{dangling}/store"),
    _c("paths", "--out is a link to a folder, --overwrite", "world", "make", "--out", "{linkdir}", "--overwrite"),
    _c("paths", "export onto a link to nothing", "world", "export", "{store}", "--format", "nuscenes", "--out",
       "{dangling}"),
    _c("paths", "ingest into a link to nothing", "ingest", "--source", "nuscenes", "--dataroot", "{nus}",
       "--out", "{dangling}"),
    _c("paths", "a name of 300 bytes", "world", "make", "--out", "{tmp}/" + "n" * 300),
    _c("paths", "a name that leaves no room for the temporary", "world", "make", "--out", "{tmp}/" + "n" * 240),
    _c("paths", "a path of 5000 bytes", "world", "export", "{store}", "--format", "kitti", "--out",
       "{tmp}/" + "/".join(["p" * 200] * 25)),
    _c("paths", "--out under /proc", "world", "make", "--out", "/proc/omniscs-out"),
    _c("paths", "export under /sys", "world", "export", "{store}", "--format", "nuscenes", "--out",
       "/sys/omniscs-out"),
    _c("paths", "workspace is a link to nothing", "generate", "syn:straight:0", "--frames", "2", "--workspace",
       "{dangling}"),
    _c("paths", "workspace under a link to nothing", "generate", "syn:straight:0", "--frames", "2", "--workspace",
       "{dangling}/ws"),
    _c("paths", "catalog table that leads out of the workspace", "catalog", "query", "SELECT count(*) FROM runs",
       "--workspace", "{wscatlink}"),
    # --------------------------------------------------------------- counts and seeds of the benchmarks
    _c("numbers", "bench seeds in Arabic-Indic digits", "bench", "world", "--seeds", "\u0665", "--out", "{tmp}/r"),
    _c("numbers", "bench seed beyond 2^32", "bench", "world", "--seeds", "0,4294967296", "--out", "{tmp}/r"),
    _c("numbers", "bench threads 100000", "bench", "behavior", "--threads", "100000", "--out", "{tmp}/r"),
    _c("numbers", "bench seed offset negative", "bench", "behavior", "--seed-offset", "-5", "--out", "{tmp}/r"),
    _c("numbers", "reliability seed beyond 2^32", "bench", "reliability", "--seed", "99999999999", "--out",
       "{tmp}/r"),
    # --------------------------------------------------------------- closed loop: options checked before Prefect starts
    _c("closed loop", "run: --width -5", "closedloop", "run", "syn-x/log", "--width", "-5"),
    _c("closed loop", "run: --run-id ../x", "closedloop", "run", "syn-x/log", "--run-id", "../x"),
    _c("closed loop", "run: --steps 0", "closedloop", "run", "syn-x/log", "--steps", "0"),
    _c("closed loop", "run: a scenario of no scene", "closedloop", "run", "nope/log", "--workspace", "{ws}"),
    _c("closed loop", "serve: --port 70000", "closedloop", "serve", "--scenario", "syn-x/log", "--port", "70000",
       "--token", "t"),
    _c("closed loop", "serve: --port -1", "closedloop", "serve", "--scenario", "syn-x/log", "--port", "-1", "--token",
       "t"),
    _c("closed loop", "serve: a token file that does not exist", "closedloop", "serve", "--scenario", "syn-x/log",
       "--token-file", "{tmp}/nope"),
    _c("numbers", "eval: a box size of 1e300", "eval", "detection", *NUS_EVAL, "--results", "{ressize}"),
    _c("numbers", "eval: sizes given as strings", "eval", "detection", *NUS_EVAL, "--results", "{resstring}"),
    _c("numbers", "eval: a boolean score", "eval", "detection", *NUS_EVAL, "--results", "{resbool}"),
    _c("numbers", "eval: a quaternion of norm 1e-30", "eval", "detection", *NUS_EVAL, "--results", "{resquat}"),
    _c("numbers", "eval: a score of 7", "eval", "detection", *NUS_EVAL, "--results", "{resscore}"),
    _c("numbers", "pool import: log-scales of 80 (5e34 m Gaussians)", "pool", "import", "{plyhuge}/model.ply",
       "--category", "car", "--pool", "{tmp}/pool"),
)


# ----------------------------------------------------------------------------- fixtures
#: Fixtures of the number cases: detection results with a size of 1e300, sizes as strings, a boolean score, a
#: near-zero quaternion, a score of 7; a PLY whose log-scales hold 80.
NUMBER_FIXTURES = ("ressize", "resstring", "resbool", "resquat", "resscore", "plyhuge")
#: Fixtures of the path cases: a link to nothing (inside the case's folder, so a folder made through it shows), a
#: link to a folder, and a workspace whose catalog table is a link out of it.
PATH_FIXTURES = ("dangling", "linkdir", "wscatlink")


def path_fixture(name: str, path: Path) -> Path:
    """Path fixture ``name`` at ``path``."""
    if name == "dangling":
        os.symlink(path.parent / "nowhere", path)
    elif name == "linkdir":
        (path.parent / "realdir").mkdir()
        os.symlink(path.parent / "realdir", path)
    elif name == "wscatlink":
        catalog_run_stage("fixture-run", path, "generate_dataset", "completed", 0, 1, 0, {})
        runs = path / "catalog" / "runs"
        shutil.move(str(runs), str(path.parent / "elsewhere"))
        os.symlink(path.parent / "elsewhere", runs)
    else:
        raise KeyError(name)
    return path


class Fixtures:
    """The files the cases point at, made once per table run in ``root`` and copied into each case's folder."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.store = write_synthetic_scene(SyntheticSource("straight", 3, n_frames=3, n_cameras=1, width=32,
                                                           height=18), root / "store")

        self.nus = Path(export_scenes([self.store], "nuscenes", root / "nus"))

    def number_fixture(self, name: str, path: Path) -> None:
        """Results files whose numbers are JSON but wrong, and a PLY whose log-scales are sizes."""
        if name == "plyhuge":
            g = torch.Generator().manual_seed(0)
            params = GaussianParams(torch.randn(50, 3, generator=g), torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(50, 1),
                                    torch.full((50, 3), 80.0), torch.zeros(50), torch.rand(50, 3, generator=g),
                                    torch.zeros(50, 0, 3))
            path.mkdir()
            write_gaussian_ply(params, path / "model.ply")  # a folder holding it: the suffix says it is a splat
            return
        samples = json.loads((self.nus / NUS_VERSION / "sample.json").read_text())
        box = {"sample_token": samples[0]["token"], "translation": [1.0, 2.0, 0.5], "size": [1.8, 4.5, 1.6],
               "rotation": [1.0, 0.0, 0.0, 0.0], "velocity": [0.0, 0.0], "detection_name": "car",
               "detection_score": 0.5, "attribute_name": ""}
        box.update({"ressize": {"size": [1.8, 1e300, 1.6]}, "resstring": {"size": ["1.8", "4.5", "1.6"]},
                    "resbool": {"detection_score": True}, "resquat": {"rotation": [1e-30, 0.0, 0.0, 0.0]},
                    "resscore": {"detection_score": 7.0}}[name])
        results = {s["token"]: [] for s in samples}
        results[samples[0]["token"]] = [box]
        path.write_text(json.dumps({"meta": {"use_camera": True}, "results": results}))

    def make(self, name: str, case_dir: Path) -> Path:
        """Fixture ``name`` inside ``case_dir`` (made fresh: a case may damage it further)."""
        path = case_dir / name
        if name in PATH_FIXTURES:
            return path_fixture(name, path)
        if name in ("store", "badid", "badpng", "trunclidar", "mlist", "mgarbage", "wrongcol", "noimage"):
            shutil.copytree(self.store, path)
            manifest = path / "manifest.json"
            if name == "badid":
                m = json.loads(manifest.read_text())
                m["scene_id"] = "../../x"
                manifest.write_text(json.dumps(m))
            elif name == "badpng":
                png = sorted((path / "images").rglob("*.png"))[0]
                data = bytearray(png.read_bytes())
                data[len(data) // 2:len(data) // 2 + 16] = bytes(16)
                png.write_bytes(bytes(data))
            elif name == "trunclidar":
                npy = sorted((path / "lidar").glob("*"))[0]
                npy.write_bytes(npy.read_bytes()[: npy.stat().st_size // 2])
            elif name == "mlist":
                manifest.write_text("[]")
            elif name == "mgarbage":
                manifest.write_text("{not json")
            elif name == "wrongcol":
                table = pq.read_table(path / "frames.parquet")
                i = table.column_names.index("timestamp_us")
                table = table.set_column(i, "timestamp_us", pa.array([str(v) for v in table.column(i).to_pylist()]))
                pq.write_table(table, path / "frames.parquet")
            elif name == "noimage":
                sorted((path / "images").rglob("*.png"))[0].unlink()
        elif name in ("mdeep", "mbigint", "mlatin1", "mfifo", "worlddeep"):
            shutil.copytree(self.store, path)
            manifest = path / "manifest.json"
            if name == "mdeep":
                manifest.write_bytes(DEEP)
            elif name == "mbigint":
                m = json.loads(manifest.read_text())
                manifest.write_text(json.dumps(m)[:-1] + ', "seed": ' + "9" * 5000 + "}")
            elif name == "mlatin1":  # the scene id in Latin-1, as an editor set to it would save it
                m = json.loads(manifest.read_text())
                m["scene_id"] = "caf\u00e9"
                manifest.write_bytes(json.dumps(m, ensure_ascii=False).encode("latin-1"))
            elif name == "mfifo":
                manifest.unlink()
                os.mkfifo(manifest)
            else:  # with its size and hash updated in the manifest, as a careful attacker would
                (path / "world.json").write_bytes(DEEP)
                m = json.loads(manifest.read_text())
                m["files"]["world.json"] = [len(DEEP), hashlib.sha256(DEEP).hexdigest()]
                manifest.write_text(json.dumps(m))
        elif name == "nus":
            shutil.copytree(self.nus, path)
        elif name in ("nusdeep", "nusloop", "nusfifo"):
            shutil.copytree(self.nus, path)
            tables = next(path.glob("v1.0-*"))
            if name == "nusdeep":
                (tables / "sample.json").write_bytes(DEEP)
            elif name == "nusloop":  # the scene's last keyframe leads back to its first
                rows = json.loads((tables / "sample.json").read_text())
                last = next(r for r in rows if not r["next"])
                last["next"] = next(r for r in rows if not r["prev"])["token"]
                (tables / "sample.json").write_text(json.dumps(rows))
            else:
                (tables / "sample_annotation.json").unlink()
                os.mkfifo(tables / "sample_annotation.json")
        elif name == "deepjson":
            path.write_bytes(DEEP)
        elif name == "bigintjson":
            path.write_text('{"results": {}, "n": ' + "1" * 5000 + "}")
        elif name == "infjson":
            path.write_text('{"results": {"t": [{"velocity": [Infinity, 0.0]}]}}')
        elif name in NUMBER_FIXTURES:
            self.number_fixture(name, path)
        elif name == "emptyresults":
            path.write_text('{"results": {}}')
        elif name == "latin1json":
            path.write_bytes('[{"op": "remove", "track_id": 1, "why": "caf\u00e9"}]'.encode("latin-1"))
        elif name == "fifo":
            os.mkfifo(path)
        elif name == "dsdeep":
            path.mkdir()
            (path / "dataset.json").write_bytes(DEEP)
        elif name in ("wsjunk", "wstrunc", "wsforeign"):
            catalog_run_stage("fixture-run", path, "generate_dataset", "completed", 0, 1, 0, {})
            files = sorted((path / "catalog" / "runs").rglob("*.parquet"))
            bad = files[0].parent / "run-0000000000000001-000000000000.parquet"
            if name == "wsjunk":
                bad.write_text("run_id,status\nx,completed\n")
            elif name == "wstrunc":
                bad.write_bytes(files[0].read_bytes()[:-20])
            else:  # a real Parquet file with someone else's columns: it must not show as a run
                pq.write_table(pa.table({"status": ["completed"], "card_number": ["4111 1111 1111 1111"]}), bad)
        elif name in ("pooljunk", "poolforeign"):
            index = path / "index"
            index.mkdir(parents=True)
            if name == "pooljunk":
                (index / "pm-000000000000.parquet").write_bytes(b"\x00" * 64)
            else:
                pq.write_table(pa.table({"model_id": ["pm-000000000000"], "owner": ["someone else"]}),
                               index / "pm-000000000000.parquet")
        elif name == "file":
            path.write_text("this is a file, not a folder {\n")
        elif name == "empty":
            path.mkdir()
        elif name == "userdir":
            path.mkdir()
            (path / "thesis.tex").write_text("years of work\n")
        elif name == "notckpt":
            path.mkdir()
            (path / "notes.txt").write_text("not a checkpoint\n")
        elif name == "bckpt_trunc":
            shutil.copytree(DEFAULT_CHECKPOINT, path)
            biggest = max((p for p in path.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
            biggest.write_bytes(biggest.read_bytes()[: biggest.stat().st_size // 3])
        elif name == "ws":
            catalog_run_stage("fixture-run", path, "generate_dataset", "completed", 0, 1, 0, {})
            (path / "outside.txt").write_text("secret beside the catalog\n")
        else:
            raise KeyError(name)
        return path


#: The fixtures a case may name as ``{name}`` in its argv (``{tmp}`` is the case's folder itself).
FIXTURES = ("store", "badid", "badpng", "trunclidar", "mlist", "mgarbage", "wrongcol", "noimage", "nus", "file",
            "empty", "userdir", "notckpt", "bckpt_trunc", "ws",
            # hostile JSON and files
            "mdeep", "mbigint", "mlatin1", "mfifo", "worlddeep", "nusdeep", "nusloop", "nusfifo", "deepjson",
            "bigintjson", "infjson", "emptyresults", "latin1json", "fifo", "dsdeep", "wsjunk", "wstrunc", "wsforeign",
            "pooljunk", "poolforeign")
FIXTURES += PATH_FIXTURES + NUMBER_FIXTURES
_PLACEHOLDER = re.compile(r"\{(" + "|".join(FIXTURES + ("tmp",)) + r")\}")


def _placeholders(argv: tuple[str, ...]) -> list[str]:
    names = []
    for arg in argv:
        for name in _PLACEHOLDER.findall(arg):
            if name != "tmp" and name not in names:
                names.append(name)
    return names


# ----------------------------------------------------------------------------- running one case
@dataclass(frozen=True)
class Outcome:
    case: str
    category: str
    outcome: str
    exit_code: int | None
    stderr: str
    stdout_lines: int
    new_files: tuple[str, ...]


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            try:
                st = p.lstat()
            except OSError:
                continue
            out[p.relative_to(root).as_posix()] = (st.st_size if p.is_file() else -1, st.st_mtime_ns)
    return out


@contextlib.contextmanager
def _environment(cwd: Path, env: dict[str, str]) -> Iterator[None]:
    old_cwd, old_env, old_argv = os.getcwd(), dict(os.environ), list(sys.argv)
    os.chdir(cwd)
    os.environ.update(env)
    try:
        yield
    finally:
        os.chdir(old_cwd)
        os.environ.clear()
        os.environ.update(old_env)
        sys.argv = old_argv


def console_main():
    """The function the installed ``omniscs`` console script calls (the project's entry point, found through the
    package metadata: the bench exercises what a user runs, and the CLI that offers the bench is not imported
    back)."""
    found = entry_points(group="console_scripts", name="omniscs")
    if not found:
        raise RuntimeError("the omniscs console script is not installed in this environment; install the project "
                           "(pip install -e .) before the bad-inputs benchmark")
    return next(iter(found)).load()


def invoke(argv: list[str], cwd: Path, env: dict[str, str]) -> tuple[int | None, str, str, bool]:
    """Run ``omniscs argv`` in this process as the console script does; returns exit code, stdout, stderr and
    whether an exception escaped ``main`` (a traceback the user would see)."""
    main = console_main()

    out, err = io.StringIO(), io.StringIO()
    escaped = False
    code: int | None = 0

    def too_long(signum, frame):
        raise CaseRanTooLong(f"still running after {CASE_LIMIT_S:.0f} s: the bad input was accepted and real work "
                             "started")

    previous = signal.signal(signal.SIGALRM, too_long)
    with _environment(cwd, env), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        sys.argv = ["omniscs", *argv]
        signal.setitimer(signal.ITIMER_REAL, CASE_LIMIT_S)
        try:
            main()
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except CaseRanTooLong as exc:
            code = 0  # accepted: the command was doing real work with the bad input
            print(f"(harness) {exc}", file=err)
        except BaseException:  # noqa: BLE001 - an escaped exception is what this harness looks for
            escaped = True
            code = 1
            traceback.print_exc(file=err)
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, previous)
    return code, out.getvalue(), err.getvalue(), escaped


#: Longest a case may run in process: a bad input is refused in well under a second, so a case still running
#: after this was accepted (and started real work, e.g. a training run).
CASE_LIMIT_S = 30.0


class CaseRanTooLong(Exception):
    """Raised in a case that ran past ``CASE_LIMIT_S``."""


def invoke_subprocess(argv: list[str], cwd: Path, env: dict[str, str]) -> tuple[int | None, str, str, bool]:
    """The same through a new ``omniscs`` process (slower: the import alone takes seconds)."""
    try:
        proc = subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", *argv], cwd=cwd,
                              env={**os.environ, **env}, capture_output=True, text=True,
                              timeout=CASE_LIMIT_S + 30)  # + the import of a fresh process
    except subprocess.TimeoutExpired as exc:
        return 0, "", f"(harness) still running after {exc.timeout:.0f} s: the bad input was accepted", False
    return proc.returncode, proc.stdout, proc.stderr, False


def classify(code: int | None, stdout: str, stderr: str, escaped: bool, new_files: list[str]) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    if escaped or "Traceback (most recent call last)" in stderr + stdout:
        return "traceback"
    if code == 0:
        return "silently wrong"
    if new_files:
        return "left files"
    if code == 2 and len(lines) == 1 and lines[0].startswith("error: "):
        return "one clear line"
    return "other"


def run_case(case: Case, fixtures: Fixtures, tmp: Path, subprocess_mode: bool = False) -> Outcome:
    """Run one case in a fresh folder ``tmp`` (its working directory; its workspace is ``tmp/ws`` unless the case
    names one) and classify what happened."""
    tmp.mkdir(parents=True, exist_ok=True)
    values = {"tmp": str(tmp)}
    for name in _placeholders(case.argv):
        values[name] = str(fixtures.make(name, tmp))
    argv = [_PLACEHOLDER.sub(lambda m: values[m.group(1)], a) for a in case.argv]
    env = {"OMNISCS_HOME": str(tmp / "omniscs-data"), "PREFECT_LOGGING_LEVEL": "WARNING",
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "COLUMNS": "200"}
    before = _snapshot(tmp)
    code, stdout, stderr, escaped = (invoke_subprocess if subprocess_mode else invoke)(argv, tmp, env)
    after = _snapshot(tmp)
    new = sorted(k for k in after if k not in before or after[k] != before[k])
    new += sorted(f"(removed) {k}" for k in before if k not in after)
    return Outcome(case.id, case.category, classify(code, stdout, stderr, escaped, new), code, stderr.strip(),
                   len(stdout.splitlines()), tuple(new[:10]))


# ----------------------------------------------------------------------------- the table
def run_table(cases: tuple[Case, ...] = CASES, subprocess_mode: bool = False,
              progress: Progress = no_progress) -> list[Outcome]:
    with tempfile.TemporaryDirectory(prefix="omniscs-bad-inputs-") as tmp:
        fixtures = Fixtures(Path(tmp) / "fixtures")
        outcomes = []
        for i, case in enumerate(cases):
            outcomes.append(run_case(case, fixtures, Path(tmp) / f"case-{i:03d}", subprocess_mode))
            progress(i + 1, len(cases), case.id)
    return outcomes


def summary(outcomes: list[Outcome]) -> list[dict]:
    """Per category (and in total): tried and how many ended in each outcome."""
    rows = []
    for category in list(dict.fromkeys(o.category for o in outcomes)) + ["all"]:
        chosen = [o for o in outcomes if category in ("all", o.category)]
        rows.append({"category": category, "tried": len(chosen),
                     **{k: sum(o.outcome == k for o in chosen) for k in OUTCOMES}})
    return rows


def run_bench(out_dir: str | Path = "reports", subprocess_mode: bool = False,
              progress: Progress = no_progress) -> dict:
    machine = machine_info()
    outcomes = run_table(subprocess_mode=subprocess_mode, progress=progress)
    server_abuse = run_server_abuse(progress=progress)  # its own section: requests to the server, not argv
    report = {"mode": "subprocess" if subprocess_mode else "in-process", "machine": finish(machine),
              "summary": summary(outcomes), "cases": [o.__dict__ for o in outcomes], "server_abuse": server_abuse}
    write_report(out_dir, "bad-inputs", report, markdown(report))
    return report


def markdown(report: dict) -> str:
    lines = ["# Bad inputs: every command, one clear line each", "",
             f"{report['summary'][-1]['tried']} bad inputs over every command (`omniscs.bench.bad_inputs.CASES`), "
             f"run {report['mode']} as the console script runs them, each in a fresh folder that is also its "
             "working directory and workspace. Expected for every case: exit code 2, one `error:` line on stderr, "
             "no traceback, nothing new on disk.", "",
             "| category | tried | " + " | ".join(OUTCOMES) + " |", "|---|---|" + "---|" * len(OUTCOMES)]
    for row in report["summary"]:
        name = f"**{row['category']}**" if row["category"] == "all" else row["category"]
        lines.append(f"| {name} | {row['tried']} | " + " | ".join(str(row[k]) for k in OUTCOMES) + " |")
    bad = [c for c in report["cases"] if c["outcome"] != "one clear line"]
    lines += ["", f"Cases not ending in one clear line: {len(bad)}."]
    for c in bad:
        lines.append(f"- {c['case']}: {c['outcome']} (exit {c['exit_code']}): "
                     f"`{c['stderr'].splitlines()[-1][:200] if c['stderr'] else ''}` {list(c['new_files'])}")
    lines += ["", "Every error line, as a user sees it:", "", "| case | error line |", "|---|---|"]
    for c in report["cases"]:
        if c["outcome"] == "one clear line":
            text = c["stderr"].replace("|", "\\|")
            lines.append(f"| {c['case']} | `{text[:240]}` |")
    if "server_abuse" in report:
        lines += server_markdown(report["server_abuse"])
    lines += ["", load_line(report["machine"]), ""]
    return "\n".join(lines)
