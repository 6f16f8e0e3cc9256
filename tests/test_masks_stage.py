"""``gcgs masks`` as a user runs it (issue 58): a synthetic capture prepared without masks and
its MVS init -> a new scene whose masks are marked derived and match the object, the input
untouched, an overlay per view; a fallback named on stderr; refusals in one line that leave
nothing behind. Scene: tests/test_masks.py's object on a block (views 23, 24, 33, 200x150)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline import cli
from pipeline import masks as M
from pipeline.data import dtu
from pipeline.init.io import DepthMap, depth_path, load_init_depths, write_depth
from pipeline.meshing.region import Region
from pipeline.synth import shapes
from pipeline.synth.scenes import SynthScene
from test_atomic import tree_digest
from test_masks import H, VIEWS, W, block_scene, render

REPO = Path(__file__).resolve().parents[1]
PARAMS = str(REPO / "params.yaml")
MIN_IOU = 0.9


def _gcgs(capsys, *argv) -> tuple[int, str]:
    rc = cli.main([str(a) for a in argv])
    return rc, capsys.readouterr().err


def _lines(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ln.strip()]


@pytest.fixture(scope="module")
def capture(tmp_path_factory, bundled_scan):
    """The source scan (images, cameras, the true masks), the scene prepared from it without
    masks, the one prepared with them (given masks), and the init folder of the former."""
    root = tmp_path_factory.mktemp("masks_stage")
    cams = dtu.load_cameras(bundled_scan)
    views = render(block_scene(cams), cams, table_half_mm=125.0)
    src = dtu.write_scene(root / "src", images=dict(zip(VIEWS, views.images)), K=dict(zip(VIEWS, views.K)),
                          world_to_cam=dict(zip(VIEWS, views.world_to_cam)), norm_to_world=views.norm_to_world,
                          masks=dict(zip(VIEWS, views.truth)), meta={"name": "block"})
    prepare = ["prepare", "--src", src, "--views", *VIEWS, "--width", W, "--params", PARAMS]
    assert cli.main([str(a) for a in prepare + ["--out", root / "scene", "--masks", "none"]]) == 0
    assert cli.main([str(a) for a in prepare + ["--out", root / "given"]]) == 0
    assert cli.main([str(a) for a in ["init", "--scene", root / "scene", "--out-dir", root / "init",
                                      "--params", PARAMS]]) == 0
    return {"root": root, "views": views, "cams": cams, "scene": root / "scene", "given": root / "given",
            "init": root / "init"}


@pytest.fixture(scope="module")
def derived(capture):
    """``gcgs masks`` run once on the capture, with the input's bytes before and after."""
    root, scene = capture["root"], capture["scene"]
    before = tree_digest(scene)
    out, overlays = root / "derived", root / "overlays"
    rc = cli.main(["masks", "--scene", str(scene), "--init-dir", str(capture["init"]), "--out-scene", str(out),
                   "--overlays", str(overlays), "--params", PARAMS])
    return {"rc": rc, "out": out, "overlays": overlays, "before": before, "after": tree_digest(scene)}


def test_the_new_scene_has_derived_masks_that_match_the_object(capture, derived):
    assert derived["rc"] == 0
    out = derived["out"]
    meta = json.loads((out / "scene.json").read_text())
    given_meta = json.loads((capture["scene"] / "scene.json").read_text())
    assert meta["masks"] == "derived" and "masks" not in given_meta
    assert {k: v for k, v in meta.items() if k not in ("masks", "derived_masks")} == given_meta  # nothing else changed
    assert sorted(meta["derived_masks"]["views"]) == sorted(map(str, VIEWS))
    scene = dtu.load_scene(out, view_ids=None)  # what every later stage reads
    assert scene.view_ids == VIEWS and scene.masks is not None
    ious = [float((m & t).sum() / (m | t).sum()) for m, t in zip(scene.masks, capture["views"].truth)]
    assert min(ious) >= MIN_IOU, ious
    # The copy is byte for byte but for scene.json and the new mask/ (the format prepare writes masks in).
    copied = {k: v for k, v in tree_digest(out).items() if k != "scene.json" and not k.startswith("mask/")}
    assert copied == {k: v for k, v in derived["before"].items() if k != "scene.json"}
    assert sorted(p.name for p in (out / "mask").iterdir()) == [f"{v:03d}.png" for v in VIEWS]
    assert set(np.unique(cv2.imread(str(out / "mask" / "023.png"), cv2.IMREAD_UNCHANGED))) <= {0, 255}


def test_init_on_the_new_scene_matches_inside_the_derived_masks_only(capture, derived, tmp_path):
    """The stages read derived masks as given ones: MVS on the new scene leaves no depth
    outside them, where on the scene without masks it matched the table too."""
    assert cli.main(["init", "--scene", str(derived["out"]), "--out-dir", str(tmp_path / "init"),
                     "--params", PARAMS]) == 0
    scene = dtu.load_scene(derived["out"], view_ids=None)
    new = load_init_depths(tmp_path / "init", scene, needed_by="this test")
    old = load_init_depths(capture["init"], scene, needed_by="this test")
    for depth, without, mask in zip(new, old, scene.masks):
        assert (without.valid & ~mask).sum() > 0.1 * mask.sum()
        assert depth.valid.any() and not (depth.valid & ~mask).any()


def test_the_input_scene_is_unchanged(derived):
    assert derived["rc"] == 0 and derived["after"] == derived["before"]


def test_an_overlay_per_view_shows_the_mask_over_the_image(capture, derived):
    names = [f"{v:03d}.png" for v in VIEWS]
    assert sorted(p.name for p in derived["overlays"].iterdir() if p.suffix == ".png") == names
    scene = dtu.load_scene(derived["out"], view_ids=None)
    for v, image, mask in zip(VIEWS, scene.images, scene.masks):
        shown = cv2.imread(str(derived["overlays"] / f"{v:03d}.png"))[..., ::-1].astype(float)
        assert shown.shape == (H, W, 3)
        plain = M.to_uint8(image)[..., ::-1].astype(float)
        # Off the contour, which also runs along the image's border where the mask reaches it.
        inside = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8), borderType=cv2.BORDER_CONSTANT,
                           borderValue=0).astype(bool)
        outside = ~cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        assert np.array_equal(shown[inside], plain[inside])  # the object as it is
        assert shown[outside].mean() < 0.5 * plain[outside].mean()  # the rest darkened
        cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
        edge = mask & ~cv2.erode(mask.astype(np.uint8), cross).astype(bool)  # pixels 4-next to the outside
        contour = np.all(shown == M.OVERLAY_CONTOUR_RGB, axis=-1)
        assert contour[edge].all() and not contour[~mask].any()  # the outline drawn on the mask's own edge


def test_a_fallback_is_one_warning_per_view_on_stderr(capture, capsys, tmp_path):
    """Depth maps that see only the table (the init missed the object): every view falls
    back to the region's silhouette (the sphere cut by the table), each named in one warning
    line with the failed test; the scene is written (exit 0) with those masks."""
    views = capture["views"]
    empty = SynthScene("empty", 0, 0, [shapes.Part(np.zeros((3, 3)), np.array([[0, 1, 2]]), "noise", False)],
                       views.scene.local_to_world, views.scene.light_dir_world)
    table = render(empty, capture["cams"], table_half_mm=125.0).depths
    scene = dtu.load_scene(capture["scene"], view_ids=None)
    for v, depth, K, T in zip(VIEWS, table, scene.K, scene.world_to_cam):
        seen = depth > 0
        write_depth(depth_path(tmp_path / "init", v), DepthMap(v, depth.astype(np.float32), seen.astype(np.float32),
                                                               seen, K, T))
    rc, err = _gcgs(capsys, "masks", "--scene", capture["scene"], "--init-dir", tmp_path / "init",
                    "--out-scene", tmp_path / "out", "--params", PARAMS)
    assert rc == 0
    warnings = [ln for ln in _lines(err) if ln.startswith("gcgs: warning: ")]
    assert len(warnings) == len(VIEWS)
    for v, line in zip(VIEWS, warnings):
        assert f"view {v}:" in line and "no object points" in line and "region's silhouette" in line
    record = json.loads((tmp_path / "out" / "scene.json").read_text())["derived_masks"]
    assert {r["method"] for r in record["views"].values()} == {"fallback_region"}
    out = dtu.load_scene(tmp_path / "out", view_ids=None)
    region = Region(np.array(record["region"]["sphere_centre_mm"]), record["region"]["sphere_radius_mm"],
                    np.array(record["region"]["support_plane"]), record["region"]["plane_margin_mm"])
    for mask, K, T in zip(out.masks, out.K, out.world_to_cam):
        expected = M.silhouette(region, K, T, (H, W), parts="no_footprint")
        assert (mask != expected).mean() < 1e-3  # the record's rounding of the plane
        assert mask.any() and not mask.all()  # cut by the table


@pytest.mark.parametrize("case", ["given_masks", "already_derived", "missing_init", "output_inside_input",
                                  "overlays_inside_output"])
def test_refusals_are_one_line_and_leave_nothing_behind(capture, derived, capsys, tmp_path, case):
    scene, init = capture["scene"], capture["init"]
    out, overlays = tmp_path / "new", None
    expected = {"given_masks": "given masks always win", "already_derived": "already has derived masks",
                "missing_init": "init folder not found", "output_inside_input": "lies inside the input",
                "overlays_inside_output": "must not hold one another"}[case]
    if case == "given_masks":
        scene = capture["given"]
    elif case == "already_derived":
        scene = derived["out"]
    elif case == "missing_init":
        init = tmp_path / "no_init"
    elif case == "output_inside_input":
        out = scene / "derived"
    else:
        overlays = out / "overlays"
    inputs = {p: tree_digest(p) for p in (scene, capture["init"])}
    before = sorted(p.name for p in tmp_path.iterdir())
    args = ["masks", "--scene", scene, "--init-dir", init, "--out-scene", out, "--params", PARAMS]
    rc, err = _gcgs(capsys, *args, *(["--overlays", overlays] if overlays else []))
    lines = _lines(err)
    assert rc != 0 and len(lines) == 1 and lines[0].startswith("gcgs masks: error: ") and expected in lines[0], err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == before
    assert {p: tree_digest(p) for p in inputs} == inputs


@pytest.mark.parametrize("layout", ["colmap_text", "colmap_binary", "nerfstudio"])
def test_captures_of_every_layout_get_derived_masks_and_surfels_only_inside(capture, tmp_path, layout):
    """The same capture without masks as a COLMAP (text, binary) or nerfstudio folder, as a
    user brings it, through the usual stages with no second pass: prepare (every image an
    input view; it derives the masks), init, priors, a short training. The masks match the
    object (IoU >= 0.9) and no surfel ends outside the region (the sphere and the derived
    masks' visual hull)."""
    from pipeline.config.optimize import OptimizeConfig
    from pipeline.data import export
    from pipeline.optimize.region import region_from_views
    from pipeline.surfels import read_surfel_ply

    views = capture["views"]
    ids = range(len(VIEWS))  # COLMAP and nerfstudio number views by image name, from 0
    parts = (dict(zip(ids, views.K)), dict(zip(ids, views.world_to_cam)), (W, H), dict(zip(ids, views.images)))
    src = tmp_path / "capture"
    if layout == "nerfstudio":
        export.write_nerfstudio(src, *parts)
    else:
        export.write_colmap(src, *parts, binary=layout == "colmap_binary")
    out, init, priors, surfels = (tmp_path / d for d in ("scene", "init", "priors", "surfels"))
    for argv in (["prepare", "--src", src, "--out", out, "--width", W],  # no --views: every image
                 ["init", "--scene", out, "--out-dir", init],
                 ["priors", "--scene", out, "--init-dir", init, "--out-dir", priors],
                 ["optimize", "--scene", out, "--init-dir", init, "--priors-dir", priors, "--out-dir", surfels,
                  "--iterations", 120, "--no-progress"]):
        assert cli.main([str(a) for a in argv] + ["--params", PARAMS]) == 0, argv[0]
    derived = dtu.load_scene(out, view_ids=None)
    assert derived.view_ids == [0, 1, 2]
    ious = [iou for iou in (float((m & t).sum() / (m | t).sum()) for m, t in zip(derived.masks, views.truth))]
    assert min(ious) >= MIN_IOU, (layout, ious)
    trained = json.loads((surfels / "train.json").read_text())
    assert trained["masks"] and trained["surfel_budget"]["object_area_from"] == "masks"
    cfg = OptimizeConfig.default()  # conf/'s region: what params.yaml composes
    region = region_from_views(derived, [np.asarray(m, bool) for m in derived.masks], cfg)
    params = read_surfel_ply(surfels / "surfels.ply", derived.norm_to_world)
    assert params.num >= 32 and bool(region.contains(params.means).all())


def test_masks_without_an_init_folder_run_the_mvs_themselves(capture, derived, tmp_path):
    """``gcgs masks`` without ``--init-dir`` runs the init's MVS in memory: the same masks as
    from the init folder the same settings wrote."""
    out = tmp_path / "derived"
    assert cli.main(["masks", "--scene", str(capture["scene"]), "--out-scene", str(out), "--params", PARAMS]) == 0
    a, b = dtu.load_scene(out, view_ids=None), dtu.load_scene(derived["out"], view_ids=None)
    assert np.array_equal(a.masks, b.masks)
    assert json.loads((out / "scene.json").read_text())["derived_masks"]["init_dir"] is None


def test_prepare_derives_the_masks_of_a_capture_without_them(capture, tmp_path, capsys):
    """No second pass: ``gcgs prepare --no-masks`` (the capture as if it had none) writes a
    scene with derived masks, marked as such, that match the object; ``--masks none`` keeps
    none; ``--masks capture`` on a capture without masks is one line naming it."""
    src = capture["root"] / "src"
    prepare = ["prepare", "--src", src, "--views", *VIEWS, "--width", W, "--params", PARAMS]
    rc, err = _gcgs(capsys, *prepare, "--out", tmp_path / "derived", "--no-masks")
    assert rc == 0, err
    scene = dtu.load_scene(tmp_path / "derived", view_ids=None)
    meta = json.loads((tmp_path / "derived" / "scene.json").read_text())
    assert meta["masks"] == "derived" and meta["derived_masks"]["scene"] == str(src)
    ious = [float((m & t).sum() / (m | t).sum()) for m, t in zip(scene.masks > 0.5, capture["views"].truth)]
    assert min(ious) >= MIN_IOU, ious
    assert _gcgs(capsys, *prepare, "--out", tmp_path / "none", "--no-masks", "--masks", "none")[0] == 0
    assert dtu.load_scene(tmp_path / "none", view_ids=None).masks is None
    bare = tmp_path / "bare"
    shutil.copytree(tmp_path / "none", bare)
    (bare / "scene.json").unlink()
    rc, err = _gcgs(capsys, "prepare", "--src", bare, "--out", tmp_path / "refused", "--masks", "capture",
                    "--params", PARAMS)
    lines = _lines(err)
    assert rc != 0 and len(lines) == 1 and "has no masks" in lines[0] and str(bare) in lines[0], err
    assert not (tmp_path / "refused").exists()
