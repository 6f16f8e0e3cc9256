"""Smoke tests of the ``gcgs bench-*`` benchmarks on tiny cases: each runs through the CLI
and writes a report that parses and holds finite numbers (speed is never asserted)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from pipeline import cli
from relief_scene import write_relief_scene


def _numbers(obj) -> list[float]:
    if isinstance(obj, bool) or obj is None or isinstance(obj, str):
        return []
    if isinstance(obj, (int, float)):
        return [float(obj)]
    items = obj.values() if isinstance(obj, dict) else obj
    return [x for v in items for x in _numbers(v)]


def read_report(path: Path) -> dict:
    """The JSON report, refusing NaN/Infinity (not JSON) and non-finite numbers."""
    def no_constant(name):
        raise AssertionError(f"{path}: {name} in the report")

    data = json.loads(path.read_text(), parse_constant=no_constant)
    nums = _numbers(data)
    assert nums and all(math.isfinite(x) for x in nums), path
    return data


def test_bench_eval(tmp_path):
    out = tmp_path / "reports"
    assert cli.main(["bench-eval", "--vertices", "3000", "--radius", "12", "--gt-vertices", "2000",
                     "--out-dir", str(out)]) == 0
    rep = read_report(out / "evaluation.json")
    assert len(rep["runs"]) == 2 and rep["mesh_vertices"] > 2000
    near, far = rep["runs"]
    assert near["wall_s"] > 0 and 50 < near["peak_rss_mib"] < 4000
    assert near["accuracy_mm"] < 1.0 < far["accuracy_mm"]  # the 2 mm-off mesh is 2 mm off
    assert "| bumpy ball" in (out / "evaluation.md").read_text()


def test_bench_raster(tmp_path, monkeypatch):
    from pipeline.benchmarks import rasterizer

    monkeypatch.setattr(rasterizer, "QUICK", [(64, 48, 400)])
    assert cli.main(["bench-raster", "--quick", "--repeats", "1", "--out-dir", str(tmp_path)]) == 0
    recs = read_report(tmp_path / "rasterizer_quick.json")
    assert {r["backend"] for r in recs} == {"cpu", "simd", "reference"}
    md = (tmp_path / "rasterizer_quick.md").read_text()
    simd_ok = rasterizer.simd.available()[0]
    for r in recs:
        if r["backend"] == "simd" and not simd_ok:
            assert "skipped" in r
            continue
        assert r["forward_s"] > 0 and r["backward_s"] > 0 and r["peak_mb"] is not None
    assert "| 64x48 | 400 |" in md
    for backend in ("cpu", "simd") if simd_ok else ("cpu",):
        (rec,) = [r for r in recs if r["backend"] == backend]
        split = rec["split_s"]
        assert list(split) == [*rasterizer.KERNEL_PARTS, "rest"]
        # every part ran (own time > 0), and the parts add up to the timed forward + backward
        assert all(split[k] > 0 for k in rasterizer.KERNEL_PARTS), backend
        assert sum(split.values()) == pytest.approx(rec["forward_s"] + rec["backward_s"], abs=5e-4)  # 4-decimal rounding
    assert "## Where the cpu backend's (and the simd kernels') time goes" in md
    if simd_ok:
        (rec,) = [r for r in recs if r["backend"] == "simd"]
        assert rec["cpu_alternated_total_s"] > 0
        assert "## The simd kernels against the cpu backend" in md


@pytest.fixture(scope="module")
def tiny_scene_and_init(tmp_path_factory, bundled_scan):
    scene_dir, init_dir, _ = write_relief_scene(tmp_path_factory.mktemp("bench_priors"), bundled_scan, (23, 24, 33),
                                                80, 60)
    return scene_dir, init_dir


def test_bench_priors(tmp_path, tiny_scene_and_init):
    scene, init = tiny_scene_and_init
    out = tmp_path / "stage_benchmark.json"
    assert cli.main(["bench-priors", "--scene", str(scene), "--init-dir", str(init), "--repeats", "1",
                     "--out", str(out)]) == 0
    rep = read_report(out)
    assert rep["size"] == "80x60" and len(rep["stage"]) == 3
    for r in rep["stage"].values():
        assert r["wall_s_median"] > 0 and 50 < r["max_rss_mb_max"] < 4000
    assert rep["losses_float32_cpu"]["gcf_points"] > 0


def test_bench_gcf(tmp_path, bundled_scan):
    assert cli.main(["bench-gcf", "--cameras", str(bundled_scan), "--width", "80", "--height", "60",
                     "--delta-step", "5", "--out", str(tmp_path)]) == 0
    rep = read_report(tmp_path / "gcf_vs_depth_offset.json")
    assert rep["delta_mm"] == [-10.0, -5.0, 0.0, 5.0, 10.0]
    assert len(rep["curves"]["relief plate"]["loss"]) == 5
    assert (tmp_path / "gcf_vs_depth_offset.png").stat().st_size > 0


def test_bench_train(tmp_path, bundled_scan):
    import numpy as np

    from pipeline import geometry
    from pipeline.init.io import PointCloud, write_ply

    scene, init, relief = write_relief_scene(tmp_path, bundled_scan, (23, 24, 33), 80, 60)
    d, K, T = relief.depth_mm[0], relief.K[0], relief.world_to_cam[0]
    pts = geometry.backproject_depth(K, T, d)[d > 0][::4]
    n = len(pts)
    write_ply(init / "points.ply", PointCloud(pts, np.full((n, 3), 0.5), np.tile([0.0, 0.0, -1.0], (n, 1)), np.ones(n)))
    out = tmp_path / "training.json"
    assert cli.main(["bench-train", "--scene", str(scene), "--init-dir", str(init), "--at", "400",
                     "--iterations", "2", "--out", str(out)]) == 0
    rep = read_report(out)
    split = rep["split_s_per_iteration"]
    assert rep["s_per_iteration"] > 0 and rep["surfels"] > 0 and rep["from_iteration"] == 400
    assert split["raster forward kernel"] > 0 and split["torch autograd (loss terms' backward)"] > 0
    assert split["loss kernels (L_mv's patches, warp and NCC; SSIM's blur; L_smooth; L_dn)"] > 0  # L_mv is on at 400
    assert sum(split.values()) == pytest.approx(rep["s_per_iteration"], rel=0.01, abs=1e-3)
    assert "| raster forward kernel |" in out.with_suffix(".md").read_text()


def test_bench_train_refuses_a_missing_scene(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        cli.main(["bench-train", "--scene", str(tmp_path / "nope"), "--out", str(tmp_path / "t.json")])


@pytest.mark.parametrize("argv, report, work", [
    (["bench-raster", "--quick"], "rasterizer_quick.json", ("pipeline.benchmarks.rasterizer", "_bench_case")),
    (["bench-eval"], "evaluation.md", ("pipeline.benchmarks.evaluation", "uv_sphere")),
    (["bench-train", "--scene", "nope", "--init-dir", "nope"], "training.md", ("pipeline.benchmarks.training", "load_params")),
])
def test_a_bench_refuses_a_foreign_report_before_its_work(tmp_path, monkeypatch, capsys, argv, report, work):
    """A report path holding a file gcgs did not write is refused at the start: minutes of
    timing are not run only to fail at the write (as bench-raster once did, after 8 minutes)."""
    import importlib

    module, name = work
    monkeypatch.setattr(importlib.import_module(module), name, lambda *a, **k: pytest.fail("the work started"))
    (tmp_path / report).write_text("someone's notes\n")
    out = ["--out", str(tmp_path / "training.json")] if argv[0] == "bench-train" else ["--out-dir", str(tmp_path)]
    assert cli.main([*argv, *out]) != 0
    assert "was not written by gcgs" in capsys.readouterr().err
    assert (tmp_path / report).read_text() == "someone's notes\n"


def test_bench_train_counts_the_smoothness_and_depth_normal_kernels():
    """L_smooth's and L_dn's numba kernels are loss kernels in the split, not the rest."""
    import cProfile
    import pstats

    import torch

    from pipeline.benchmarks.training import LOSS_KERNELS, split_profile
    from pipeline.losses import depth_normal_loss, normal_smoothness_loss

    def both():
        normal = torch.randn(48, 64, 3, requires_grad=True)
        depth = (2.0 + torch.rand(48, 64)).requires_grad_(True)
        K = torch.tensor([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])
        n = normal.permute(2, 0, 1)
        loss = normal_smoothness_loss(n, torch.rand(3, 48, 64), torch.ones(48, 64, dtype=torch.bool), 10.0)
        (loss + depth_normal_loss(n, depth, torch.rand(48, 64), K)).backward()

    both()  # compiled or loaded from numba's cache outside the profile
    profiler = cProfile.Profile()
    profiler.enable()
    both()
    profiler.disable()
    split = split_profile(pstats.Stats(profiler), 1.0)
    assert split[LOSS_KERNELS] > 0
