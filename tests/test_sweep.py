"""The sweep app (``python -m pipeline.sweep``, docs/sweeps.md): its launcher configs compose
(nothing is submitted) and a cell's params are the pipeline's params for one scene."""
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pipeline.config.params import CONF_DIR, compose_params
from pipeline.errors import ConfigError
from pipeline.sweep import SWEEP_CONFIG, cell_params


def _compose(overrides, hydra=True):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name=SWEEP_CONFIG, overrides=overrides, return_hydra_config=hydra)


def test_local_launcher_is_joblib():
    launcher = _compose(["hydra/launcher=local"]).hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"
    assert launcher.n_jobs == 2
    # The default launcher of the sweep app is the local one.
    assert _compose([]).hydra.launcher._target_ == launcher._target_


def test_slurm_launcher_is_submitit_with_overridable_resources():
    launcher = _compose(["hydra/launcher=slurm", "hydra.launcher.partition=cpu",
                         "hydra.launcher.timeout_min=240"]).hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert (launcher.partition, launcher.timeout_min) == ("cpu", 240)
    assert launcher.cpus_per_task >= 1 and launcher.mem_gb > 0 and launcher.gpus_per_node == 0
    assert launcher.array_parallelism >= 1


def test_cell_params_are_the_pipeline_params_of_one_scene():
    cfg = OmegaConf.to_container(_compose(["optimize=paper", "loss.lambda_gcf=0", "cell.scene=synth_thin"], hydra=False),
                                 resolve=True)
    assert cfg["cell"]["scene"] == "synth_thin"
    params = cell_params(cfg, "synth_thin")
    want = compose_params(["optimize=paper", "loss.lambda_gcf=0"])
    want["scenes"] = {"synth_thin": want["scenes"]["synth_thin"]}
    assert params == want
    assert params["optimize"]["preset"] == "paper" and params["loss"]["lambda_gcf"] == 0


def test_unknown_cell_scene_is_named():
    cfg = OmegaConf.to_container(_compose([], hydra=False), resolve=True)
    with pytest.raises(ConfigError, match=r"cell.scene='scan99' is not in `scenes`"):
        cell_params(cfg, "scan99")
