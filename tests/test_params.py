"""params.yaml must be the Hydra composition of conf/ (DVC reads params.yaml only)."""
import yaml

from pipeline.config.ablation import AblationConfig
from pipeline.config.data import DataConfig
from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.init import InitConfig, MVSConfig
from pipeline.config.loss import LossConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import PARAMS_PATH, compose_params, dump_params, from_dict, load_params, section
from pipeline.config.priors import PriorsConfig
from pipeline.config.scenes import SceneEntry
from pipeline.config.synth import SynthConfig

# Top-level params.yaml sections and their typed configs (``scenes`` maps names to entries).
SECTIONS: dict[str, type] = {
    "data": DataConfig,
    "synth": SynthConfig,
    "evaluate": EvaluateConfig,
    "loss": LossConfig,
    "init": InitConfig,
    "priors": PriorsConfig,
    "mesh": MeshConfig,
    "optimize": OptimizeConfig,
    "ablation": AblationConfig,
}


def test_params_yaml_is_composed_from_conf():
    composed = dump_params(compose_params())
    current = PARAMS_PATH.read_text()
    assert yaml.safe_load(current) == yaml.safe_load(composed), "params.yaml is stale: run `gcgs params --write`"
    assert current == composed


def test_every_section_parses_into_its_dataclass():
    params = load_params()
    untyped = set(params) - set(SECTIONS) - {"scenes"}
    assert not untyped, f"params sections without a typed config in SECTIONS: {untyped}"
    for key, cls in SECTIONS.items():
        section(cls, key, params)
    for name, entry in params["scenes"].items():
        from_dict(SceneEntry, entry, where=f"scenes.{name}")


def test_unknown_key_is_rejected():
    import pytest

    with pytest.raises(ValueError, match=r"unknown key\(s\) \['widht'\] in config section data"):
        from_dict(DataConfig, {"widht": 3}, where="data")


def test_hydra_override_changes_composition():
    assert compose_params(["data.width=400"])["data"]["width"] == 400


def test_section_applies_overrides_before_validation():
    import pytest

    from pipeline.errors import ConfigError

    params = load_params()
    before = yaml.safe_dump(params)
    cfg = section(InitConfig, "init", params, {"backend": "random", "mast3r.model": "m.onnx",
                                                             "seed": None})
    assert (cfg.backend, cfg.mast3r.model, cfg.seed) == ("random", "m.onnx", params["init"]["seed"])
    assert cfg.mvs == MVSConfig(**params["init"]["mvs"])  # the rest comes from params
    assert yaml.safe_dump(params) == before  # params are not modified
    with pytest.raises(ConfigError, match="init.backend must be one of mvs, sfm, mast3r, random, got 'colmap'"):
        section(InitConfig, "init", params, {"backend": "colmap"})
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['windw'\] in config section init.mvs"):
        section(InitConfig, "init", params, {"mvs.windw": 5})
    with pytest.raises(ConfigError, match="data.views must be distinct view ids"):
        section(DataConfig, "data", params, {"views": [1, 1]})
    with pytest.raises(ConfigError, match=r"loss.gcf_max_dissimilarity must be in \(0, 2\]"):
        section(LossConfig, "loss", params, {"gcf_max_dissimilarity": 0.0})
    for bad in (-0.01, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="loss.mv_ncc_gamma must be a finite number >= 0"):
            section(LossConfig, "loss", params, {"mv_ncc_gamma": bad})
    for bad in (-0.01, float("nan")):
        with pytest.raises(ConfigError, match="loss.lambda_smooth, smooth_gamma and smooth_max_std must be finite and >= 0"):
            section(LossConfig, "loss", params, {"smooth_max_std": bad})
    with pytest.raises(ConfigError, match="loss.mv_best_sources must be an int >= 0"):
        section(LossConfig, "loss", params, {"mv_best_sources": -1})
    with pytest.raises(ConfigError, match="loss.mv_best_sources must be an integer, got 1.5"):  # from_dict's type check
        section(LossConfig, "loss", params, {"mv_best_sources": 1.5})
    for bad in (0.0, 2.5, float("nan")):
        with pytest.raises(ConfigError, match=r"loss.mv_max_cost must be in \(0, 2\]"):
            section(LossConfig, "loss", params, {"mv_max_cost": bad})


def test_one_list_of_init_backends():
    from pipeline.init.backends import BACKEND_MODULES

    assert InitConfig.BACKENDS == tuple(BACKEND_MODULES)


def test_config_package_imports_no_concept():
    """Each stage depends only on the config modules it imports (dvc.yaml deps): the
    package's __init__ must import none of them, or every stage would depend on all."""
    import ast

    init = PARAMS_PATH.parent / "src" / "pipeline" / "config" / "__init__.py"
    tree = ast.parse(init.read_text())
    assert not [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
