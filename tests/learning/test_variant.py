"""Variant selection: env override, bad names, LLVM detection (never an aborting libLLVM)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from learning.data import variant as V
from tests.support import ROOT



def _run(code: str, **env_changes: str | None) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    for k, v in env_changes.items():
        if v is None:
            env.pop(k, None)
        else:
            env[k] = v
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300, check=False)


def test_llvm_major_from_path() -> None:
    assert V.llvm_major_from_path("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert V.llvm_major_from_path("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1") == 15
    assert V.llvm_major_from_path("/usr/lib/llvm-14/lib/libLLVM-14.0.6.so") == 14
    assert V.llvm_major_from_path("/usr/lib/llvm-18/lib/libLLVM.so") == 18
    assert V.llvm_major_from_path("/opt/custom/libLLVM.so") is None


def test_old_libllvm_in_env_is_not_trusted(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    old = tmp_path / "libLLVM-15.so.1"
    old.write_bytes(b"")
    monkeypatch.setenv(V.ENV_LIBLLVM, str(old))
    path, _why = V.find_libllvm()
    assert path != str(old)
    if path is not None:
        major = V.llvm_major_from_path(path)
        assert major is None or major >= V.MIN_LLVM_MAJOR


def test_env_override_to_scalar_in_fresh_process() -> None:
    code = ("import logging; logging.basicConfig(level=logging.INFO)\n"
            "from learning.data.variant import select_variant, current_variant, variant_reason\n"
            "v = select_variant(); assert select_variant() == v\n"
            "print(v, current_variant(), variant_reason(), sep='|')")
    res = _run(code, NOISESTOP_VARIANT="scalar_rgb")
    assert res.returncode == 0, res.stderr
    v, cur, reason = res.stdout.strip().split("|")
    assert v == cur == "scalar_rgb"
    assert "NOISESTOP_VARIANT" in reason
    assert "mitsuba variant: scalar_rgb" in res.stderr


def test_detection_picks_llvm_here() -> None:
    if V.find_libllvm()[0] is None:
        pytest.skip("no libLLVM >= 16 on this machine")
    code = ("import os\nfrom learning.data.variant import select_variant\n"
            "print(select_variant(), os.environ['DRJIT_LIBLLVM_PATH'], sep='|')")
    res = _run(code, NOISESTOP_VARIANT=None, DRJIT_LIBLLVM_PATH=None)
    assert res.returncode == 0, res.stderr
    name, lib = res.stdout.strip().split("|")
    assert name == "llvm_ad_rgb"
    assert (V.llvm_major_from_path(lib) or 0) >= 16


def test_unknown_variant_is_a_clear_value_error() -> None:
    with pytest.raises(ValueError, match="unknown Mitsuba variant 'no_such_rgb'.*scalar_rgb"):
        V.select_variant("no_such_rgb")


def test_idempotent_and_no_switching() -> None:
    first = V.select_variant()
    assert V.select_variant() == first == V.current_variant()
    assert V.select_variant(first) == first
    assert isinstance(V.variant_reason(), str) and V.variant_reason()
    other = "scalar_spectral" if first == "scalar_rgb" else "scalar_rgb"
    with pytest.raises(RuntimeError, match="already set"):
        V.select_variant(other)
