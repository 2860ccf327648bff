"""Nothing writes into the installed package unless asked (`--update-package`).

`calibrate`, `pretrain` and `train` run as a user would, with HOME and XDG_DATA_HOME in a
temporary directory: no file under the package directories changes, the outputs land in
the user data directory (or the given --out), and the readers find them there before the
shipped files. The control runs the same commands with the maintainer flag on a copy of
the packages and sees the shipped files change.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from tests.support import ROOT

PACKAGES = ("noisefeat", "learning", "renderer", "service")
FIXTURE = ROOT / "tests" / "fixtures" / "dataset"
# fast settings: one pre-training step, an SVM without cross-validation or offset calibration
COMMANDS = {
    "calibrate": ["calibrate", "--data", str(FIXTURE)],
    "pretrain": ["pretrain", "--data", str(FIXTURE), "--steps", "1"],
    "train": ["train", "--data", str(FIXTURE), "--model", "dsvm", "--no-cv", "--no-calibrate",
              "--test-scenes", "", "--input", "none"],
}


def tree_hash(root: Path) -> dict[str, str]:
    """SHA-256 of every file of the packages under `root` (bytecode caches aside)."""
    out = {}
    for pkg in PACKAGES:
        for p in sorted((root / pkg).rglob("*")):
            if p.is_file() and "__pycache__" not in p.parts:
                out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def user_env(home: Path, pythonpath: Path = ROOT) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "NOISESTOP_DATA_DIR"}
    env.update(HOME=str(home), XDG_DATA_HOME=str(home / "xdg"), PYTHONPATH=str(pythonpath))
    return env


def cli(args: list[str], env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess:
    out = subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True,
                         env=env, cwd=cwd, timeout=600)
    assert out.returncode == 0, out.stderr
    return out


def data_dir(env: dict[str, str]) -> Path:
    code = "from noisefeat.userdata import user_data_dir; print(user_data_dir())"
    return Path(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                               check=True).stdout.strip())


@pytest.mark.slow
def test_calibrate_pretrain_train_leave_the_package_unchanged(tmp_path: Path) -> None:
    env = user_env(tmp_path / "home")
    before = tree_hash(ROOT)
    cli(COMMANDS["calibrate"], env, tmp_path)
    cli(COMMANDS["pretrain"], env, tmp_path)
    cli([*COMMANDS["train"], "--out", str(tmp_path / "model")], env, tmp_path)
    assert tree_hash(ROOT) == before
    mine = data_dir(env)
    assert mine == tmp_path / "home" / "xdg" / "noisestop"      # $XDG_DATA_HOME/noisestop
    assert (mine / "flip.json").is_file() and (mine / "weights" / "pretrained.safetensors").is_file()
    assert (tmp_path / "model" / "manifest.json").is_file()
    # the readers find the user's files before the shipped ones
    code = ("from learning.inputs.halves import load_flip_calibration; from noisefeat.weights import named_file;"
            "print(load_flip_calibration()['source']); print(named_file('pretrained'))")
    found = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert found.stdout.split() == [str(mine / "flip.json"), str(mine / "weights" / "pretrained.safetensors")]


@pytest.mark.slow
def test_update_package_writes_the_shipped_files_control(tmp_path: Path) -> None:
    """The maintainer flag does write the package (in a copy of it), and nothing to the user."""
    copy = tmp_path / "src"
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, copy / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    env = user_env(tmp_path / "home", pythonpath=copy)
    before = tree_hash(copy)
    cli([*COMMANDS["calibrate"], "--update-package"], env, copy)
    cli([*COMMANDS["pretrain"], "--update-package"], env, copy)
    cli([*COMMANDS["train"], "--update-package"], env, copy)
    after = tree_hash(copy)
    changed = {k for k in after if before.get(k) != after[k]}
    assert {"learning/flip.json", "noisefeat/weights/pretrained.safetensors",
            "learning/bundled/manifest.json"} <= changed, changed
    assert json.loads((copy / "learning" / "bundled" / "manifest.json").read_text())["kind"] == "dsvm"
    assert not data_dir(env).exists()


def test_precedence_explicit_then_user_then_shipped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from noisefeat import userdata

    shipped = tmp_path / "shipped.json"
    monkeypatch.setenv(userdata.ENV, str(tmp_path / "user"))
    assert userdata.user_data_dir() == tmp_path / "user"
    assert userdata.find("flip.json", shipped) == shipped
    (tmp_path / "user").mkdir()
    (tmp_path / "user" / "flip.json").write_text("{}")
    assert userdata.find("flip.json", shipped) == tmp_path / "user" / "flip.json"
    monkeypatch.delenv(userdata.ENV)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert userdata.user_data_dir() == tmp_path / "xdg" / "noisestop"
    monkeypatch.delenv("XDG_DATA_HOME")
    assert userdata.user_data_dir() == tmp_path / "home" / ".local" / "share" / "noisestop"


def test_train_needs_out_or_the_maintainer_flag(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "service.cli", *COMMANDS["train"]], capture_output=True,
                         text=True, env=user_env(tmp_path), cwd=tmp_path, timeout=120)
    assert out.returncode == 2 and "--out" in out.stderr and "Traceback" not in out.stderr
