"""Leftover doors of `render`: a folder given as `--reference` that holds no stack is said
to be a folder (it was "no stack of scene 'cornell'"), and `--resume` with a checkpoint
that is a loop of symbolic links is refused in one line (it started over, exit 0)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.support.errors import assert_one_line_error, run

pytestmark = pytest.mark.slow

TINY = ["--scene", "cornell", "--resolution", "32", "--block", "16", "--step", "4", "--min-spp", "4",
        "--max-spp", "8", "--criterion", "uniform"]


def test_a_folder_without_a_stack_as_reference_is_said_to_be_a_folder(tmp_path, capsys) -> None:
    (tmp_path / "empty").mkdir()
    rc, err = run(capsys, "render", *TINY, "--reference", str(tmp_path / "empty"), "--out", str(tmp_path / "o"))
    assert_one_line_error(rc, err, str(tmp_path / "empty"), "a folder with no stack in it")
    assert "no stack of scene" not in err


@pytest.mark.parametrize("loop", ["itself", "a loop of two"])
def test_resume_refuses_a_checkpoint_that_is_a_loop_of_links(tmp_path, capsys, loop) -> None:
    out = tmp_path / "o"
    out.mkdir()
    if loop == "itself":
        os.symlink("checkpoint.npz", out / "checkpoint.npz")
    else:
        os.symlink("other.npz", out / "checkpoint.npz")
        os.symlink("checkpoint.npz", out / "other.npz")
    rc, err = run(capsys, "render", *TINY, "--out", str(out), "--resume")
    assert_one_line_error(rc, err, "checkpoint.npz", "loop of symbolic links")
    assert not (out / "final.exr").exists() and (out / "checkpoint.npz").is_symlink()    # nothing rendered


def test_present_sees_broken_and_looping_links_and_open_input_names_them(tmp_path) -> None:
    from noisefeat.safeio import InputFileError, open_input, present

    loop, broken = tmp_path / "loop", tmp_path / "broken"
    os.symlink("loop", loop)
    os.symlink("nothing-here", broken)
    assert present(loop) and present(broken) and not present(tmp_path / "absent")
    assert not Path(loop).exists()                      # what `--resume` used to ask
    with pytest.raises(InputFileError, match="loop of symbolic links"):
        open_input(loop, "checkpoint")
    with pytest.raises(FileNotFoundError, match="link to a missing file"):
        open_input(broken, "checkpoint")
