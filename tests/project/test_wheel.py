"""What ships: the wheel (`pip install 'noisestop[serve]'`) and the serving image hold the four
packages and no benchmark, example, load-generator or attack code; from such a plain install
`noisestop bench` says in one line that it needs a source checkout."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.support import ROOT

PACKAGES = ("noisefeat", "learning", "renderer", "service")
#: what a checkout holds and no install may: the benchmarks, the examples, the tests, the old lab
NOT_SHIPPED = ("benchmarks/", "examples/", "tests/", "service/lab/")
#: file names of the load generators, attack drivers and hardening harnesses (and the attack
#: package's folder), wherever they would land
BENCH_FILES = re.compile(r"(^|/)((attack|loadtest|openloop|reliability|hardening\w*|bench_\w+)\.py$|attack/)")
#: what the Dockerfile may copy into the serving image
IMAGE_SOURCES = {"pyproject.toml", "README.md", *PACKAGES}


def _copy_source(dest: Path) -> Path:
    """The checkout as a fresh clone has it (no build outputs, datasets or virtual environment)."""
    top = {".git", ".venv", "build", "out", "data", "bench-out"}        # /data/ is ignored, learning/data is not
    anywhere = shutil.ignore_patterns("*.egg-info", "__pycache__", ".hypothesis", ".pytest_cache", ".cache")

    def skip(folder: str, names: list[str]) -> set[str]:
        return set(anywhere(folder, names)) | (top & set(names) if Path(folder) == ROOT else set())
    return Path(shutil.copytree(ROOT, dest, ignore=skip))


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel `pip wheel` builds from a copy of the checkout, benchmarks/, examples/ and tests/ included."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = _copy_source(tmp / "src")
    assert (src / "benchmarks" / "attack" / "wire.py").is_file()   # there to be left out
    assert (src / "examples" / "references" / "studio_preview.exr").is_file()
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                          "--no-index", "-w", str(tmp / "dist"), str(src)],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    (built,) = (tmp / "dist").glob("noisestop-*.whl")
    return built


def shipped_benchmarks(names: list[str]) -> list[str]:
    """Entries of a wheel listing that are benchmark, test or attack code."""
    return [n for n in names if n.startswith(NOT_SHIPPED) or BENCH_FILES.search(n)]


def test_the_wheel_holds_the_packages_and_no_benchmarks(wheel) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert tops == {*PACKAGES, "noisestop-0.1.0.dist-info"}, tops
    assert shipped_benchmarks(names) == []
    # complete: every module of the packages is in it, the bench command's door too
    source = {str(p.relative_to(ROOT)) for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}
    assert source <= set(names) and "service/commands/bench.py" in names
    assert {"noisefeat/weights/smoothing.safetensors", "learning/flip.json"} <= set(names)


def test_the_checker_sees_benchmarks_in_a_listing() -> None:
    """Control: a listing with the old lab, the benchmarks, the tests or an attack driver
    moved into a package is caught; the real packages' files are not."""
    listing = ["service/app.py", "service/commands/bench.py", "learning/models/bundle.py", "service/lab/attack.py",
               "benchmarks/bench.py", "tests/support/demo.py", "service/loadtest.py", "renderer/bench_passes.py",
               "service/attack/wire.py", "learning/hardening_files.py"]
    assert shipped_benchmarks(listing) == listing[3:]


def test_bench_from_a_plain_install_needs_a_checkout(wheel, tmp_path) -> None:
    """The wheel unpacked as site-packages (no checkout beside it): one line, exit 2."""
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import service; "
            "assert service.__file__.startswith(sys.argv[1]), service.__file__; "
            "from service.cli import main; sys.exit(main(['bench', 'stability']))")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NOISESTOP_DEBUG")}
    out = subprocess.run([sys.executable, "-c", code, str(site)], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=300)
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 2 and len(lines) == 1, out.stderr
    assert lines[0].startswith("noisestop bench: error: ") and "source checkout" in lines[0], lines[0]


def copied_sources(dockerfile: str) -> set[str]:
    """What the Dockerfile's COPY and ADD lines take from the build context."""
    found: set[str] = set()
    for line in dockerfile.splitlines():
        words = line.split()
        if words and words[0].upper() in ("COPY", "ADD"):
            args = [w for w in words[1:] if not w.startswith("--")]
            found |= {a.rstrip("/") or "." for a in args[:-1]}
    return found


def test_the_image_copies_the_packages_only() -> None:
    text = (ROOT / "docker" / "Dockerfile").read_text()
    assert copied_sources(text) == IMAGE_SOURCES
    assert re.search(r'pip install [^\n]*"\.\[serve\]"', text)          # installs what the wheel holds


def test_the_checker_sees_the_image_copy_more() -> None:
    """Control: copying the whole context or the benchmarks is seen."""
    assert copied_sources("FROM x\nCOPY . .\n") == {"."}
    assert copied_sources("COPY --chown=a benchmarks/ benchmarks\nCOPY service service\n") == \
        {"benchmarks", "service"}
