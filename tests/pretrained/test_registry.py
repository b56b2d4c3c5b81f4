"""The registry of shipped weights: every default loads from a registered, hash-checked folder; a changed byte is
refused with one clear error; a user's own weights are not checked; the wheel's package-data covers every file."""
import fnmatch
import json
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from omniscs.errors import OmniscsError
from omniscs.pretrained import registry

ROOT = Path(__file__).resolve().parents[2]
SHIPPED_NAMES = ("behavior", "planner", "detector", "msnet", "reldepth", "inpaint")


def flip_one_byte(path: Path, offset: int = -1) -> None:
    """Change one byte of ``path`` in place (the last by default: inside a weights file's tensor data)."""
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x01
    path.write_bytes(bytes(data))


def test_the_registry_names_the_six_shipped_models_with_their_record_and_command():
    assert tuple(registry.entries()) == SHIPPED_NAMES
    for model in registry.entries().values():
        assert model.folder == registry.WEIGHTS_ROOT / model.name
        assert (model.folder / model.record).is_file(), model.name
        assert model.record in {f.name for f in model.files}
        assert model.command.startswith("omniscs pretrained train " + model.name)
        assert model.seed == 0 and model.data


def test_every_shipped_file_matches_its_registered_hash_and_size():
    for model in registry.entries().values():
        assert registry.mismatches(model) == []
        for f in model.files:
            assert (model.folder / f.name).stat().st_size == f.size


def test_no_shipped_weights_live_outside_the_registry_folder():
    stray = [p for p in (ROOT / "omniscs").rglob("*.safetensors") if registry.WEIGHTS_ROOT not in p.parents]
    assert stray == []
    on_disk = {p.name for p in registry.WEIGHTS_ROOT.iterdir() if p.is_dir()}
    assert on_disk == set(SHIPPED_NAMES)


def test_package_data_covers_every_registered_file():
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    patterns = config["tool"]["setuptools"]["package-data"]["omniscs.pretrained"]
    needed = registry.package_data_patterns()
    uncovered = [path for path in needed if not any(fnmatch.fnmatch(path, p) for p in patterns)]
    assert uncovered == [], f"pyproject.toml package-data misses {uncovered}"


def test_the_check_itself_sees_an_uncovered_file():
    patterns = ["registry.json", "weights/*/*.safetensors"]
    needed = ["weights/planner/planner_config.json"]
    assert [p for p in needed if not any(fnmatch.fnmatch(p, g) for g in patterns)] == needed


@pytest.fixture
def weights_copy(tmp_path, monkeypatch):
    """The registry pointed at a copy of its weights folder (each model's folder copied on demand)."""
    root = tmp_path / "weights"
    root.mkdir()
    monkeypatch.setattr(registry, "WEIGHTS_ROOT", root)

    def copy(name: str) -> Path:
        return Path(shutil.copytree(ROOT / "omniscs/pretrained/weights" / name, root / name))
    return copy


@pytest.mark.parametrize("name", SHIPPED_NAMES)
def test_a_shipped_file_with_one_changed_byte_is_refused_with_one_clear_error(name, weights_copy):
    folder = weights_copy(name)
    model = registry.entry(name)
    weights = next(f for f in model.files if f.name.endswith(".safetensors"))
    registry.load(name)  # the intact copy loads through its default loader
    flip_one_byte(folder / weights.name)
    with pytest.raises(OmniscsError) as err:
        registry.load(name)
    message = str(err.value)
    assert "\n" not in message
    assert str(folder / weights.name) in message and weights.sha256[:registry.PREFIX] in message
    assert model.command in message and "reinstall" in message


def test_the_default_loaders_check_the_shipped_folder_itself(weights_copy):
    from omniscs.eval.planner import load_planner

    folder = weights_copy("planner")
    flip_one_byte(folder / "planner_config.json", offset=0)
    with pytest.raises(OmniscsError, match="planner_config.json has sha256"):
        load_planner(registry.folder("planner"))


def test_a_users_own_weights_are_not_checked_against_the_registry(tmp_path):
    from omniscs.eval.planner import load_planner

    own = Path(shutil.copytree(registry.entry("planner").folder, tmp_path / "my-planner"))
    flip_one_byte(own / "planner.safetensors")  # a different last weight: a different, valid model
    assert registry.shipped_name(own) is None
    load_planner(own)


def test_a_file_is_hashed_once_until_it_changes(tmp_path, monkeypatch):
    path = tmp_path / "w.bin"
    path.write_bytes(b"a" * 1000)
    calls = []
    real = registry.hashlib.sha256
    monkeypatch.setattr(registry.hashlib, "sha256", lambda *a: calls.append(1) or real(*a))
    first = registry.file_sha256(path)
    assert registry.file_sha256(path) == first and len(calls) == 1
    stat = path.stat()
    path.write_bytes(b"b" * 1000)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    assert registry.file_sha256(path) != first and len(calls) == 2


def test_cli_verify_exits_2_with_one_line_on_a_changed_file(tmp_path):
    weights = tmp_path / "pkg" / "omniscs"
    shutil.copytree(ROOT / "omniscs", weights, ignore=shutil.ignore_patterns("__pycache__"))
    flip_one_byte(weights / "pretrained/weights/msnet/msnet.safetensors")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "pkg"), str(ROOT)])}
    proc = subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", "pretrained", "verify"],
                          capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "msnet.safetensors has sha256" in proc.stderr
    ok = subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", "pretrained", "verify"],
                        capture_output=True, text=True, cwd=tmp_path, timeout=120,
                        env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert ok.returncode == 0 and "verified 6" in ok.stdout


@pytest.mark.parametrize("args, message", [
    (["train", "nope"], "no shipped model called 'nope'"),
    (["train", "planner", "--install", "x"], "--export-data and --install are for reldepth and inpaint"),
    (["train", "inpaint"], "inpaint trains on a GPU machine"),
    (["verify", "nope"], "no shipped model called 'nope'"),
])
def test_pretrained_cli_mistakes_are_one_error_and_write_nothing(args, message):
    from typer.testing import CliRunner

    from omniscs.cli import app

    before = {p: p.stat().st_mtime_ns for p in registry.WEIGHTS_ROOT.rglob("*")}
    registry_before = registry.REGISTRY_FILE.read_bytes()
    result = CliRunner().invoke(app, ["pretrained", *args])
    assert result.exit_code != 0 and isinstance(result.exception, OmniscsError)
    assert message in str(result.exception)
    assert {p: p.stat().st_mtime_ns for p in registry.WEIGHTS_ROOT.rglob("*")} == before
    assert registry.REGISTRY_FILE.read_bytes() == registry_before


def test_register_records_new_hashes_of_a_retrained_model(tmp_path, monkeypatch):
    """What ``omniscs pretrained train`` does after a trainer installed new weights: the registry then accepts the
    new files (and only them)."""
    root = tmp_path / "pretrained"
    shutil.copytree(registry.WEIGHTS_ROOT / "planner", root / "weights" / "planner")
    shutil.copy(registry.REGISTRY_FILE, root / "registry.json")
    monkeypatch.setattr(registry, "WEIGHTS_ROOT", root / "weights")
    monkeypatch.setattr(registry, "REGISTRY_FILE", root / "registry.json")
    registry.entries.cache_clear()
    try:
        flip_one_byte(root / "weights" / "planner" / "planner.safetensors")  # "retrained"
        assert registry.mismatches(registry.entry("planner"))
        entry = registry.register("planner")
        assert registry.mismatches(entry) == [] and registry.entry("planner") == entry
        shipped = registry._parse(json.loads((ROOT / "omniscs/pretrained/registry.json").read_text()))
        assert registry.entry("msnet").files == shipped["msnet"].files  # the other entries stay as they were
    finally:
        registry.entries.cache_clear()


@pytest.mark.slow
def test_the_planner_trainer_reproduces_the_shipped_planner_bit_for_bit():
    """The registry's command is honest: the moved trainer makes exactly the shipped weights (2 min on 2 cores)."""
    from safetensors.torch import load_file

    from omniscs.training.planner import train_shipped_planner

    model, record = train_shipped_planner(out=None)
    shipped = load_file(str(registry.entry("planner").folder / "planner.safetensors"))
    state = model.state_dict()
    assert set(state) == set(shipped)
    assert all(state[k].equal(shipped[k]) for k in shipped)
    original = json.loads((registry.entry("planner").folder / "training.json").read_text())
    assert record["epoch_loss_m"] == original["epoch_loss_m"] and record["data"] == original["data"]


def test_weights_that_do_not_fit_the_network_of_their_config_are_one_clear_error(tmp_path):
    import json
    import shutil

    from omniscs.errors import ValidationError
    from omniscs.eval.planner import DEFAULT_PLANNER, load_planner

    folder = tmp_path / "planner"
    shutil.copytree(DEFAULT_PLANNER, folder)
    config = json.loads((folder / "planner_config.json").read_text())
    (folder / "planner_config.json").write_text(json.dumps({**config, "hidden": 2 * config["hidden"]}))
    with pytest.raises(ValidationError, match="the weights do not fit the network of planner_config.json"):
        load_planner(folder)
