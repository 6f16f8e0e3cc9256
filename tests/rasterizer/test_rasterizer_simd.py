"""The simd kernels (the ``simd`` backend, ``pipeline.rasterizer.simd``, C++): against the float64 reference and
the cpu backend, thread-count determinism, the portable build, their exp, bad input and a
missing compiler."""
from __future__ import annotations

import os
import platform
import shutil
import subprocess
import sys
import textwrap

import numba
import numpy as np
import pytest
import torch
from raster_helpers import MAPS, PARAMS, random_camera, random_surfels, with_grad

from pipeline.benchmarks.surfel_scenes import dtu_camera, object_surfels
from pipeline.errors import ConfigError
from pipeline.rasterizer import Camera, Surfels, rasterize, resolve_backend, simd

# CI has a compiler (a missing one is a failure there, not a skip: .ci/run sets GCGS_REQUIRE_SIMD).
pytestmark = pytest.mark.skipif(
    shutil.which("c++") is None and not os.environ.get("GCGS_REQUIRE_SIMD"), reason="no C++ compiler on PATH"
)

# Tolerance against the float64 reference, relative to the largest magnitude of each tensor:
# the kernels work in float32 (moments and per-surfel sums in float64); observed <= 1.7e-5 for
# maps and <= 1.4e-4 for gradients on these scenes (the cpu backend's float32 path: <= 1.7e-4),
# bound 1e-3.
TOL = 1e-3
CASES = [  # width, height, surfels, channels, seed
    (24, 18, 30, 3, 0),
    (40, 30, 150, 8, 1),
    (33, 27, 400, 3, 2),
    (64, 48, 500, 1, 3),
]


def _render(s: Surfels, cam: Camera, kernels: str, cotangent_seed: int = 1):
    """Maps and gradients of every parameter and ``means2d`` for random cotangents, drawn in
    float64 so that every backend and dtype contracts with the same numbers."""
    s = with_grad(s)
    out = rasterize(s, cam, kernels)
    g = torch.Generator().manual_seed(cotangent_seed)
    cot = {k: torch.randn(getattr(out, k).shape, generator=g, dtype=torch.float64) for k in MAPS}
    sum((getattr(out, k) * cot[k].to(out.alpha.dtype)).sum() for k in MAPS).backward()
    grads = {k: getattr(s, k).grad for k in PARAMS}
    grads["means2d"] = out.means2d.grad
    return out, grads


def _as(s: Surfels, dtype) -> Surfels:
    return Surfels(*(getattr(s, k).to(dtype) for k in PARAMS))


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return ((a.double() - b.double()).abs().max() / b.double().abs().max().clamp_min(1e-12)).item()


@pytest.mark.parametrize("W,H,P,C,seed", CASES)
def test_simd_matches_the_float64_reference(W, H, P, C, seed):
    cam = random_camera(W, H, seed)
    s = random_surfels(P, cam, C, seed, torch.float32)
    a, ga = _render(s, cam, "simd")
    b, gb = _render(_as(s, torch.float64), cam, "reference")
    assert (b.alpha > 0).float().mean() > 0.5, "scene should cover most pixels"
    for k in MAPS:
        assert getattr(a, k).dtype == torch.float32
        assert _rel(getattr(a, k), getattr(b, k)) <= TOL, k
    assert torch.equal(a.radii, b.radii)
    for k in ga:
        assert gb[k].abs().max() > 0, f"gradient of {k} should not vanish"
        assert _rel(ga[k], gb[k]) <= TOL, f"d/d{k}: {_rel(ga[k], gb[k]):.2e}"


def test_simd_matches_cpu_on_a_dense_object():
    """The bench-raster scene (surfels tiling an object, many pairs per pixel): a threshold
    (alpha >= 1/255, the 0.99 cap, T > 0.5, rho3 <= rho2) may fall on the other side for a few
    pairs in float32, so compare the 99.9th percentile, and the share of outliers."""
    cam, n2w = dtu_camera(200, 150)
    s = object_surfels(10_000, n2w, seed=0)
    a, ga = _render(s, cam, "simd")
    b, gb = _render(s, cam, "cpu")
    for k in MAPS + tuple(ga):
        x, y = (getattr(a, k), getattr(b, k)) if k in MAPS else (ga[k], gb[k])
        err = ((x - y).abs() / y.abs().max()).flatten().double()
        assert torch.quantile(err, 0.999) <= 1e-4, k
        assert (err > 1e-3).double().mean() <= 1e-3, k


def _depth_cases():
    rng = np.random.default_rng(7)
    n = 5000
    spread = rng.uniform(1.0, 900.0, n)  # distinct depths
    ties = rng.choice([3.0, 4.5, 600.25], n)  # long runs of equal depths
    # depths closer than float32's spacing: the radix keys tie, the float64 order must not
    f32_twins = 600.0 + rng.integers(0, 40, n) * 1e-9 + rng.integers(0, 3, n) * 1e-4
    reversed_twins = 600.0 + np.arange(n)[::-1] * 1e-12  # one long key run, ids against depths
    base = rng.uniform(1.0, 900.0, n // 2)
    pairs = rng.permutation(np.concatenate([base, base + base * 1e-9]))  # short key runs
    return [spread, ties, f32_twins, reversed_twins, pairs, np.zeros(0)]


@pytest.mark.parametrize("case", range(6))
def test_depth_order_is_the_cpu_backends(case):
    """The radix sort against ``cpu.depth_order`` (numpy's sort, then ties by id), some
    surfels not drawn."""
    from pipeline.rasterizer import cpu

    depth = _depth_cases()[case]
    radii = np.random.default_rng(case).integers(0, 3, depth.shape[0]).astype(np.int32)
    got = simd.depth_order(depth, radii)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, cpu.depth_order(depth, radii))


def _prepare_cases():
    cam, n2w = dtu_camera(200, 150)
    yield object_surfels(5_000, n2w, seed=0), cam
    for seed in range(3):  # scales over six decades; seed 2 with zero and tiny opacities, surfels behind
        cam = random_camera(64, 48, seed)
        s = random_surfels(501, cam, 3, seed, torch.float32, scale=(1e-6, 3.0))
        if seed == 2:
            s.opacities.data[:10] = 0.0
            s.opacities.data[10:20] = 1e-3
            s.means.data[20:30, 2] *= -1.0
            # around the opacity from which the set-up takes the cap 9 without the log
            # (exp(4.5) / 255 = 0.353008; the C++ skips the log from 0.3532)
            near_cap = [0.3501, 0.352, 0.3530, 0.35300836, 0.3530084, 0.3531, 0.35319998, 0.3532, 0.35320002, 0.36]
            s.opacities.data[30:40] = torch.tensor(near_cap)
        yield s, cam


@pytest.mark.parametrize("case", range(4))
def test_prepare_is_the_cpu_backends_bit_for_bit(case):
    """The C++ set-up and binning against the numba kernels: every per-surfel output, the
    kernels' float32 rows (``geo`` rounded, then the centre depth, normal and box) and the
    tile lists, bit for bit."""
    from pipeline.rasterizer import cpu
    from pipeline.rasterizer import _kernels as K

    s, cam = list(_prepare_cases())[case]
    a = simd.prepare(s.means, s.quats, s.scales, s.opacities, s.features, cam)
    b = cpu.prepare(s.means, s.quats, s.scales, s.opacities, cam)
    if case == 3:
        assert (b.radii == 0).sum() >= 10, "the undrawn surfels' rows are compared too"
    for k in ("Tm", "nrm", "depth", "box", "radii", "centre", "tile_start", "tile_list", "emit_start", "slot_of_entry"):
        x, y = getattr(a, k), getattr(b, k)
        assert x.dtype == y.dtype and x.shape == y.shape, k
        assert x.tobytes() == y.tobytes(), k
    expected = np.concatenate([b.geo.astype(np.float32), b.Tm[:, 8:9], b.nrm, b.box.astype(np.float32)], axis=1)
    assert a.surf[:, : K.E_FEAT].tobytes() == expected.tobytes()
    C = s.features.shape[1]
    assert a.surf[:, K.E_FEAT : K.E_FEAT + C].tobytes() == s.features.numpy().tobytes(), "the features in the rows"
    # each tile's record region as the cpu backend's, with room for one vector behind it
    slack = simd.RECORD_SLACK * np.arange(b.rec_tile_start.shape[0])
    np.testing.assert_array_equal(a.rec_tile_start, b.rec_tile_start + slack)
    cost = np.diff(b.rec_tile_start) + cpu._ENTRY_COST * np.diff(a.tile_start)
    assert sorted(a.worker_tiles.tolist()) == list(range(cost.shape[0])), "every tile once"
    assert (np.diff(cost[a.worker_tiles]) <= 0).all(), "largest first"


def _entry_spans(s: Surfels, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """First and last tile column (0-15) of each (tile, surfel) entry's box in its tile."""
    with torch.no_grad():
        g = simd.prepare(s.means, s.quats, s.scales, s.opacities, s.features, cam)
    tile = np.repeat(np.arange(g.tile_start.shape[0] - 1), np.diff(g.tile_start))
    x0 = (tile % g.n_tx) * 16
    box = g.box[g.tile_list]
    return np.maximum(box[:, 0], x0) - x0, np.minimum(box[:, 1], np.minimum(x0 + 15, cam.width - 1)) - x0


def test_entries_at_most_8_wide_across_the_middle_of_a_tile():
    """The kernels evaluate an entry at most 8 pixels wide in its tile on 8 lanes from its own
    first column (0 or 8 when it lies in one half of the tile), a wider one on 16; the backward
    sums a window's lanes in the order of the tile row's 16. Scenes with all three kinds."""
    for seed in range(3):
        cam = random_camera(48, 32, seed)
        s = random_surfels(160, cam, 3, seed, torch.float32, scale=(0.01, 0.2))
        first, last = _entry_spans(s, cam)
        narrow = last - first < 8
        straddling = narrow & (first < 8) & (last >= 8)
        assert straddling.sum() >= 20 and (narrow & ~straddling).sum() >= 20 and (~narrow).sum() >= 20
        a, ga = _render(s, cam, "simd")
        b, gb = _render(_as(s, torch.float64), cam, "reference")
        for k in MAPS:
            assert _rel(getattr(a, k), getattr(b, k)) <= TOL, (seed, k)
        for k in ga:
            assert _rel(ga[k], gb[k]) <= TOL, (seed, k, _rel(ga[k], gb[k]))


def test_a_full_tile_leaves_the_next_tiles_records_alone():
    """Tiny surfels whose boxes are composited pixel for pixel fill their tile's record region;
    the kernels store a whole vector at a tile's last record, which once overwrote the first
    records of the next tile when that tile had been rendered first (on one thread: the larger
    first), and its gradients lost those pairs (9 of 300 such scenes, errors up to 114%)."""
    cam = random_camera(32, 16, 0)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        for seed in range(60):  # seeds 12, 14 and 50 overran
            s = random_surfels(6, cam, 3, seed, torch.float32, scale=(0.001, 0.004), opacity=(0.5, 0.95))
            _, ga = _render(s, cam, "simd")
            _, gb = _render(s, cam, "cpu")
            for k in ga:
                assert _rel(ga[k], gb[k]) <= TOL, (seed, k)
    finally:
        numba.set_num_threads(threads)


def test_same_input_same_output_any_thread_count():
    cam = random_camera(70, 50, 4)
    s = random_surfels(800, cam, 3, 4, torch.float32)
    a, ga = _render(s, cam, "simd")
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        b, gb = _render(s, cam, "simd")
    finally:
        numba.set_num_threads(threads)
    for k in MAPS:
        assert torch.equal(getattr(a, k), getattr(b, k)), k
    for k in ga:
        assert torch.equal(ga[k], gb[k]), k


@pytest.fixture(params=["x86-64-v3", "x86-64-v2"])
def portable_build(request, tmp_path):
    """The kernels built for x86-64-v3 (AVX2, no AVX-512: the lane-loop fallbacks of the masks,
    compress and expand) and x86-64-v2 (SSE4.2: also the window's lane rotation)."""
    flags = tuple(f"-march={request.param}" if f == "-march=native" else f for f in simd.FLAGS)
    lib = simd.load(simd.build(shutil.which("c++"), flags, tmp_path))
    saved = dict(simd._state)
    simd._state.clear()
    simd._state["lib"] = lib
    try:
        yield
    finally:
        simd._state.clear()
        simd._state.update(saved)


@pytest.mark.skipif(platform.machine() != "x86_64", reason="the portable builds target x86-64")
def test_portable_build_gives_the_same_results(portable_build):
    cam = random_camera(40, 30, 5)
    s = random_surfels(300, cam, 3, 5, torch.float32)
    a, ga = _render(s, cam, "simd")
    b, gb = _render(_as(s, torch.float64), cam, "reference")
    for k in MAPS:
        assert _rel(getattr(a, k), getattr(b, k)) <= TOL, k
    for k in ga:
        assert _rel(ga[k], gb[k]) <= TOL, k


def test_exp_within_two_ulp():
    x = -np.linspace(0.0, 87.0, 200_003, dtype=np.float32)
    got = simd.exp(x).astype(np.float64)
    want = np.exp(x.astype(np.float64))
    ulp = np.spacing(np.exp(x)).astype(np.float64)
    assert np.max(np.abs(got - want) / ulp) <= 2.0
    assert simd.exp(np.array([0.0], np.float32))[0] == 1.0


def test_extremes_give_finite_zeros():
    cam = random_camera(9, 7, 0)
    empty = Surfels(torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 2), torch.zeros(0), torch.zeros(0, 3))
    out = rasterize(empty, cam, "simd")
    assert all(getattr(out, k).abs().max() == 0 for k in MAPS)
    one_px = Camera(K=np.array([[2.0, 0, 0], [0, 2.0, 0], [0, 0, 1]]), world_to_cam=np.eye(4), width=1, height=1)
    s = random_surfels(20, one_px, 3, 1, torch.float32)
    a, ga = _render(s, one_px, "simd")
    assert all(torch.isfinite(getattr(a, k)).all() for k in MAPS)
    assert all(torch.isfinite(g).all() for g in ga.values())


def test_bad_input_is_refused():
    cam = random_camera(20, 16, 0)
    with pytest.raises(ValueError, match="float32"):
        rasterize(random_surfels(10, cam, 3, 0, torch.float64), cam, "simd")
    with pytest.raises(ValueError, match="at most 8 feature channels"):
        rasterize(random_surfels(10, cam, 9, 0, torch.float32), cam, "simd")


def test_a_missing_compiler_is_named(monkeypatch):
    saved = dict(simd._state)
    simd._state.clear()
    monkeypatch.setenv("CXX", "no-such-compiler-gcgs")
    try:
        ok, why = simd.available()
        assert not ok and "no-such-compiler-gcgs" in why
        with pytest.raises(simd.SimdUnavailable, match="no-such-compiler-gcgs"):
            simd.library()
    finally:
        simd._state.clear()
        simd._state.update(saved)


def test_a_failed_build_names_the_source(tmp_path):
    with pytest.raises(simd.SimdUnavailable, match="_simd.cpp"):
        simd.build(shutil.which("c++"), simd.FLAGS + ("-DGCGS_BROKEN", "-include", "no/such/header.h"), tmp_path)
    assert not list(tmp_path.glob("*.so*")), "a failed build leaves no library behind"


def test_auto_is_simd_for_float32_and_cpu_where_the_kernels_cannot_take_the_surfels():
    cam = random_camera(20, 16, 0)
    assert resolve_backend("auto") == "simd" and resolve_backend("simd") == "simd"
    s32 = random_surfels(40, cam, 3, 0, torch.float32)
    for backend in ("simd", "cpu"):  # auto is bit for bit the backend it picks
        want, got = rasterize(s32, cam, backend), rasterize(s32, cam, "auto")
        same = all(torch.equal(getattr(got, k), getattr(want, k)) for k in MAPS)
        assert same == (backend == "simd")
    s64 = random_surfels(40, cam, 3, 0, torch.float64)
    got, want = rasterize(s64, cam, "auto"), rasterize(s64, cam, "cpu")
    assert got.features.dtype == torch.float64 and all(torch.equal(getattr(got, k), getattr(want, k)) for k in MAPS)
    s9 = random_surfels(40, cam, 9, 0, torch.float32)
    assert torch.equal(rasterize(s9, cam, "auto").features, rasterize(s9, cam, "cpu").features)


def test_without_kernels_auto_falls_back_with_one_warning_and_simd_is_an_error(monkeypatch, capsys):
    import pipeline.rasterizer as R

    saved = dict(simd._state)
    simd._state.clear()
    monkeypatch.setenv("CXX", "no-such-compiler-gcgs")
    monkeypatch.setattr(R, "_fallback_said", [])
    try:
        cam = random_camera(20, 16, 0)
        s = random_surfels(40, cam, 3, 0, torch.float32)
        assert resolve_backend("auto") == "cpu"
        assert torch.equal(rasterize(s, cam, "auto").features, rasterize(s, cam, "cpu").features)
        err = capsys.readouterr().err
        assert err.count("warning") == 1 and "no-such-compiler-gcgs" in err and "numba cpu" in err
        with pytest.raises(ConfigError, match="simd.*no-such-compiler-gcgs"):
            resolve_backend("simd")
    finally:
        simd._state.clear()
        simd._state.update(saved)


def test_training_runs_with_the_compiler_hidden(tmp_path):
    """The fallback in a fresh process, as on a machine without a compiler: one warning line,
    a render and its backward, exit 0."""
    code = textwrap.dedent("""
        import torch
        from pipeline.rasterizer import rasterize, resolve_backend
        from pipeline.benchmarks.surfel_scenes import dtu_camera, object_surfels
        cam, norm_to_world = dtu_camera(40, 30)
        s = object_surfels(200, norm_to_world)
        s.means.requires_grad_(True)
        assert resolve_backend("auto") == "cpu"
        out = rasterize(s, cam, "auto")
        out.features.sum().backward()
        assert torch.isfinite(s.means.grad).all()
        print("rendered")
    """)
    env = {**os.environ, "CXX": "no-such-compiler-gcgs", "GCGS_CACHE_DIR": str(tmp_path)}
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "rendered"
    warnings = [line for line in res.stderr.splitlines() if "warning" in line]
    assert len(warnings) == 1 and "no-such-compiler-gcgs" in warnings[0], res.stderr
    assert "Traceback" not in res.stderr


def _fake_compiler(tmp_path):
    """A stand-in ``c++`` that writes its ``-o`` file and counts its runs (no real build)."""
    script = tmp_path / "fake-c++"
    script.write_text(textwrap.dedent(f"""\
        #!/bin/sh
        if [ "$1" = "--version" ]; then echo "fake 1.0"; exit 0; fi
        echo run >> {tmp_path / "runs"}
        while [ $# -gt 0 ]; do if [ "$1" = "-o" ]; then echo lib > "$2"; fi; shift; done
    """))
    script.chmod(0o755)
    return str(script)


def test_the_build_cache_keeps_one_build_per_machine(tmp_path, monkeypatch):
    """A checkout shared by nodes of two CPU types keeps both builds; a new source replaces
    only the same machine's build; an existing build is reused without compiling."""
    cxx, cache = _fake_compiler(tmp_path), tmp_path / "cache"
    source = tmp_path / "_simd.cpp"
    source.write_text("// v1")
    monkeypatch.setattr(simd, "SOURCE", source)
    monkeypatch.setattr(simd, "_cpu_flags", lambda: "flags avx2")
    a1 = simd.build(cxx, simd.FLAGS, cache)
    monkeypatch.setattr(simd, "_cpu_flags", lambda: "flags avx512f")
    b1 = simd.build(cxx, simd.FLAGS, cache)
    assert a1 != b1 and a1.exists() and b1.exists()
    assert simd.build(cxx, simd.FLAGS, cache) == b1
    assert (tmp_path / "runs").read_text().count("run") == 2, "the second call reused the build"
    source.write_text("// v2")
    b2 = simd.build(cxx, simd.FLAGS, cache)
    assert b2.exists() and not b1.exists(), "the same machine's old build is replaced"
    assert a1.exists(), "another machine's build is never deleted"


def test_an_unwritable_cache_folder_moves_on_to_the_next(tmp_path, monkeypatch):
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the cache folder would be")
    monkeypatch.setenv("GCGS_CACHE_DIR", str(blocked))
    assert simd.cache_dirs()[0] == blocked / "simd"
    saved = dict(simd._state)
    simd._state.clear()
    try:
        ok, why = simd.available()
        assert ok, why
    finally:
        simd._state.clear()
        simd._state.update(saved)


def test_kernel_functions_are_typed_once():
    """numba types a kernel argument from its cached type, not a new one per call."""
    from numba import typeof

    k = simd._kernels()["simd_forward"]
    assert typeof(k) is k.numba_type and typeof(k) is typeof(k)
