"""The settings an ablation variant (``ablation.variants``, :mod:`pipeline.config.ablation`)
runs with: its own partial sections merged over the main ``optimize``, ``loss`` and
``mesh``, and the folders its init source names. Apart from ``config.ablation`` so that the
stages reading only the variants' definitions (priors) do not depend on every section's code."""
from __future__ import annotations

from pathlib import Path

from pipeline.config.ablation import AblationConfig, VariantConfig
from pipeline.config.loss import LossConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import merged_section, section
from pipeline.errors import ConfigError


def init_sources(init_dir: str | Path, baseline_dir: str | Path) -> dict[str, Path]:
    """Each init source a variant may name (:attr:`VariantConfig.INITS`) -> the folder holding
    its ``points.ply``: the init stage's output (``mvs``) or the baseline stage's clouds."""
    return {"mvs": Path(init_dir), "sfm": Path(baseline_dir) / "sfm", "random": Path(baseline_dir) / "random"}


def training_report(report: str | Path) -> Path:
    """Where a cell's training time goes: beside its metrics ``report``, suffix ``.train.json``."""
    return Path(report).with_suffix(".train.json")


def variant_entry(params: dict, variant: str) -> VariantConfig:
    """The settings ``variant`` changes (``ablation.variants.VARIANT``); an error naming the
    defined ones when it is not defined."""
    ablation = section(AblationConfig, "ablation", params)
    if variant not in ablation.variants:
        raise ConfigError(f"ablation variant {variant!r} is not defined (defined: {sorted(ablation.variants)})")
    return ablation.variants[variant]


def variant_training(params: dict, variant: str) -> tuple[VariantConfig, OptimizeConfig, LossConfig]:
    """The variant's own settings and the optimize and loss sections it trains with (not
    ``mesh``: its training must not depend on the meshing settings)."""
    v = variant_entry(params, variant)
    return (v, merged_section(OptimizeConfig, "optimize", params, v.optimize, variant),
            merged_section(LossConfig, "loss", params, v.loss, variant))


def variant_configs(params: dict, variant: str) -> tuple[VariantConfig, OptimizeConfig, LossConfig, MeshConfig]:
    """The variant's own settings and the optimize, loss and mesh sections it runs with."""
    v, opt, loss = variant_training(params, variant)
    return v, opt, loss, merged_section(MeshConfig, "mesh", params, v.mesh, variant)
