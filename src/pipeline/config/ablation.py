"""Table II's variants and the speed-accuracy sweep (conf/ablation)."""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import Any

from pipeline.config.loss import LossConfig
from pipeline.config.params import FromConf, from_dict, merged_section, nested_sections, section
from pipeline.errors import ConfigError


@dataclass
class VariantConfig:
    """One ablation variant (conf/ablation): where its init cloud comes from and the
    settings it changes, as partial sections merged over params ``optimize``, ``loss`` and
    ``mesh``. A set of changes, not a section with values of its own in conf/: its fields keep
    defaults that mean "no change" (a key a variant leaves out changes nothing; ``full: {}`` is
    the main pipeline), one of the two exceptions to "conf/ gives every default" with
    :class:`~pipeline.config.scenes.SceneEntry` (tests/test_config_defaults.py)."""

    INITS = ("mvs", "sfm", "random")

    init: str = "mvs"  # mvs: the init stage's dense cloud; sfm / random: the baseline stage's clouds
    optimize: dict = field(default_factory=dict)
    loss: dict = field(default_factory=dict)
    mesh: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.init not in self.INITS:
            raise ConfigError(f"ablation variant init must be one of {', '.join(self.INITS)}, got {self.init!r}")


@dataclass
class SweepConfig(FromConf):
    """The speed-accuracy sweep: each cell (a variant) on each scene (values:
    conf/ablation/default.yaml ``speed_accuracy``)."""

    SECTION = "ablation.speed_accuracy"

    scenes: list[str]
    cells: list[str]  # names of ``variants``


SEED_REPLICATE = re.compile(r"^(?P<row>.+)_seed(?P<seed>\d+)$")  # Table II's row ROW with training seed K


@dataclass
class AblationConfig(FromConf):
    """``ablation``: the variants that exist, the ones ``dvc repro`` runs (Table II) and the
    speed-accuracy sweep's cells (values: conf/ablation/default.yaml)."""

    SECTION = "ablation"

    run: list[str]  # names of ``variants``
    variants: dict  # name -> VariantConfig (a mapping as read from YAML becomes one)
    speed_accuracy: SweepConfig

    def __post_init__(self) -> None:
        self.variants = {name: v if isinstance(v, VariantConfig) else from_dict(VariantConfig, v,
                                                                                where=f"ablation.variants.{name}")
                         for name, v in (self.variants or {}).items()}
        nested_sections(self, "ablation", speed_accuracy=SweepConfig)
        for key, names in (("run", self.run), ("speed_accuracy.cells", self.speed_accuracy.cells)):
            missing = sorted(set(names) - set(self.variants))
            if missing:
                raise ConfigError(f"ablation.{key} names undefined variant(s) {missing}; defined: {sorted(self.variants)}")
        for name, v in self.variants.items():
            self._check_seed_replicate(name, v)

    def _check_seed_replicate(self, name: str, v: VariantConfig) -> None:
        """``X_seedK`` is Table II's row X trained with seed K (``full``: the main pipeline):
        it must be X with only ``optimize.seed: K`` added, or its figures would be averaged
        into a row they do not belong to."""
        m = SEED_REPLICATE.match(name)
        if m is None:
            return
        base = VariantConfig() if m["row"] == "full" else self.variants.get(m["row"])
        if base is None:
            raise ConfigError(f"ablation.variants.{name}: a seed replicate of {m['row']!r}, which is not defined")
        expect = dataclasses.replace(base, optimize={**base.optimize, "seed": int(m["seed"])})
        if v != expect:
            raise ConfigError(f"ablation.variants.{name}: a seed replicate must be {m['row']!r} with only "
                              f"optimize.seed: {m['seed']} added, i.e. {dataclasses.asdict(expect)}; got {dataclasses.asdict(v)}")


def losses_in_use(params: dict[str, Any]) -> list[LossConfig]:
    """The loss settings that train on a scene's priors: the main ``loss`` section and each
    variant of ``ablation.run`` merged over it. A prior is needed when any of them weights it."""
    ablation = section(AblationConfig, "ablation", params)
    return [section(LossConfig, "loss", params)] + [
        merged_section(LossConfig, "loss", params, ablation.variants[n].loss, n) for n in ablation.run]
