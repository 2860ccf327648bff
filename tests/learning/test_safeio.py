"""Every input file is read through noisefeat.safeio: regular files only, each kind
capped in size, EXR chunks checked against the file; the token file, flip.json, meta.json,
references and the XDG rule."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from learning.data.exr import read_exr, write_exr
from learning.inputs.halves import load_flip_calibration
from noisefeat import safeio, userdata
from noisefeat.safeio import InputFileError, read_input, read_json
from renderer.client.token import resolve_token

FIXTURES = Path(__file__).parents[1] / "fixtures" / "dataset"


def test_a_link_to_a_device_is_refused_in_one_line(tmp_path):
    link = tmp_path / "reference.exr"
    link.symlink_to("/dev/zero")
    with pytest.raises(InputFileError, match="is a device, not a regular file") as exc:
        read_input(link, "EXR")
    assert "\n" not in str(exc.value) and str(link) in str(exc.value)


def test_a_fifo_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "meta.json"
    os.mkfifo(fifo)
    with pytest.raises(InputFileError, match="FIFO"):
        read_input(fifo, "meta.json")


def test_each_kind_is_capped_from_its_size_before_reading(tmp_path):
    big = tmp_path / "meta.json"
    with open(big, "wb") as f:
        f.truncate(safeio.CAPS["meta.json"] + 1)        # sparse: no disk, no memory
    with pytest.raises(InputFileError, match="over the limit"):
        read_input(big, "meta.json")
    small = tmp_path / "ok.json"
    small.write_text('{"a": 1}')
    assert read_json(small, "meta.json") == {"a": 1}


def test_token_file_on_dev_zero_is_refused():
    with pytest.raises(ValueError, match="token file is a device"):
        resolve_token(token_file="/dev/zero", environ={})


def test_deep_json_names_the_file(tmp_path):
    deep = tmp_path / "flip.json"
    deep.write_text("[" * 5000 + "]" * 5000)
    with pytest.raises(ValueError, match=str(deep).replace(".", r"\.")):
        load_flip_calibration(deep)


def test_negative_tau_in_a_user_flip_json_is_refused(tmp_path):
    from learning.inputs.halves import FLIP_CALIBRATION
    cal = json.loads(FLIP_CALIBRATION.read_text())
    cal["curve"][0]["tau"] = -abs(cal["curve"][0]["tau"])
    path = tmp_path / "flip.json"
    path.write_text(json.dumps(cal))
    with pytest.raises(ValueError, match="taus must be positive"):
        load_flip_calibration(path)


def test_a_relative_xdg_data_home_is_ignored(monkeypatch, tmp_path):
    monkeypatch.delenv(userdata.ENV, raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", "relative/dir")
    assert userdata.user_data_dir().is_absolute()
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))
    assert userdata.user_data_dir() == tmp_path / "noisestop"


def test_a_user_file_linked_to_a_device_is_refused_not_skipped(monkeypatch, tmp_path):
    monkeypatch.setenv(userdata.ENV, str(tmp_path))
    (tmp_path / "flip.json").symlink_to("/dev/zero")
    with pytest.raises(InputFileError, match="device"):
        load_flip_calibration()


def test_an_exr_with_a_zero_filled_tail_is_refused(tmp_path):
    path = tmp_path / "level.exr"
    write_exr(path, np.random.default_rng(0).random((64, 48, 3), dtype=np.float32))
    data = bytearray(path.read_bytes())
    data[len(data) // 2:] = bytes(len(data) - len(data) // 2)    # same size, zero-filled tail
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="zero-filled|corrupt"):
        read_exr(path)


def test_dataset_check_names_a_reference_linked_to_a_device(tmp_path):
    from learning.data.check import check_stack
    stack = tmp_path / "checker"
    shutil.copytree(FIXTURES / "checker", stack)
    (stack / "reference.exr").unlink(missing_ok=True)
    (stack / "reference.exr").symlink_to("/dev/zero")
    problems = [p.message for p in check_stack(stack)]
    assert any("device" in m for m in problems), problems
