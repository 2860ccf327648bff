"""A stack whose meta.json is a directory is refused in one line naming it (not skipped
without a word while `evaluate` exits 0 on the other stacks)."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.support.errors import assert_one_line_error, run

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "dataset"


def test_a_meta_json_that_is_a_directory_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for scene in ("sky", "checker"):
        shutil.copytree(FIXTURE / scene, tmp_path / scene)
    (tmp_path / "sky" / "meta.json").unlink()
    (tmp_path / "sky" / "meta.json").mkdir()
    rc, err = run(capsys, "evaluate", "--data", str(tmp_path), "--criterion", "flip")
    assert_one_line_error(rc, err, str(tmp_path / "sky" / "meta.json"), "directory")
