"""params.yaml must be the Hydra composition of conf/ (DVC reads params.yaml only)."""
import yaml

from pipeline import config
from pipeline.config import compose_params, dump_params


def test_params_yaml_is_composed_from_conf():
    composed = dump_params(compose_params())
    current = config.PARAMS_PATH.read_text()
    assert yaml.safe_load(current) == yaml.safe_load(composed), "params.yaml is stale: run `gcgs params --write`"
    assert current == composed


def test_every_section_parses_into_its_dataclass():
    params = config.load_params()
    untyped = set(params) - set(config.SECTIONS) - {"scenes"}
    assert not untyped, f"params sections without a typed config in config.SECTIONS: {untyped}"
    for key, cls in config.SECTIONS.items():
        config.section(cls, key, params)
    for name, entry in params["scenes"].items():
        config.from_dict(config.SceneEntry, entry, where=f"scenes.{name}")


def test_unknown_key_is_rejected():
    import pytest

    with pytest.raises(ValueError, match=r"unknown key\(s\) \['widht'\] in config section data"):
        config.from_dict(config.DataConfig, {"widht": 3}, where="data")


def test_hydra_override_changes_composition():
    assert compose_params(["data.width=400"])["data"]["width"] == 400


def test_section_applies_overrides_before_validation():
    import pytest

    from pipeline.errors import ConfigError

    params = config.load_params()
    before = yaml.safe_dump(params)
    cfg = config.section(config.InitConfig, "init", params, {"backend": "random", "mast3r.model": "m.onnx",
                                                             "seed": None})
    assert (cfg.backend, cfg.mast3r.model, cfg.seed) == ("random", "m.onnx", params["init"]["seed"])
    assert cfg.mvs == config.MVSConfig(**params["init"]["mvs"])  # the rest comes from params
    assert yaml.safe_dump(params) == before  # params are not modified
    with pytest.raises(ConfigError, match="init.backend must be one of mvs, sfm, mast3r, random, got 'colmap'"):
        config.section(config.InitConfig, "init", params, {"backend": "colmap"})
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['windw'\] in config section init.mvs"):
        config.section(config.InitConfig, "init", params, {"mvs.windw": 5})
    with pytest.raises(ConfigError, match="data.views must be distinct view ids"):
        config.section(config.DataConfig, "data", params, {"views": [1, 1]})
    with pytest.raises(ConfigError, match=r"loss.gcf_max_dissimilarity must be in \(0, 2\]"):
        config.section(config.LossConfig, "loss", params, {"gcf_max_dissimilarity": 0.0})


def test_one_list_of_init_backends():
    from pipeline.init import BACKEND_MODULES

    assert config.InitConfig.BACKENDS == tuple(BACKEND_MODULES)
