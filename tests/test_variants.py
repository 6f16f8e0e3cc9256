"""Ablation variants: a variant's partial sections merge over the main params, are
validated like params values, and bad definitions fail with a message naming them."""
import json
from pathlib import Path

import pytest

from pipeline.errors import InputError
from pipeline.config import AblationConfig, ConfigError, LossConfig, OptimizeConfig, merged_section, section
from pipeline.runs.variant import variant_configs

REPO = Path(__file__).resolve().parents[1]

BASE = {
    "optimize": {"iterations": 500, "densify": {"every": 100, "max_surfels": 1000}},
    "loss": {"lambda_gcf": 2.0, "lambda_nor": 0.25},
    "mesh": {"depth": "median"},
    "ablation": {"run": ["plain"], "variants": {"plain": {"init": "sfm", "loss": {"lambda_gcf": 0.0, "lambda_nor": 0.0},
                                                          "optimize": {"densify": {"every": 50}}}}},
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
        AblationConfig(run=["nope"], variants={})
    with pytest.raises(ConfigError, match="init must be one of"):
        AblationConfig(run=[], variants={"x": {"init": "colmap"}})
    with pytest.raises(ConfigError, match="ablation.variants.x"):
        AblationConfig(run=[], variants={"x": {"lr": 1}})
    with pytest.raises(ConfigError, match="'missing' is not defined"):
        variant_configs(BASE, "missing")


def _write(path, data):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def test_table2_rows_components_and_mean(tmp_path):
    from pipeline.reports.table2 import FULL, LIMIT, MVS_TSDF, build_table2, csv_text, markdown, read_published_ablation

    scenes = ["a", "b"]
    def chamfer(overall, acc, used):
        return {"overall_mm": overall, "accuracy_mm": acc, "completeness_mm": 2 * overall - acc,
                "counts": {"completeness_used": used, "gt_above_plane": 200}}

    for s, (lim, mvs, plain, full) in {"a": (0.5, 3.0, 5.0, 1.0), "b": (1.5, 2.0, 7.0, 2.0)}.items():
        _write(tmp_path / "limit" / f"{s}.json", {"chamfer": chamfer(lim, 0.0, 120)})
        _write(tmp_path / "baseline" / f"{s}.json", {"evaluate": {"metrics": chamfer(mvs, 0.5, 50)}})
        _write(tmp_path / "variants" / "plain" / f"{s}.json", {"chamfer": chamfer(plain, 2.0, 100)})
        _write(tmp_path / "metrics" / f"{s}.json", {"chamfer": chamfer(full, 0.25, 150)})
    ablation = AblationConfig(**BASE["ablation"])
    rows = build_table2(BASE, scenes, ablation.run, ablation.variants, tmp_path / "metrics", tmp_path / "variants",
                        tmp_path / "baseline", tmp_path / "limit")
    assert [r["row"] for r in rows] == [LIMIT, MVS_TSDF, "plain", FULL]
    assert [r["mean"] for r in rows] == [1.0, 2.5, 6.0, 1.5]
    assert rows[0]["accuracy"] == {"a": 0.0, "b": 0.0, "mean": 0.0}
    assert rows[3]["completeness"] == {"a": 1.75, "b": 3.75, "mean": 2.75}
    assert (rows[0]["dense_init"], rows[1]["gcf"]) == (None, None)
    assert (rows[2]["dense_init"], rows[2]["gcf"], rows[2]["nor"]) == (False, False, False)
    assert (rows[3]["dense_init"], rows[3]["gcf"], rows[3]["nor"]) == (True, True, True)
    assert [r["covered"] for r in rows][1:] == [{"a": 0.25, "b": 0.25}, {"a": 0.5, "b": 0.5}, {"a": 0.75, "b": 0.75}]
    assert csv_text(rows, scenes).splitlines()[3] == ("plain,0,0,0,5.0000,7.0000,6.0000,0.5000,0.5000,"
                                                     "2.0000,2.0000,2.0000,8.0000,12.0000,10.0000")
    md = markdown(rows, scenes, "abc")
    # The limit is the yardstick, not a row to win: the best method row is in bold.
    assert "| full method | yes | yes | yes | 1.000 | 2.000 | **1.500** |" in md
    assert f"| {LIMIT} | — | — | — | 0.500 | 1.500 | 1.000 |" in md
    assert "| full method | 0.250 / 1.750 | 0.250 / 3.750 | 0.250 / 2.750 |" in md
    assert f"| {MVS_TSDF} | 0.25 | 0.25 |" in md
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


def test_table2_names_a_missing_or_bad_report(tmp_path):
    from pipeline.reports.table2 import build_table2

    ablation = AblationConfig(**BASE["ablation"])
    args = (BASE, ["a"], ablation.run, ablation.variants, tmp_path / "m", tmp_path / "v", tmp_path / "b",
            tmp_path / "l")
    _write(tmp_path / "l" / "a.json", {"chamfer": {"overall_mm": 1.0, "accuracy_mm": 0.0, "completeness_mm": 2.0,
                                                   "counts": {"completeness_used": 1, "gt_above_plane": 2}}})
    with pytest.raises(InputError, match=r"b/a\.json: no report \(file not found; run `dvc repro` first\)"):
        build_table2(*args)
    _write(tmp_path / "b" / "a.json", {"evaluate": {"metrics": {"overall_mm": float("nan")}}})
    with pytest.raises(InputError, match=r"b/a\.json: evaluate\.metrics: `accuracy_mm` must be a number"):
        build_table2(*args)
    _write(tmp_path / "b" / "a.json", {"evaluate": {"metrics": {"overall_mm": 1.0, "accuracy_mm": 0.5,
                                                               "completeness_mm": 1.5}}})  # no counts
    with pytest.raises(InputError, match=r"b/a\.json: evaluate\.metrics: `completeness_used` must be a finite number"):
        build_table2(*args)


@pytest.mark.parametrize("preset, cell", [("quick", "sa_it150"), ("balanced", "sa_it1000"), ("paper", "sa_paper")])
def test_presets_are_the_sweep_cells_they_cite(preset, cell):
    """conf/optimize/{quick,balanced,paper}.yaml must stay the settings measured as their sweep cell."""
    import dataclasses

    from pipeline.config import OptimizeConfig, compose_params, load_params

    preset_cfg = dataclasses.asdict(section(OptimizeConfig, "optimize", compose_params([f"optimize={preset}"])))
    cell_cfg = dataclasses.asdict(variant_configs(load_params(), cell)[1])
    assert preset_cfg.pop("preset") == preset
    cell_cfg.pop("preset")
    assert preset_cfg == cell_cfg
