"""One source for each default (issue 60): conf/ gives every default value and the config
dataclasses none, so the two cannot disagree. ``SomeConfig.default(**changes)`` builds a
config from conf/'s default composition (what ``gcgs params --write`` composes)."""
from __future__ import annotations

import dataclasses
import importlib
import pkgutil

import pytest

import pipeline.config
from pipeline.config.ablation import AblationConfig, SweepConfig, VariantConfig
from pipeline.config.init import InitConfig, MVSConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import CropConfig, DensifyConfig, OptimizeConfig
from pipeline.config.params import CONF_DIR, PARAMS_PATH, FromConf, conf_defaults, load_params, section
from pipeline.config.scenes import SceneEntry
from pipeline.errors import ConfigError

# The only config fields with defaults, and why: not settings that conf/ gives a value for.
EXCEPTIONS = {
    VariantConfig: {"init", "optimize", "loss", "mesh"},  # a variant's changes: a key left out changes nothing
    SceneEntry: {"gt"},  # an entry of `scenes`: no ground truth unless given
}


def config_classes() -> list[type]:
    """Every dataclass defined in a module of pipeline.config."""
    found = []
    for info in pkgutil.iter_modules(pipeline.config.__path__):
        module = importlib.import_module(f"pipeline.config.{info.name}")
        found += [obj for obj in vars(module).values()
                  if isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__module__ == module.__name__]
    return sorted(found, key=lambda c: c.__name__)


CLASSES = config_classes()
SECTIONS = [c for c in CLASSES if c not in EXCEPTIONS]


def defaulted(cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)
            if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING}


def test_the_classes_are_found():
    assert {OptimizeConfig, DensifyConfig, MeshConfig, InitConfig, AblationConfig, SweepConfig, VariantConfig} <= set(CLASSES)
    assert len(SECTIONS) >= 18


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_no_config_field_has_a_default(cls):
    """conf/ is the one source of each default: a default in a dataclass would be a second
    one, free to disagree (as lambda_gcf 2.0 against conf/'s 0.0 did)."""
    assert defaulted(cls) == EXCEPTIONS.get(cls, set()), (
        f"{cls.__name__}: fields with a default in the dataclass; give the value in conf/ instead")


@pytest.mark.parametrize("cls", SECTIONS, ids=lambda c: c.__name__)
def test_conf_gives_every_field_and_no_other_key(cls):
    assert issubclass(cls, FromConf) and cls.SECTION, f"{cls.__name__}: a config class needs FromConf and its SECTION"
    given = conf_defaults(cls.SECTION)
    assert isinstance(given, dict), f"conf/ {cls.SECTION} is not a section"
    fields = [f.name for f in dataclasses.fields(cls)]
    assert not sorted(set(fields) - set(given)), f"conf/ {cls.SECTION} lacks key(s) of {cls.__name__}"
    assert not sorted(set(given) - set(fields)), f"conf/ {cls.SECTION} has key(s) {cls.__name__} does not know"
    for name, value in vars(cls.default()).items():  # a nested section's class reads its own part of conf/
        if dataclasses.is_dataclass(value):
            assert type(value).SECTION == f"{cls.SECTION}.{name}"


@pytest.mark.parametrize("cls", [c for c in SECTIONS if "." not in c.SECTION], ids=lambda c: c.__name__)
def test_the_default_is_the_committed_params_section(cls):
    """params.yaml is conf/'s default composition (tests/test_params.py), so a default config
    is the one the stages read."""
    assert cls.default() == section(cls, cls.SECTION, load_params(PARAMS_PATH))


def test_default_applies_changes_like_a_params_value():
    cfg = OptimizeConfig.default(iterations=7, densify={"every": 3}, crop=CropConfig.default(fraction=0.5))
    params = load_params(PARAMS_PATH)["optimize"]
    assert (cfg.iterations, cfg.densify.every, cfg.crop.fraction) == (7, 3, 0.5)
    assert cfg.densify.max_surfels == params["densify"]["max_surfels"]  # a mapping merges key by key
    assert cfg.crop.full_every == params["crop"]["full_every"]
    assert cfg.lr.means == params["lr"]["means"] and cfg.downscale == params["downscale"]
    assert OptimizeConfig.default(downscale=[[0.0, 1]]).downscale == [[0.0, 1]]  # a list replaces
    assert InitConfig.default(mvs=MVSConfig.default(window=5)).mvs.window == 5
    assert AblationConfig.default(run=[], variants={}, speed_accuracy={"cells": []}).variants == {}
    with pytest.raises(ConfigError, match=r"^optimize\.densify\.every must be >= 1, got 0$"):
        OptimizeConfig.default(densify={"every": 0})
    with pytest.raises(ConfigError, match=r"^optimize\.iterations must be an integer, got 1\.5$"):
        OptimizeConfig.default(iterations=1.5)
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['everyy'\] in config section optimize\.densify"):
        OptimizeConfig.default(densify={"everyy": 3})
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['voxel'\] in config section mesh"):
        MeshConfig.default(voxel=0.01)


def test_each_default_is_a_fresh_config():
    first = OptimizeConfig.default()
    first.densify.every = 999
    first.downscale.append([0.9, 1])
    assert OptimizeConfig.default() == section(OptimizeConfig, "optimize", load_params(PARAMS_PATH))


def test_a_params_section_lacking_a_key_is_named():
    """No dataclass default fills in: a params file gives every key (it is composed from conf/)."""
    params = load_params(PARAMS_PATH)
    mesh = {k: v for k, v in params["mesh"].items() if k != "voxel_norm"}
    with pytest.raises(ConfigError, match=r"^missing key\(s\) \['voxel_norm'\] in config section mesh "):
        section(MeshConfig, "mesh", {"mesh": mesh})
    with pytest.raises(ConfigError, match=r"^missing key\(s\) \['fraction', 'full_every'\] in config section optimize\.crop"):
        section(OptimizeConfig, "optimize", {"optimize": {**params["optimize"], "crop": None}})


def test_default_inside_a_hydra_app():
    """The sweep is a Hydra app: a default built inside one composes beside it."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from pipeline.config import params as params_module

    params_module._composed_defaults.cache_clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        assert MeshConfig.default() == section(MeshConfig, "mesh", load_params(PARAMS_PATH))
        assert compose(config_name="config").mesh.voxel_norm == MeshConfig.default().voxel_norm  # its state is back
    assert not GlobalHydra.instance().is_initialized()
