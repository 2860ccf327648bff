"""Pick the Mitsuba 3 variant once per process, safely.

Why this module exists: Mitsuba's JIT variants fail in ways that cannot be caught.
`llvm_ad_rgb` loaded against libLLVM 15 (Debian's default) *aborts the process*
("Cannot select ... fminimum") the first time a kernel is compiled, so we must decide
which libLLVM Dr.Jit will load before `drjit` is ever imported, and never try the LLVM
backend without a libLLVM >= 16. CUDA is only tried when a driver is visibly present.

Order of choice:
  1. the explicit `requested` argument, else the env var ``NOISESTOP_VARIANT``;
  2. ``cuda_ad_rgb`` if a CUDA driver is present and Dr.Jit reports the CUDA backend;
  3. ``llvm_ad_rgb`` if a libLLVM >= 16 is found (``DRJIT_LIBLLVM_PATH`` honoured);
  4. ``scalar_rgb`` (always works, about half the speed of llvm on 2 cores).
"""

from __future__ import annotations

import ctypes.util
import glob
import logging
import os
import re
import sys
import threading

from noisefeat.extras import require

logger = logging.getLogger(__name__)

ENV_VARIANT = "NOISESTOP_VARIANT"
ENV_LIBLLVM = "DRJIT_LIBLLVM_PATH"
MIN_LLVM_MAJOR = 16

# Searched in order; the first readable file with a parseable major >= 16 wins.
# Newest first so that a machine with several versions picks the best one.
LLVM_CANDIDATE_GLOBS: tuple[str, ...] = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.*",
    "/usr/lib/x86_64-linux-gnu/libLLVM-[1-9][0-9].so*",
    "/usr/lib/llvm-[1-9][0-9]/lib/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM.so.*",
    "/usr/lib/aarch64-linux-gnu/libLLVM-[1-9][0-9].so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
)

_lock = threading.Lock()
_chosen: str | None = None
_reason: str | None = None


def llvm_major_from_path(path: str) -> int | None:
    """Major LLVM version encoded in a library path, or None if it cannot be told.

    Understands ``libLLVM.so.19.1``, ``libLLVM-17.so.1``, ``libLLVM-14.0.6.so`` and
    ``/usr/lib/llvm-18/lib/libLLVM.so``.
    """
    name = os.path.basename(path)
    for pattern in (r"^libLLVM-(\d+)", r"^libLLVM\.so\.(\d+)"):
        m = re.match(pattern, name)
        if m:
            return int(m.group(1))
    m = re.search(r"/llvm-(\d+)/", path)
    if m:
        return int(m.group(1))
    return None


def find_libllvm() -> tuple[str | None, str]:
    """Return (path, why) of a libLLVM usable by Dr.Jit (major >= 16), or (None, why).

    An existing ``DRJIT_LIBLLVM_PATH`` is honoured unless its name says it is older
    than 16 (that would abort the process later) or the file does not exist.
    """
    env = os.environ.get(ENV_LIBLLVM)
    if env:
        major = llvm_major_from_path(env)
        if not os.path.exists(env):
            logger.warning("%s=%s does not exist; ignoring it", ENV_LIBLLVM, env)
        elif major is not None and major < MIN_LLVM_MAJOR:
            logger.warning(
                "%s=%s is LLVM %d (< %d, would abort the JIT); ignoring it",
                ENV_LIBLLVM, env, major, MIN_LLVM_MAJOR,
            )
        else:
            return env, f"{ENV_LIBLLVM}={env}"
    best: tuple[int, str] | None = None
    for pattern in LLVM_CANDIDATE_GLOBS:
        for path in sorted(glob.glob(pattern)):
            major = llvm_major_from_path(path)
            if major is None or major < MIN_LLVM_MAJOR or not os.path.isfile(path):
                continue
            if best is None or major > best[0]:
                best = (major, path)
    if best is None:
        return None, f"no libLLVM >= {MIN_LLVM_MAJOR} found"
    return best[1], f"found libLLVM {best[0]} at {best[1]}"


def cuda_driver_present() -> bool:
    """Cheap check for an NVIDIA driver, done before asking Dr.Jit (which may be slow)."""
    if os.path.exists("/dev/nvidiactl") or glob.glob("/dev/nvidia[0-9]*"):
        return True
    return ctypes.util.find_library("cuda") is not None


def current_variant() -> str | None:
    """The Mitsuba variant set in this process, or None (never imports Mitsuba)."""
    if _chosen is not None:
        return _chosen
    mi = sys.modules.get("mitsuba")
    if mi is None:
        return None
    return mi.variant()


def variant_reason() -> str | None:
    """Short human-readable reason for the chosen variant (for reports), or None."""
    if _reason is not None:
        return _reason
    v = current_variant()
    return None if v is None else "set outside noisestop"


def _loaded_llvm_major() -> int | None:
    """Major version of the libLLVM an already-imported Dr.Jit loaded (None: unknown)."""
    dr = sys.modules.get("drjit")
    try:
        major = int(dr.detail.llvm_version()[0])  # type: ignore[union-attr]
    except (AttributeError, RuntimeError, TypeError, ValueError, IndexError):
        return None
    return major if major > 0 else None


def _prepare_llvm() -> str | None:
    """Make sure Dr.Jit will use a good libLLVM; return a reason, or None if it cannot.

    Dr.Jit picks its libLLVM when it is imported, so the environment variable only helps
    before that. If it is already imported we ask it which version it loaded instead.
    """
    if "drjit" in sys.modules:
        major = _loaded_llvm_major()
        if major is None or major < MIN_LLVM_MAJOR:
            logger.warning("drjit was imported before noisestop chose a libLLVM and uses LLVM %s; "
                           "llvm variants disabled (need >= %d)", major, MIN_LLVM_MAJOR)
            return None
        return f"drjit already loaded libLLVM {major}"
    path, why = find_libllvm()
    if path is None:
        return None
    os.environ[ENV_LIBLLVM] = path
    return why


def _check_known(name: str) -> None:
    mi = require("mitsuba")

    known = mi.variants()
    if name not in known:
        raise ValueError(f"unknown Mitsuba variant {name!r}; available: {', '.join(known)}")


def select_variant(requested: str | None = None) -> str:
    """Choose and set the Mitsuba variant (once per process) and return its name.

    A second call returns the variant already set; asking explicitly for a different
    one then raises RuntimeError, because Mitsuba objects built under the old variant
    would silently become invalid.
    """
    global _chosen, _reason
    with _lock:
        already = current_variant()
        if already is not None:
            if requested is not None and requested != already:
                _check_known(requested)
                raise RuntimeError(
                    f"Mitsuba variant already set to {already!r} in this process; "
                    f"cannot switch to {requested!r}"
                )
            if _chosen is None:
                _chosen, _reason = already, "set outside noisestop"
            return already

        name: str | None = requested or os.environ.get(ENV_VARIANT) or None
        reason: str
        if name:
            source = "requested" if requested else f"{ENV_VARIANT}"
            reason = source
            if name.startswith("llvm_"):
                why = _prepare_llvm()
                if why is None:
                    raise RuntimeError(
                        f"variant {name!r} needs libLLVM >= {MIN_LLVM_MAJOR} (older ones abort the "
                        f"process); none found. Install e.g. Debian libllvm19 or set {ENV_LIBLLVM}"
                    )
                reason = f"{source}; {why}"
            else:
                # Harmless, and keeps any later llvm use in this process safe.
                _prepare_llvm()
            _check_known(name)
        else:
            llvm_why = _prepare_llvm()
            name, reason = "scalar_rgb", f"fallback: no CUDA device, no libLLVM >= {MIN_LLVM_MAJOR}"
            if cuda_driver_present():
                dr = require("drjit")

                if dr.has_backend(dr.JitBackend.CUDA):
                    name, reason = "cuda_ad_rgb", "CUDA device available"
            if name == "scalar_rgb" and llvm_why is not None:
                name, reason = "llvm_ad_rgb", f"no CUDA device; {llvm_why}"

        mi = require("mitsuba")

        try:
            mi.set_variant(name)
        except Exception as exc:  # known name, but its backend is not usable here
            raise RuntimeError(f"Mitsuba variant {name!r} is not usable on this machine: {exc}") from exc
        _chosen, _reason = name, reason
        logger.info("mitsuba variant: %s (%s)", name, reason)
        return name
