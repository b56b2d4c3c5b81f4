"""The run's request is defined once (``RunRequest``) and the per-scene pipeline once (``STAGES``): every field reaches
the command line and the flow, and every walker goes through the same table."""
from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from omniscs.cli import app
from omniscs.cli import generate as cli_generate
from omniscs.errors import OmniscsError
from omniscs.pipeline import stages
from omniscs.pipeline.records import StageRecord
from omniscs.pipeline.request import RunRequest, SceneRequest

runner = CliRunner()

#: A value for every field, none of them the default, as the command line spells it.
NON_DEFAULT = {
    "sources": ["syn:straight:0", "syn:t_junction:1"], "fit_preset": "fast", "behavior_variants": 3,
    "behavior_preset": "accurate", "behavior_checkpoint": "/ckpt", "edits": [{"op": "remove", "track_id": 4}],
    "previews": False, "device": "cuda:1", "annotate": True, "pool": "/pool", "appearance_variants": 2,
    "appearance_objects": ["pm-a", "pm-b"], "workspace": "/ws", "run_id": "r1", "n_frames": 7, "n_cameras": 2,
    "width": 64, "height": 48, "dataset_id": "ds1", "task_runner": "dask", "workers": 3,
    "dask_address": "tcp://127.0.0.1:8786", "keep_failed": True, "variant_budget": 5, "near_miss_m": 1.5,
    "min_visible_frames": 4, "min_fidelity_psnr": 18.5,
}


def _argv(values: dict) -> list[str]:
    argv = ["generate", *values["sources"]]
    for name, value in values.items():
        flag = cli_generate.option_name(name)
        if name == "sources":
            continue
        if isinstance(value, bool):
            argv.append(flag if value else f"--no-{flag[2:]}")
        elif name == "edits":
            argv += [flag, json.dumps(value)]
        elif isinstance(value, list):
            for v in value:
                argv += [flag, v]
        else:
            argv += [flag, str(value)]
    return argv


def test_the_example_sets_every_field_of_the_request_to_a_non_default_value():
    assert set(NON_DEFAULT) == set(RunRequest.model_fields)
    for name, field in RunRequest.model_fields.items():
        if not field.is_required():
            assert NON_DEFAULT[name] != field.get_default(call_default_factory=True), name


def test_every_request_field_is_an_option_of_generate_with_its_docstring_as_help(monkeypatch):
    monkeypatch.setattr("typer.rich_utils.MAX_WIDTH", 300)  # typer's help ignores the runner's width
    out = runner.invoke(app, ["generate", "--help"], terminal_width=300).output
    for name, field in RunRequest.model_fields.items():
        assert field.description, f"{name} has no docstring"
        if name != "sources":
            assert cli_generate.option_name(name) in out, name


def test_every_request_field_given_on_the_command_line_reaches_the_request(monkeypatch):
    seen = []
    monkeypatch.setattr(cli_generate, "run_generate", lambda request: seen.append(request) or {
        "run_id": "r1", "workspace": "/ws", "scenes": []})
    result = runner.invoke(app, _argv(NON_DEFAULT))
    assert result.exit_code == 0, result.output
    (request,) = seen
    assert isinstance(request, RunRequest)
    assert request.to_dict() == NON_DEFAULT


def test_the_flow_takes_the_request_as_its_one_typed_parameter_with_every_field_in_its_form():
    from prefect.utilities.callables import parameter_schema

    from flows.generate import generate_dataset

    schema = parameter_schema(generate_dataset.fn).model_dump()
    assert list(schema["properties"]) == ["request"]
    (model,) = schema["definitions"].values()
    assert set(model["properties"]) == set(RunRequest.model_fields)
    assert model["properties"]["behavior_variants"]["description"].startswith("Behaviour-level SCS variants")


def test_every_scene_field_of_the_run_reaches_the_scene_request():
    run = RunRequest(**{k: v for k, v in NON_DEFAULT.items()})
    scene = run.scene_request()
    assert type(scene) is SceneRequest
    assert scene.to_dict() == {k: NON_DEFAULT[k] for k in SceneRequest.model_fields}


@pytest.mark.parametrize("fields, message", [
    ({"sources": ["a"], "behavior_variants": "2"}, "behavior_variants: Input should be a valid integer"),
    ({"sources": ["a"], "workers": 0}, "workers: Input should be greater than or equal to 1"),
    ({"sources": ["a"], "annotate": True}, "a dataset renders variants through a scene graph"),
    ({"sources": ["a"], "run_id": "a/b"}, "run id 'a/b' is not a safe id"),
    ({"sources": "syn:straight:0"}, "sources: Input should be a valid list"),
    ({"behavior_variants": 1}, "sources: Field required"),
])
def test_a_bad_request_is_one_line_naming_the_field(fields, message):
    with pytest.raises(OmniscsError, match=message) as info:
        RunRequest.parse(fields)
    assert len(str(info.value).splitlines()) == 1
    with pytest.raises(OmniscsError, match=message):
        RunRequest(**fields)


def test_the_stage_table_is_the_pipeline_in_order():
    assert stages.STAGE_NAMES == ("ingest", "plan", "preview", "fit", "agents", "background", "behavior",
                                  "appearance", "uncovered", "annotate")
    assert [s.name for s in stages.STAGES if s.makes_model] == ["fit", "agents", "background"]
    with pytest.raises(OmniscsError, match="unknown stage 'fitt'"):
        stages.stage("fitt")


class _Plan:
    def __init__(self, **on):
        self.stages = {k: on.get(k, False) for k in ("fit_nsg", "agent_models", "background_repair",
                                                     "behavior_variants", "appearance_variants", "render_annotate")}


def _fake_walk(monkeypatch, plan: _Plan, request: SceneRequest, **walk):
    """Walk the table with a runner that only records which stage ran with which scene graph."""
    monkeypatch.setattr(stages.SceneState, "plan", property(lambda self: plan))
    calls = []

    def call(row, state):
        calls.append((row.name, state.model.stage if state.model is not None else None))
        return StageRecord(row.name, "s", f"/{row.name}")

    state = stages.walk_scene(stages.start_scene("syn:straight:0", request, "/ws"), call, **walk)
    return calls, state


def test_a_walk_runs_what_the_plan_needs_and_hands_each_stage_the_latest_graph(monkeypatch):
    plan = _Plan(fit_nsg=True, agent_models=True, background_repair=True, behavior_variants=True,
                 render_annotate=True)
    calls, state = _fake_walk(monkeypatch, plan, SceneRequest(previews=False))
    assert calls == [("ingest", None), ("plan", None), ("fit", None), ("agents", "fit"), ("background", "agents"),
                     ("behavior", "background"), ("annotate", "background")]
    assert state.model.stage == "background"


def test_annotated_appearance_variants_get_a_repair_of_what_they_uncover_before_annotation(monkeypatch):
    plan = _Plan(fit_nsg=True, appearance_variants=True, render_annotate=True)
    calls, state = _fake_walk(monkeypatch, plan, SceneRequest(previews=False))
    # the repaired graph is for the variants that uncover: the scene graph of the later stages stays the fit's
    assert calls == [("ingest", None), ("plan", None), ("fit", None), ("appearance", "fit"), ("uncovered", "fit"),
                     ("annotate", "fit")]
    assert state.model.stage == "fit" and state.ran("uncovered") is not None
    # without annotation nothing renders the variants: the repair is not needed
    calls, _ = _fake_walk(monkeypatch, _Plan(fit_nsg=True, appearance_variants=True), SceneRequest(previews=False))
    assert [c[0] for c in calls] == ["ingest", "plan", "fit", "appearance"]


def test_a_walk_stops_after_until_and_leaves_out_skipped_stages(monkeypatch):
    plan = _Plan(fit_nsg=True, agent_models=True, background_repair=True, behavior_variants=True)
    calls, _ = _fake_walk(monkeypatch, plan, SceneRequest(), until="background", skip=("agents",))
    assert [c[0] for c in calls] == ["ingest", "plan", "preview", "fit", "background"]
    calls, _ = _fake_walk(monkeypatch, _Plan(), SceneRequest(previews=False))
    assert [c[0] for c in calls] == ["ingest", "plan"]  # nothing asked, nothing modelled
    with pytest.raises(OmniscsError, match="unknown stage"):
        _fake_walk(monkeypatch, plan, SceneRequest(), until="render")


def test_dataset_build_asks_the_flow_for_an_annotated_run(monkeypatch):
    seen = []
    monkeypatch.setattr(cli_generate, "run_generate", lambda request: seen.append(RunRequest.parse(request)) or {
        "dataset_path": "/nowhere"})
    monkeypatch.setattr("omniscs.cli.dataset.show_dataset", lambda path: None)
    result = runner.invoke(app, ["dataset", "build", "syn:straight:3", "--frames", "8", "--out", "ds-mine",
                                 "--keep-failed", "--variant-budget", "4"])
    assert result.exit_code == 0, result.output
    (request,) = seen
    assert (request.sources, request.annotate, request.fit_preset, request.behavior_variants, request.n_frames,
            request.dataset_id, request.previews) == (["syn:straight:3"], True, "fast", 2, 8, "ds-mine", False)
    assert request.keep_failed and request.variant_budget == 4


def test_a_run_is_checked_once_when_the_cli_hands_its_check_to_the_flow_and_afresh_otherwise(monkeypatch):
    from omniscs.pipeline import validate

    checked = []
    monkeypatch.setattr(validate, "check_sources", lambda sources, *rig: checked.append(list(sources)) or ([], []))
    monkeypatch.setattr(validate, "check_request", lambda request: request)
    request = RunRequest(sources=["syn:straight:5"], run_id="once")
    validate.check_run(request, hand_on=True)  # the CLI, before Prefect starts
    validate.check_run(request)  # the flow in the same process takes that check
    assert checked == [["syn:straight:5"]]
    validate.check_run(request)  # a later run of the same request (a served flow, a deployment) checks again
    validate.check_run(request)
    assert len(checked) == 3
