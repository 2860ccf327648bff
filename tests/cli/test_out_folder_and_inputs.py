"""The out folder and the smaller command-line inputs.

- `--out ""` (the current folder, without the out-folder lock) and `--out /` are one-line
  errors, on the command line and in the API.
- A render removes an earlier render's final.exr and report.json when it starts (a resume
  too, once its checkpoint is accepted; a refused resume touches nothing), so a render
  killed after its first checkpoint never leaves them beside its own checkpoint.
- `--reference` naming /dev/zero, a FIFO or a folder says what it is (not "not found");
  `--scene ""` is refused (not cornell); numbers are ASCII digits only (not `１６` or `1_024`).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from renderer.live import adaptive, outputs, plan
from renderer.live.session import RenderSession
from service import cli
from tests.support.errors import assert_one_line_error, run

RENDER = ["render", "--scene", "cornell", "--resolution", "16", "--step", "4", "--min-spp", "4",
          "--max-spp", "16", "--criterion", "uniform"]


@pytest.fixture(autouse=True)
def _no_logging_setup(monkeypatch):
    """The handlers main() would install outlive one test's captured stderr."""
    monkeypatch.setattr(cli, "_setup_logging", lambda verbose, quiet: None)


@pytest.mark.parametrize("out", ["", "/", "//", "/tmp/.."])
def test_an_empty_or_root_out_is_one_line(out, capsys, tmp_path, monkeypatch):
    import renderer.render_many

    def never(*args, **kwargs):       # were the check gone, no render may write into /
        raise AssertionError(f"rendered into {out!r}")

    monkeypatch.setattr(renderer.render_many, "render_command", never)
    monkeypatch.chdir(tmp_path)
    rc, err = run(capsys, *RENDER, "--out", out)
    assert_one_line_error(rc, err, "output folder")
    assert os.listdir(tmp_path) == []            # nothing written into the current folder


@pytest.mark.parametrize("out", ["", "/"])
def test_the_api_refuses_them_too(out, monkeypatch, tmp_path):
    def never(*args, **kwargs):       # were the check gone, no render may write into /
        raise AssertionError(f"rendered into {out!r}")

    monkeypatch.setattr(plan, "BlockRenderer", never)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match="output folder"):
        outputs.prepare_output_dir(out)
    with pytest.raises(ValueError, match="output folder"):
        adaptive.adaptive_render("cornell", out, "uniform", resolution=16, max_spp=16, progress=False)


def test_a_render_killed_after_its_first_checkpoint_leaves_no_earlier_results(tmp_path, capsys, monkeypatch):
    out = tmp_path / "o"
    assert cli.main(["-q", *RENDER, "--out", str(out)]) == 0
    (out / outputs.COMPARE).write_bytes(b"an earlier render's")       # one a reference render left
    assert (out / outputs.FINAL_EXR).exists() and (out / outputs.REPORT).exists()
    save = RenderSession.checkpoint

    def killed(self):               # the kill -9 lands just after the first checkpoint
        save(self)
        raise SystemExit(137)

    monkeypatch.setattr(RenderSession, "checkpoint", killed)
    with pytest.raises(SystemExit):
        cli.main(["-q", *RENDER, "--max-spp", "32", "--checkpoint-every", "0", "--out", str(out)])
    left = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    assert left == ["checkpoint.npz"], left
    monkeypatch.setattr(RenderSession, "checkpoint", save)
    assert cli.main(["-q", *RENDER, "--max-spp", "32", "--checkpoint-every", "0", "--resume", "--out", str(out)]) == 0
    report = json.loads((out / outputs.REPORT).read_text())
    assert report["max_spp"] == 32 and (out / outputs.FINAL_EXR).exists() and not (out / outputs.COMPARE).exists()


def test_a_refused_resume_leaves_the_results_as_they_were(tmp_path, capsys):
    out = tmp_path / "o"
    assert cli.main(["-q", *RENDER, "--checkpoint-every", "0", "--out", str(out)]) == 0
    before = (out / outputs.REPORT).read_bytes()
    rc, err = run(capsys, *RENDER, "--max-spp", "32", "--checkpoint-every", "0", "--resume", "--out", str(out))
    assert rc == 2
    assert (out / outputs.REPORT).read_bytes() == before and (out / outputs.FINAL_EXR).exists()


def test_a_result_that_cannot_be_removed_is_one_line_before_any_pass(tmp_path, capsys):
    out = tmp_path / "o"
    (out / outputs.FINAL_EXR).mkdir(parents=True)
    rc, err = run(capsys, *RENDER, "--out", str(out))
    assert_one_line_error(rc, err, "final.exr", "cannot remove the previous render's result")
    assert not (out / "checkpoint.npz").exists()


# --- 8: the smaller ones ---------------------------------------------------------------------

@pytest.mark.parametrize("kind,said", [("device", "is a device"), ("fifo", "is a FIFO"),
                                       ("folder", "is a directory")])
def test_a_reference_that_is_no_file_says_what_it_is(kind, said, tmp_path, capsys):
    ref = tmp_path / "ref.exr"
    if kind == "device":
        ref.symlink_to("/dev/zero")
    elif kind == "fifo":
        os.mkfifo(ref)
    else:
        ref.mkdir()
    rc, err = run(capsys, *RENDER, "--reference", str(ref), "--out", str(tmp_path / "o"))
    assert_one_line_error(rc, err, str(ref), said)
    assert "not found" not in err


def test_an_empty_scene_is_one_line(tmp_path, capsys):
    rc, err = run(capsys, *RENDER[:1], "--scene", "", *RENDER[3:], "--out", str(tmp_path / "o"))
    assert_one_line_error(rc, err, "--scene")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("flag,text", [("--max-spp", "１６"), ("--max-spp", "1_024"), ("--resolution", "１６"),
                                       ("--resolution", "1_6x16"), ("--exposure", "０.５"), ("--exposure", "1_0"),
                                       ("--checkpoint-every", "1_0"), ("--grid", "٢")])
def test_numbers_are_ascii_digits_only(flag, text, tmp_path, capsys):
    extra = [text, "2"] if flag == "--grid" else [text]
    rc, err = run(capsys, *RENDER, flag, *extra, "--out", str(tmp_path / "o"))
    assert rc == 2 and "Traceback" not in err and flag in err, err
    assert not (tmp_path / "o").exists()


def test_ascii_numbers_still_parse():
    from service.commands.arguments import float_in, int_in

    assert int_in(1)(" 16") == 16 and int_in(-5)("-3") == -3
    assert float_in(0, 10)("1e0") == 1.0 and float_in(0, 10)(".5") == 0.5
