"""Ablation variants: a variant's partial sections merge over the main params, are
validated like params values, and bad definitions fail with a message naming them."""
import json
from dataclasses import asdict
from pathlib import Path

import pytest

from pipeline.config.ablation import AblationConfig
from pipeline.config.loss import LossConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import merged_section, section
from pipeline.config.variants import variant_configs
from pipeline.errors import ConfigError, InputError

REPO = Path(__file__).resolve().parents[1]

NO_SWEEP = {"scenes": [], "cells": []}  # ablation.speed_accuracy without cells

# Complete main sections (a params file gives every key): conf/'s defaults with the values these
# tests set and, where conf/ has others, those they were written with: L_mv, L_mvgeo and the
# adaptive NCC off, L_mv's points among every surface pixel (the dataclass defaults before issue 60).
BASE = {
    "optimize": asdict(OptimizeConfig.default(iterations=500, lr={"means_final": 1.6e-4},
                                              densify={"every": 100, "max_surfels": 1000}, photo_reset={"enabled": True},
                                              mv_textured_points=False)),
    "loss": asdict(LossConfig.default(lambda_gcf=2.0, lambda_nor=0.25, lambda_smooth=0.1, mv_max_cost=0.5,
                                      lambda_mv=0.0, lambda_mvgeo=0.0, mv_ncc_gamma=0.0)),
    "mesh": asdict(MeshConfig.default(depth="median", init_depth_rel_tol=0.002)),
    "ablation": {"run": ["plain"], "speed_accuracy": NO_SWEEP, "variants": {"plain": {"init": "sfm", "loss": {"lambda_gcf": 0.0, "lambda_nor": 0.0,
                                                                                             "lambda_smooth": 0.0, "mv_max_cost": 2.0},
                                                          "optimize": {"densify": {"every": 50}, "lr": {"means_final": 1.6e-6},
                                                                       "photo_reset": {"enabled": False}},
                                                          "mesh": {"init_depth_rel_tol": 0.0}}}},
}


def test_variant_merges_over_main_sections():
    v, opt, loss, mesh = variant_configs(BASE, "plain")
    assert v.init == "sfm"
    assert (loss.lambda_gcf, loss.lambda_nor) == (0.0, 0.0)
    assert opt.iterations == 500  # untouched keys keep the main value
    assert opt.densify.every == 50 and opt.densify.max_surfels == 1000  # nested sections merge key by key
    assert mesh.depth == "median"
    main_loss = section(LossConfig, "loss", BASE)
    assert main_loss.lambda_gcf == 2.0  # the main params are not modified


def test_variant_change_is_validated_like_params():
    with pytest.raises(ConfigError, match="unknown key"):
        merged_section(OptimizeConfig, "optimize", BASE, {"iteratons": 3})
    with pytest.raises(ConfigError, match="optimize"):
        merged_section(OptimizeConfig, "optimize", BASE, {"iterations": 0})


def test_bad_ablation_definitions_are_named():
    with pytest.raises(ConfigError, match=r"undefined variant\(s\) \['nope'\]"):
        AblationConfig.default(run=["nope"], variants={}, speed_accuracy=NO_SWEEP)
    with pytest.raises(ConfigError, match="init must be one of"):
        AblationConfig.default(run=[], variants={"x": {"init": "colmap"}}, speed_accuracy=NO_SWEEP)
    with pytest.raises(ConfigError, match="ablation.variants.x"):
        AblationConfig.default(run=[], variants={"x": {"lr": 1}}, speed_accuracy=NO_SWEEP)
    with pytest.raises(ConfigError, match=r"ablation.variants.x_seed1: a seed replicate must be 'x' with only "
                                          r"optimize.seed: 1 added"):
        AblationConfig.default(run=[], variants={"x": {"init": "sfm"}, "x_seed1": {"optimize": {"seed": 1}}},
                               speed_accuracy=NO_SWEEP)
    with pytest.raises(ConfigError, match="a seed replicate of 'y', which is not defined"):
        AblationConfig.default(run=[], variants={"y_seed2": {"optimize": {"seed": 2}}}, speed_accuracy=NO_SWEEP)
    AblationConfig.default(run=[], variants={"x": {"init": "sfm"}, "x_seed1": {"init": "sfm", "optimize": {"seed": 1}},
                                             "full_seed3": {"optimize": {"seed": 3}}}, speed_accuracy=NO_SWEEP)
    with pytest.raises(ConfigError, match="'missing' is not defined"):
        variant_configs(BASE, "missing")


def _write(path, data):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def test_table2_rows_components_and_mean(tmp_path):
    from pipeline.reports.table2 import (EXACT_DEPTH, FULL, LIMIT, MVS_TSDF, build_table2, csv_text, markdown,
                                         read_published_ablation)

    scenes = ["a", "b"]
    def chamfer(overall, acc, used):
        return {"overall_mm": overall, "accuracy_mm": acc, "completeness_mm": 2 * overall - acc,
                "counts": {"completeness_used": used, "gt_above_plane": 200}}

    for s, (lim, exact, mvs, plain, full) in {"a": (0.5, 0.6, 3.0, 5.0, 1.0), "b": (1.5, 1.0, 2.0, 7.0, 2.0)}.items():
        _write(tmp_path / "limit" / f"{s}.json", {"chamfer": chamfer(lim, 0.0, 120),
                                                   "exact_depth": chamfer(exact, 0.1, 110)})
        _write(tmp_path / "baseline" / f"{s}.json", {"evaluate": {"metrics": chamfer(mvs, 0.5, 50)}})
        _write(tmp_path / "variants" / "plain" / f"{s}.json", {"chamfer": chamfer(plain, 2.0, 100)})
        _write(tmp_path / "metrics" / f"{s}.json", {"chamfer": {**chamfer(full, 0.25, 150), "accuracy_by_views_seen": {
            "2+": {"fraction": 0.9, "accuracy_mm": 0.2 * full}, "1": {"fraction": 0.1, "accuracy_mm": None}},
            "completeness_by_views_seen": {"2+": {"fraction": 0.5, "completeness_mm": 0.5 * full},
                                           "1": {"fraction": 0.1, "completeness_mm": full},
                                           "0": {"fraction": 0.4, "completeness_mm": 4 * full}},
            "accuracy_by_distance": {"0-0.5": {"fraction": 0.9, "share_mm": 0.1 * full},
                                     "0.5-1": {"fraction": 0.05, "share_mm": 0.05 * full},
                                     "1-2": {"fraction": 0.04, "share_mm": 0.06 * full},
                                     "2-20": {"fraction": 0.01, "share_mm": 0.04 * full}}}})
    ablation = AblationConfig(**BASE["ablation"])
    rows = build_table2(BASE, scenes, ablation.run, ablation.variants, tmp_path / "metrics", tmp_path / "variants",
                        tmp_path / "baseline", tmp_path / "limit")
    assert [r["row"] for r in rows] == [LIMIT, EXACT_DEPTH, MVS_TSDF, "plain", FULL]
    assert [r["mean"] for r in rows] == pytest.approx([1.0, 0.8, 2.5, 6.0, 1.5])
    assert rows[0]["accuracy"] == {"a": 0.0, "b": 0.0, "mean": 0.0}
    assert rows[1]["accuracy"] == pytest.approx({"a": 0.1, "b": 0.1, "mean": 0.1})
    assert rows[4]["completeness"] == {"a": 1.75, "b": 3.75, "mean": 2.75}
    assert (rows[0]["dense_init"], rows[1]["mv"], rows[2]["gcf"]) == (None, None, None)
    assert (rows[3]["dense_init"], rows[3]["gcf"], rows[3]["nor"]) == (False, False, False)
    assert (rows[4]["dense_init"], rows[4]["gcf"], rows[4]["nor"]) == (True, True, True)
    assert (rows[3]["photo_reset"], rows[4]["photo_reset"]) == (False, True)
    assert (rows[3]["init_depth_mesh"], rows[4]["init_depth_mesh"]) == (False, True)
    assert (rows[3]["ncc_support"], rows[4]["ncc_support"]) == (False, False)
    assert (rows[3]["smooth"], rows[4]["smooth"]) == (False, True)
    assert (rows[3]["mv_textured"], rows[4]["mv_textured"]) == (False, False)
    assert (rows[3]["mv_ceiling"], rows[4]["mv_ceiling"]) == (False, True)
    assert (rows[3]["means_lr_held"], rows[4]["means_lr_held"]) == (False, True)
    assert [r["covered"] for r in rows][2:] == [{"a": 0.25, "b": 0.25}, {"a": 0.5, "b": 0.5}, {"a": 0.75, "b": 0.75}]
    assert csv_text(rows, scenes).splitlines()[4] == ("plain,0,0,0,0,0,0,0,0,0,0,0,5.0000,7.0000,6.0000,0.5000,0.5000,"
                                                     "2.0000,2.0000,2.0000,8.0000,12.0000,10.0000,1,"
                                                     "0.0000,0.0000,0.0000")
    md = markdown(rows, scenes, "abc")
    # The yardsticks are not rows to win, even the lower exact-depth one: the best method row is in bold.
    assert "| full method | yes | yes | yes | no | yes | no | no | yes | yes | yes | yes | 1.000 | 2.000 | **1.500** | 1 |" in md
    assert f"| {LIMIT} | — | — | — | — | — | — | — | — | — | — | — | 0.500 | 1.500 | 1.000 | 1 |" in md
    assert f"| {EXACT_DEPTH} | — | — | — | — | — | — | — | — | — | — | — | 0.600 | 1.000 | 0.800 | 1 |" in md
    assert "| full method | 0.250 / 1.750 | 0.250 / 3.750 | 0.250 / 2.750 |" in md
    assert f"| {MVS_TSDF} | 0.25 | 0.25 |" in md
    seen2 = md.split("**Accuracy on surface seen by >= 2 input views**")[1].split("**How much")[0]
    assert "| full method | 0.200 (90%) | 0.400 (90%) | 0.300 |" in seen2 and "| plain |" not in seen2
    by_gt = md.split("**Completeness by how many input views see the GT surface**")[1].split("**How much")[0]
    assert "| full method | 0.50 / 1.00 / 4.00 | 1.00 / 2.00 / 8.00 | 0.75 / 1.50 / 6.00 |" in by_gt
    assert "| plain |" not in by_gt
    far = md.split("**Accuracy beyond 1 mm**")[1].split("**Completeness by")[0]
    assert "| full method | 0.100 (5.0%) | 0.200 (5.0%) | 0.150 |" in far and "| plain |" not in far
    assert "published" not in md  # no published figure unless given, and then apart:
    published = read_published_ablation(REPO / "data" / "published" / "gcgs_table2_ablation.csv")
    assert published[-1] == {"dense_init": True, "gcf": True, "nor": True, "mean_mm": 0.95}
    md = markdown(rows, scenes, "abc", published)
    tail = md.split("## The paper's Table II (published, not measured here)")[1]
    assert "| yes | yes | yes | 0.95 |" in tail and "full method" not in tail


def test_published_table2_bad_rows_are_named(tmp_path):
    from pipeline.reports.table2 import read_published_ablation

    bad = tmp_path / "t2.csv"
    bad.write_text("# comment\nmast3r_init,l_gcf,l_nor,mean_cd_mm\nmaybe,no,no,2.36\n")
    with pytest.raises(InputError, match="t2.csv: row 1: need mast3r_init"):
        read_published_ablation(bad)


def test_table2_seed_replicates_give_mean_and_spread(tmp_path):
    from pipeline.reports.table2 import FULL, build_table2, markdown, seed_groups

    assert seed_groups(["a", "full_seed1", "a_seed1", "b_seed2"]) == {
        "a": ["a", "a_seed1"], "full": ["full_seed1"], "b": ["b_seed2"]}
    params = {**BASE, "ablation": {"run": ["plain", "plain_seed1", "full_seed1", "full_seed2"], "speed_accuracy": NO_SWEEP, "variants": {
        **BASE["ablation"]["variants"], "plain_seed1": {"init": "sfm", "loss": {"lambda_gcf": 0.0, "lambda_nor": 0.0,
                                                                                    "lambda_smooth": 0.0, "mv_max_cost": 2.0},
                                                           "optimize": {"densify": {"every": 50}, "lr": {"means_final": 1.6e-6}, "seed": 1,
                                                                        "photo_reset": {"enabled": False}},
                                                           "mesh": {"init_depth_rel_tol": 0.0}},
        "full_seed1": {"optimize": {"seed": 1}}, "full_seed2": {"optimize": {"seed": 2}}}}}
    scenes = ["a", "b"]

    def chamfer(overall):
        return {"overall_mm": overall, "accuracy_mm": overall / 2, "completeness_mm": 3 * overall / 2,
                "counts": {"completeness_used": 1, "gt_above_plane": 2}}

    figures = {"metrics": (1.0, 2.0), "variants/full_seed1": (1.2, 2.0), "variants/full_seed2": (0.8, 2.6),
               "variants/plain": (5.0, 7.0), "variants/plain_seed1": (6.0, 7.0)}
    for where, per_scene in figures.items():
        for s, overall in zip(scenes, per_scene):
            _write(tmp_path / where / f"{s}.json", {"chamfer": chamfer(overall)})
    for s in scenes:
        _write(tmp_path / "limit" / f"{s}.json", {"chamfer": chamfer(0.5), "exact_depth": chamfer(0.7)})
        _write(tmp_path / "baseline" / f"{s}.json", {"evaluate": {"metrics": chamfer(3.0)}})
    ablation = AblationConfig(**params["ablation"])
    rows = build_table2(params, scenes, ablation.run, ablation.variants, tmp_path / "metrics", tmp_path / "variants",
                        tmp_path / "baseline", tmp_path / "limit")
    full, plain = rows[-1], rows[3]
    assert [r["row"] for r in rows][3:] == ["plain", FULL] and (full["seeds"], plain["seeds"]) == (3, 2)
    assert full["a"] == pytest.approx(1.0) and full["b"] == pytest.approx(2.2)
    # per-seed means over the scenes: 1.5, 1.6, 1.7 -> mean 1.6, half range 0.1
    assert full["mean"] == pytest.approx(1.6) and full["spread"]["mean"] == pytest.approx(0.1)
    assert full["spread"]["a"] == pytest.approx(0.2) and full["spread"]["b"] == pytest.approx(0.3)
    assert plain["spread"] == pytest.approx({"a": 0.5, "b": 0.0, "mean": 0.25})
    assert full["accuracy"]["a"] == pytest.approx(0.5) and (plain["dense_init"], plain["gcf"]) == (False, False)
    assert "| full method | yes | yes | yes | no | yes | no | no | yes | yes | yes | yes | 1.000 ± 0.200 | 2.200 ± 0.300 | **1.600** ± 0.100 | 3 |" in (
        markdown(rows, scenes, "abc"))


def test_table2_names_a_missing_or_bad_report(tmp_path):
    from pipeline.reports.table2 import build_table2

    ablation = AblationConfig(**BASE["ablation"])
    args = (BASE, ["a"], ablation.run, ablation.variants, tmp_path / "m", tmp_path / "v", tmp_path / "b",
            tmp_path / "l")
    limit = {"overall_mm": 1.0, "accuracy_mm": 0.0, "completeness_mm": 2.0,
             "counts": {"completeness_used": 1, "gt_above_plane": 2}}
    _write(tmp_path / "l" / "a.json", {"chamfer": limit})  # a limit report from before the exact-depth row
    with pytest.raises(InputError, match=r"l/a\.json: missing `exact_depth`"):
        build_table2(*args)
    _write(tmp_path / "l" / "a.json", {"chamfer": limit, "exact_depth": limit})
    with pytest.raises(InputError, match=r"b/a\.json: no report \(file not found; run `dvc repro` first\)"):
        build_table2(*args)
    _write(tmp_path / "b" / "a.json", {"evaluate": {"metrics": {"overall_mm": float("nan")}}})
    with pytest.raises(InputError, match=r"b/a\.json: evaluate\.metrics: `accuracy_mm` must be a number"):
        build_table2(*args)
    _write(tmp_path / "b" / "a.json", {"evaluate": {"metrics": {"overall_mm": 1.0, "accuracy_mm": 0.5,
                                                               "completeness_mm": 1.5}}})  # no counts
    with pytest.raises(InputError, match=r"b/a\.json: evaluate\.metrics: `completeness_used` must be a finite number"):
        build_table2(*args)


@pytest.mark.parametrize(
    "preset, cell", [("quick", "sa_it150"), ("balanced", "sa_it1000"), ("long", "sa_it2000")]
)
def test_presets_are_the_sweep_cells_they_cite(preset, cell):
    """conf/optimize/{quick,balanced,long}.yaml must stay the settings measured as their sweep cell.
    (`paper` left the sweep's `sa_paper` on 2026-12-05: docs/presets.md.)"""
    import dataclasses

    from pipeline.config.optimize import OptimizeConfig
    from pipeline.config.params import compose_params, load_params

    preset_cfg = dataclasses.asdict(section(OptimizeConfig, "optimize", compose_params([f"optimize={preset}"])))
    cell_cfg = dataclasses.asdict(variant_configs(load_params(), cell)[1])
    assert preset_cfg.pop("preset") == preset
    cell_cfg.pop("preset")
    assert preset_cfg == cell_cfg


def test_a_cell_without_its_ground_truth_fails_before_training(tmp_path, monkeypatch):
    from pipeline.errors import MissingInputError
    from pipeline.runs import variant as run

    def must_not_train(*args, **kwargs):
        raise AssertionError("trained although the ground truth is missing")

    monkeypatch.setattr(run, "train_variant", must_not_train)
    with pytest.raises(MissingInputError, match="ground-truth folder not found.*nothing was trained"):
        run.run_variant("synth_thin", "full", {}, tmp_path / "scene", tmp_path / "src", tmp_path / "no_gt", {},
                        tmp_path / "priors", tmp_path / "out", tmp_path / "r.json", [23, 24, 33])
    assert not (tmp_path / "out").exists()
