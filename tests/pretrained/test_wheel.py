"""A wheel built from the checkout, installed in a fresh virtual environment outside it, loads every shipped model;
a shipped file with one changed byte is then refused with one clear error."""
import os
import shutil
import site
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from omniscs.pretrained import registry

ROOT = Path(__file__).resolve().parents[2]

PROBE = """
import sys
import omniscs
from omniscs.pretrained import registry
assert omniscs.__file__.startswith(sys.prefix), omniscs.__file__
for name in registry.entries():
    registry.load(name)
print("loaded", " ".join(registry.entries()), "from", omniscs.__file__)
"""


def run(*args, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(list(args), capture_output=True, text=True, timeout=900, **kwargs)


@pytest.mark.slow
def test_a_wheel_installed_outside_the_checkout_loads_every_shipped_model(tmp_path):
    source = tmp_path / "source"  # a copy: building writes build/ and *.egg-info into the tree it builds
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(".git", ".venv", "__pycache__", "*.egg-info",
                                                                "build", "dist", "reports", "omniscs-data"))
    wheels = tmp_path / "wheels"
    built = run(sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation", "-w",
                str(wheels))
    assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-2000:]
    wheel = next(wheels.glob("omniscs-*.whl"))
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
    assert {f"omniscs/pretrained/{p}" for p in registry.package_data_patterns()} <= names

    env_dir = tmp_path / "venv"
    made = run(sys.executable, "-m", "venv", "--without-pip", str(env_dir))
    assert made.returncode == 0, made.stderr
    python = env_dir / "bin" / "python"
    own = run(str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])").stdout.strip()
    # the running interpreter's packages (torch & co.) after the new environment's own, without reinstalling them;
    # the checkout's editable install is left out so that omniscs can only come from the wheel
    shared = [p for p in site.getsitepackages() if Path(p).is_dir()]
    (Path(own) / "zz_shared.pth").write_text("\n".join(shared) + "\n")
    installed = run(sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", str(wheel))
    assert installed.returncode == 0, installed.stdout[-2000:] + installed.stderr[-2000:]

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    probe = run(str(python), "-I", "-c", PROBE, cwd=elsewhere, env=env)
    assert probe.returncode == 0, probe.stdout[-3000:] + probe.stderr[-3000:]
    assert "loaded behavior planner detector msnet reldepth inpaint" in probe.stdout
    assert str(env_dir) in probe.stdout

    where = run(str(python), "-I", "-c", "from omniscs.pretrained import registry; print(registry.WEIGHTS_ROOT)",
                cwd=elsewhere, env=env).stdout.strip()
    weights = Path(where) / "detector" / "detector.safetensors"
    data = bytearray(weights.read_bytes())
    data[len(data) // 2] ^= 0x01
    weights.write_bytes(bytes(data))
    refused = run(str(python), "-I", "-c", PROBE, cwd=elsewhere, env=env)
    assert refused.returncode != 0 and "detector.safetensors has sha256" in refused.stderr
    cli = run(str(python), "-I", "-c", "from omniscs.cli import main; main()", "pretrained", "verify",
              cwd=elsewhere, env=env)
    assert cli.returncode == 2 and cli.stderr.strip().count("\n") == 0, cli.stderr
    assert "detector.safetensors" in cli.stderr and "omniscs pretrained train detector" in cli.stderr
