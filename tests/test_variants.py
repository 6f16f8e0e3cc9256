"""Ablation variants: a variant's partial sections merge over the main params, are
validated like params values, and bad definitions fail with a message naming them."""
import pytest

from pipeline.config import AblationConfig, ConfigError, LossConfig, OptimizeConfig, merged_section, section
from pipeline.evaluation.variants import variant_configs

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
