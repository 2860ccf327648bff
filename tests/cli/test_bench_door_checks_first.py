"""`noisestop bench` checks what it was given before it measures: an `--update` FILE that
cannot be rewritten (/dev/zero, a FIFO, a folder) used to be found out only after the run
(2.2 GB read, a hang, a bare errno line), and an unknown `--kinds` or `--arches` name ran
for seconds and then failed on something else. Each is now one line, before any section
runs (`run_all` is replaced by a spy that fails the test if it is reached)."""
from __future__ import annotations

import os

import pytest

from learning.names import SVM_KINDS, TRANSFER_KINDS
from service.commands import bench as door
from tests.support.errors import assert_one_line_error, run


@pytest.fixture
def measured(monkeypatch) -> list[tuple]:
    """The benchmarks' `run_all`, recording its calls instead of measuring."""
    module = door.load_benchmarks()
    calls: list[tuple] = []
    monkeypatch.setattr(module, "run_all", lambda *a, **k: calls.append((a, k)) or {"failed": {}, "markdown": {}})
    return calls


def _target(tmp_path, kind: str) -> str:
    if kind == "/dev/zero":
        return "/dev/zero"
    if kind == "FIFO":
        os.mkfifo(tmp_path / "fifo.md")
        return str(tmp_path / "fifo.md")
    if kind == "folder":
        return str(tmp_path)
    return str(tmp_path / "missing" / "BENCHMARKS.md")


@pytest.mark.parametrize("kind, said", [("/dev/zero", "a device"), ("FIFO", "a FIFO"), ("folder", "a directory"),
                                        ("in a missing folder", "does not exist")])
def test_an_update_file_that_cannot_be_rewritten_is_refused_before_measuring(tmp_path, capsys, measured,
                                                                              kind, said) -> None:
    target = _target(tmp_path, kind)
    rc, err = run(capsys, "bench", "stability", "--update", target)
    assert_one_line_error(rc, err, "--update", target, said)
    assert measured == []


def test_a_writable_update_file_is_measured_into(tmp_path, capsys, measured) -> None:
    """The control: a markdown file in a writable folder passes the check."""
    doc = tmp_path / "B.md"
    doc.write_text("# figures\n")
    rc, err = run(capsys, "bench", "stability", "--update", str(doc))
    assert rc == 0 and len(measured) == 1, err


@pytest.mark.parametrize("flag, value, known", [("--kinds", "zzz", SVM_KINDS), ("--kinds", "dsvm,zzz", SVM_KINDS),
                                                ("--arches", "vgg19,resnet", TRANSFER_KINDS)])
def test_unknown_kinds_and_arches_are_refused_first_listing_the_known_ones(capsys, measured, flag, value,
                                                                           known) -> None:
    rc, err = run(capsys, "bench", "models", flag, value)
    assert_one_line_error(rc, err, flag, "unknown", ", ".join(known))
    assert measured == []


def test_known_kinds_and_arches_reach_the_benchmarks_as_tuples(capsys, measured) -> None:
    rc, err = run(capsys, "bench", "models", "--data", "x", "--kinds", "dsvm, svm_as", "--arches", "")
    assert rc == 0, err
    (_, kwargs), = measured
    assert kwargs["kinds"] == ("dsvm", "svm_as") and kwargs["arches"] == ()
