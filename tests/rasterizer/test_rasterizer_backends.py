"""cpu vs reference on random scenes, gradcheck, determinism, the densification gradient."""
from __future__ import annotations

import numba
import numpy as np
import pytest
import torch
from raster_helpers import MAPS, PARAMS, random_camera, random_surfels, render_and_grads, with_grad

from pipeline.rasterizer import Camera, Surfels, rasterize

# Tolerances, relative to the largest magnitude of each compared tensor:
# * float64: both backends compute the same maths in float64 (the cpu kernel
#   factorises the intersection through adj(T) and det T, so rounding differs);
#   observed <= 4e-13, bound 1e-10.
# * float32: the cpu kernel works in float64 internally while the reference works in
#   float32: cumulative products over ~100 pairs, gradients divided by (1 - alpha) >=
#   0.01, and the reference's distortion cancels ~100x (m ~ 0.9); observed <= 1.5e-4
#   for maps and gradients, bound 2e-3 (float32 epsilon is 6e-8).
TOL = {torch.float64: 1e-10, torch.float32: 2e-3}

CASES = [  # width, height, surfels, channels, seed
    (24, 18, 30, 3, 0),
    (40, 30, 150, 32, 1),
    (33, 27, 400, 3, 2),
]


def assert_close(a: torch.Tensor, b: torch.Tensor, tol: float, what: str) -> None:
    scale = b.abs().max().clamp_min(1e-12)
    err = ((a - b).abs().max() / scale).item()
    assert err <= tol, f"{what}: max error {err:.2e} of max |ref| {scale.item():.3e} exceeds {tol:.0e}"


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("W,H,P,C,seed", CASES)
def test_cpu_matches_reference(W, H, P, C, seed, dtype):
    cam = random_camera(W, H, seed)
    s = random_surfels(P, cam, C, seed, dtype)
    a, ga = render_and_grads(s, cam, "cpu")
    b, gb = render_and_grads(s, cam, "reference")
    assert (b.alpha > 0).float().mean() > 0.5, "scene should cover most pixels"
    for k in MAPS:
        assert getattr(a, k).dtype == dtype
        assert_close(getattr(a, k), getattr(b, k), TOL[dtype], k)
    assert torch.equal(a.radii, b.radii)
    assert_close(a.means2d, b.means2d, TOL[dtype], "means2d")
    for k in list(PARAMS) + ["means2d"]:
        assert gb[k].abs().max() > 0, f"gradient of {k} should not vanish"
        assert_close(ga[k], gb[k], TOL[dtype], f"d/d{k}")


def test_sh_colours_match_reference():
    cam = random_camera(30, 22, 5)
    s = random_surfels(120, cam, seed=5, sh_degree=3)
    a, ga = render_and_grads(s, cam, "cpu")
    b, gb = render_and_grads(s, cam, "reference")
    for k in MAPS:
        assert_close(getattr(a, k), getattr(b, k), TOL[torch.float64], k)
    for k in PARAMS:
        assert_close(ga[k], gb[k], TOL[torch.float64], f"d/d{k}")


def test_reference_blocks_equal_dense():
    """Block culling by support boxes changes nothing: the boxes are conservative."""
    cam = random_camera(37, 29, 3)
    s = random_surfels(200, cam, seed=3, scale=(0.02, 0.6))
    a, ga = render_and_grads(s, cam, "reference", reference_block=8)
    b, gb = render_and_grads(s, cam, "reference")
    for k in MAPS:
        assert_close(getattr(a, k), getattr(b, k), 1e-12, k)
    for k in PARAMS:
        assert_close(ga[k], gb[k], 1e-12, f"d/d{k}")


def _gradcheck(backend: str, seed: int) -> None:
    cam = random_camera(9, 7, seed, near=0.5, far=10.0)
    s = random_surfels(4, cam, C=2, seed=seed, scale=(0.2, 0.5), opacity=(0.2, 0.8))

    def f(means, quats, scales, opacities, features):
        out = rasterize(Surfels(means, quats, scales, opacities, features), cam, backend)
        return tuple(getattr(out, k) for k in MAPS)

    inputs = tuple(getattr(with_grad(s), k) for k in PARAMS)
    # Away from the measure-zero switches (alpha thresholds, rho3/rho2, median index)
    # the maps are smooth; these seeds keep every pair clear of them.
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_gradcheck_float64(backend):
    _gradcheck(backend, seed=7)


def test_same_input_same_output_any_thread_count():
    """Bitwise reproducible, also across numba thread counts (no atomics, fixed sums)."""
    cam = random_camera(48, 40, 4)
    s = random_surfels(600, cam, seed=4, dtype=torch.float32)
    a, ga = render_and_grads(s, cam, "cpu")
    b, gb = render_and_grads(s, cam, "cpu")
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        c, gc = render_and_grads(s, cam, "cpu")
    finally:
        numba.set_num_threads(threads)
    for k in MAPS:
        assert torch.equal(getattr(a, k), getattr(b, k)) and torch.equal(getattr(a, k), getattr(c, k)), k
    for k in ga:
        assert torch.equal(ga[k], gb[k]) and torch.equal(ga[k], gc[k]), k


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_means2d_grad_is_the_screen_translation_gradient(backend):
    """Shifting the principal point by d moves every splat by d pixels on screen, so
    dL/dcx must equal the sum over surfels of means2d.grad[:, 0] (likewise y)."""
    cam = random_camera(26, 20, 6)
    s = random_surfels(60, cam, seed=6)
    g = torch.Generator().manual_seed(2)
    cot = {k: torch.randn(getattr(rasterize(s, cam, backend), k).shape, generator=g, dtype=torch.float64) for k in MAPS}

    def loss(camera: Camera, surfels: Surfels):
        out = rasterize(surfels, camera, backend)
        return sum((getattr(out, k) * cot[k]).sum() for k in MAPS), out

    L, out = loss(cam, with_grad(s))
    L.backward()
    eps = 1e-6
    for axis in (0, 1):
        shifted = []
        for sign in (1, -1):
            K = cam.K.clone()
            K[axis, 2] += sign * eps
            with torch.no_grad():
                cam_s = Camera(K, cam.world_to_cam, cam.width, cam.height, cam.near, cam.far)
                shifted.append(loss(cam_s, s)[0].item())
        fd = (shifted[0] - shifted[1]) / (2 * eps)
        assert out.means2d.grad[:, axis].sum().item() == pytest.approx(fd, rel=1e-5, abs=1e-6)


def test_radii_mark_visible_surfels():
    cam = random_camera(20, 16, 8)
    s = random_surfels(30, cam, seed=8)
    means = s.means.clone()
    means[0] = means[0] + 100.0 * cam.world_to_cam[0, :3]  # 100 units along the camera's x axis: off-screen
    opac = s.opacities.clone()
    opac[1] = 0.0  # below 1/255: never drawn
    s = Surfels(means, s.quats, s.scales, opac, s.features)
    out = rasterize(s, cam, "cpu")
    assert out.radii.dtype == torch.int32
    assert out.radii[0] == 0 and out.radii[1] == 0
    assert (out.radii[2:] > 0).float().mean() > 0.8


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_chain_rule_writes_zeros_for_surfels_never_drawn(dtype):
    """``reduce_and_chain`` fills every row of its outputs (the backward hands it
    uninitialised arrays): zeros for a surfel without slots, its gradient for the others."""
    from pipeline.rasterizer import _kernels as K

    rng = np.random.default_rng(0)
    P, C = 600, 3
    emit_start = np.concatenate([[0], np.cumsum(rng.integers(0, 3, P))]).astype(np.int64)  # ~1/3 never drawn
    slots = rng.standard_normal((emit_start[-1], K.S_FIXED + C))
    quats = rng.standard_normal((P, 4)).astype(dtype)
    scales, means = rng.uniform(0.1, 1.0, (P, 2)).astype(dtype), rng.standard_normal((P, 3)).astype(dtype)
    Tm, nrm = rng.standard_normal((P, 9)).astype(dtype), rng.standard_normal((P, 3)).astype(dtype)
    Tm[:, 8] = rng.uniform(1.0, 2.0, P)
    shapes = [(P, 3), (P, 4), (P, 2), (P,), (P, C), (P, 2)]
    out = [np.full(shape, np.nan, dtype) for shape in shapes]
    K.reduce_and_chain(emit_start, slots, quats, scales, means, Tm, nrm, np.eye(3) * 50.0, np.eye(3), *out)
    never = np.diff(emit_start) == 0
    assert 100 < never.sum() < P - 100
    for o in out:
        assert (o[never] == 0).all() and np.isfinite(o[~never]).all()
        assert (o[~never] != 0).any(axis=tuple(range(1, o.ndim))).mean() > 0.9


def test_tile_lists_are_front_to_back_with_ties_in_id_order():
    """Each tile's list equals the stable (depth, id) sort of the drawn surfels whose box
    touches it and that reach it (random bits), also with many equal depths (the global
    quicksort breaks ties by id), and each entry's gradient slot is its surfel's own slot, in
    row-major order of the tiles it reaches."""
    import numpy as np

    from pipeline.rasterizer import _kernels as K
    from pipeline.rasterizer import cpu

    rng = np.random.default_rng(0)
    P, n_tx, n_ty = 400, 5, 4
    x0, y0 = rng.integers(0, 80, P), rng.integers(0, 64, P)
    box = np.stack([x0, np.minimum(x0 + rng.integers(0, 30, P), 79), y0, np.minimum(y0 + rng.integers(0, 30, P), 63)], 1)
    radii = (rng.random(P) > 0.2).astype(np.int32)
    depth = rng.integers(0, 12, P).astype(np.float64)  # ~30 surfels per depth value
    reached = rng.integers(0, 2**9, P).astype(np.uint64)  # boxes of at most 3 x 3 tiles
    geo = np.zeros((P, K.GEO_SIZE))  # read only for boxes of more than 64 tiles
    binned = K.bin_tiles(cpu.depth_order(depth, radii), box, reached, geo, False, n_tx, n_ty)
    tile_start, tile_list, emit_start, slot_of_entry, _ = binned

    def box_tiles(s):  # row-major
        return [(tx, ty) for ty in range(box[s, 2] // 16, box[s, 3] // 16 + 1) for tx in range(box[s, 0] // 16, box[s, 1] // 16 + 1)]

    def reached_tiles(s):
        return [t for i, t in enumerate(box_tiles(s)) if int(reached[s]) >> i & 1]

    assert (np.diff(emit_start) == [len(reached_tiles(s)) if radii[s] else 0 for s in range(P)]).all()
    dropped = 0
    for t in range(n_tx * n_ty):
        tx, ty = t % n_tx, t // n_tx
        hit = [s for s in range(P) if radii[s] and (tx, ty) in reached_tiles(s)]
        dropped += sum(1 for s in range(P) if radii[s] and (tx, ty) in box_tiles(s)) - len(hit)
        expected = sorted(hit, key=lambda s: (depth[s], s))
        got = tile_list[tile_start[t] : tile_start[t + 1]]
        assert list(got) == expected
        for j, s in zip(range(tile_start[t], tile_start[t + 1]), got):
            assert slot_of_entry[j] == emit_start[s] + reached_tiles(s).index((tx, ty))
    assert dropped > 100, "the bits drop tiles"


@pytest.mark.parametrize("n_workers", [1, 2, 3, 8])
def test_tile_schedule_partitions_and_balances(n_workers):
    """Every tile goes to exactly one worker; loads within the LPT bound (mean + one tile),
    also for a largest-first cost list (the case a contiguous prange split got wrong)."""
    import numpy as np

    from pipeline.rasterizer import _kernels as K

    rng = np.random.default_rng(n_workers)
    for cost in (rng.pareto(1.5, 300) * 100, np.sort(rng.random(475))[::-1] * 1e4, np.zeros(5)):
        start, tiles = K.schedule_tiles(cost.astype(np.float64), n_workers)
        assert start.shape == (n_workers + 1,) and start[0] == 0 and start[-1] == cost.size
        assert np.array_equal(np.sort(tiles), np.arange(cost.size))
        loads = np.array([cost[tiles[start[k] : start[k + 1]]].sum() for k in range(n_workers)])
        assert loads.max() <= cost.sum() / n_workers + cost.max() + 1e-9
        for k in range(n_workers):  # each worker renders its tiles largest first
            assert np.all(np.diff(cost[tiles[start[k] : start[k + 1]]]) <= 0)


def _loss(out, seed=1):
    g = torch.Generator().manual_seed(seed)
    return sum((getattr(out, k) * torch.randn(getattr(out, k).shape, generator=g, dtype=out.alpha.dtype)).sum() for k in MAPS)


def test_scratch_buffers_are_never_shared_between_live_graphs():
    """Two renders whose graphs are alive at once (different scenes, back-propagated in
    reverse order) get the same gradients as renders done one at a time; a freed graph's
    buffer is reused by the next render."""
    from raster_helpers import PARAMS

    from pipeline.rasterizer import cpu

    cam = random_camera(40, 32, 2)
    scenes = [random_surfels(300, cam, seed=k, dtype=torch.float32) for k in (10, 11)]
    alone = [render_and_grads(s, cam, "cpu")[1] for s in scenes]
    cpu.SCRATCH.clear()
    leaves = [with_grad(s) for s in scenes]
    outs = [rasterize(s, cam, "cpu") for s in leaves]
    assert cpu.SCRATCH.idle_bytes == 0  # both forward buffers are held by live graphs
    for k in (1, 0):
        _loss(outs[k]).backward()
    for s, ref in zip(leaves, alone):
        for name in PARAMS:
            assert torch.equal(getattr(s, name).grad, ref[name]), name
    del outs
    idle = cpu.SCRATCH.idle_bytes
    assert idle > 0  # freed graphs gave their buffers back
    with torch.no_grad():
        rasterize(scenes[0], cam, "cpu")
    assert cpu.SCRATCH.idle_bytes == idle  # taken and given back: no new allocation kept


def test_retain_graph_backward_twice_gives_the_same_gradients():
    cam = random_camera(32, 24, 3)
    s = with_grad(random_surfels(200, cam, seed=5))
    loss = _loss(rasterize(s, cam, "cpu"))
    loss.backward(retain_graph=True)
    first = s.means.grad.clone()
    s.means.grad = None
    rasterize(random_surfels(200, cam, seed=6), cam, "cpu")  # a render in between must not clobber the records
    loss.backward()
    assert torch.equal(s.means.grad, first)


def test_depth_order_with_a_long_run_of_equal_depths():
    """A fronto-parallel plane: ~21000 surfels at one depth (the run sorted by np.sort, not
    by insertion) come out in id order, and so do the short runs around it."""
    import numpy as np

    from pipeline.rasterizer import cpu

    rng = np.random.default_rng(1)
    depth = np.where(rng.random(30000) < 0.7, 5.0, np.round(rng.random(30000) * 10, 2))
    radii = (rng.random(30000) < 0.9).astype(np.int32)
    order = cpu.depth_order(depth, radii)
    drawn = np.flatnonzero(radii)
    assert np.array_equal(order, drawn[np.lexsort((drawn, depth[drawn]))])
