"""``gcgs params``: compose conf/ into params.yaml, or check that it is up to date."""
from __future__ import annotations

import argparse
from typing import Any

from pipeline.config.ablation import AblationConfig
from pipeline.config.data import DataConfig
from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.init import InitConfig
from pipeline.config.loss import LossConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import PARAMS_PATH, compose_params, dump_params, section, section_mapping
from pipeline.config.priors import PriorsConfig
from pipeline.config.scenes import scene_entry
from pipeline.config.synth import SynthConfig
from pipeline.config.variants import variant_configs
from pipeline.errors import ConfigError

# params.yaml's sections with a typed config; ``scenes`` maps names to entries.
SECTIONS: dict[str, type] = {"data": DataConfig, "synth": SynthConfig, "evaluate": EvaluateConfig, "loss": LossConfig,
                             "init": InitConfig, "priors": PriorsConfig, "optimize": OptimizeConfig, "mesh": MeshConfig,
                             "ablation": AblationConfig}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--write", action="store_true", help="write params.yaml")
    p.add_argument("--check", action="store_true", help="exit 1 if params.yaml differs from conf/")
    p.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. synth.seed=3")


def check_params(params: dict[str, Any]) -> None:
    """Build every section of ``params`` into its typed config, as the stages will, and every
    ablation variant merged over the main sections: a bad value fails here, before params.yaml
    is written, rather than in the stage that reads it."""
    known = [*SECTIONS, "scenes"]
    unknown, missing = sorted(set(params) - set(known)), [k for k in known if k not in params]
    if unknown:
        raise ConfigError(f"unknown top-level key(s) {unknown}; params has {', '.join(known)}")
    if missing:
        raise ConfigError(f"params lacks section(s) {missing}")
    for key, cls in SECTIONS.items():
        section(cls, key, params)
    for name in section_mapping("scenes", params["scenes"]):
        scene_entry(params, name)
    for name in section(AblationConfig, "ablation", params).variants:
        variant_configs(params, name)


def run(args: argparse.Namespace) -> int:
    params = compose_params(args.overrides)
    check_params(params)
    text = dump_params(params)
    if args.check:
        current = PARAMS_PATH.read_text() if PARAMS_PATH.is_file() else ""
        if current != text:
            print("params.yaml is stale: run `gcgs params --write`")
            return 1
        return 0
    if args.write:
        PARAMS_PATH.write_text(text)
        print(f"wrote {PARAMS_PATH}")
    else:
        print(text, end="")
    return 0
