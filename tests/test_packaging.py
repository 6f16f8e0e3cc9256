"""The package as pip builds it (not the editable checkout): the simd rasterizer's C++
source ships in the wheel, and an installed copy builds and loads the kernels."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(
    shutil.which("c++") is None and not os.environ.get("GCGS_REQUIRE_SIMD"), reason="no C++ compiler on PATH"
)


@pytest.mark.slow
def test_a_wheel_install_builds_the_simd_kernels(tmp_path):
    src = tmp_path / "src"  # a copy, so the build writes nothing into the checkout
    shutil.copy(REPO / "pyproject.toml", src.parent / "pyproject.toml")
    shutil.copytree(REPO / "src", src, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", "*.so"))
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run(pip + ["wheel", "--no-deps", "--no-build-isolation", "-w", str(tmp_path / "wheel"), str(tmp_path)],
                   check=True, capture_output=True, timeout=600)
    (wheel,) = (tmp_path / "wheel").glob("*.whl")
    assert "pipeline/rasterizer/_simd.cpp" in zipfile.ZipFile(wheel).namelist()
    target = tmp_path / "site"
    subprocess.run(pip + ["install", "--no-deps", "--target", str(target), str(wheel)], check=True,
                   capture_output=True, timeout=600)
    code = ("import pipeline.rasterizer.simd as s; ok, why = s.available(); "
            "print(s.__file__); print(ok, why); raise SystemExit(0 if ok else 1)")
    env = {**os.environ, "PYTHONPATH": str(target), "GCGS_CACHE_DIR": str(tmp_path / "cache")}
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.splitlines()[0].startswith(str(target)), "the installed copy, not the checkout, was imported"
    assert list((tmp_path / "cache" / "simd").glob("_simd-*-*.so"))
