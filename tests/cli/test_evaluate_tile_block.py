"""`noisestop evaluate --tile T --criterion model` where T equals the stacks' block: the
tile is the whole block, so the model decides whole blocks (no flip gate), instead of
failing on a tiling that has no tiles."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from service import cli

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "dataset"     # blocks of 16 px


def test_model_with_the_tile_of_the_block_decides_whole_blocks(capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    rc = cli.main(["evaluate", "--data", str(FIXTURE), "--criterion", "model", "--tile", "16",
                   "--scenes", "sky", "--json"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    result = json.loads(out)
    assert result["criterion"]["name"] == "model" and "tiles" not in result["criterion"], result["criterion"]
    assert result["tile"] == 16
