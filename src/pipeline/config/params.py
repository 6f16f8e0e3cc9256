"""Reading, composing and validating ``params.yaml`` sections into typed configs."""
from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any, TypeVar

import yaml

from pipeline.errors import ConfigError, MissingInputError

REPO_ROOT = Path(__file__).resolve().parents[3]
CONF_DIR = REPO_ROOT / "conf"
PARAMS_PATH = REPO_ROOT / "params.yaml"

T = TypeVar("T")


def check_image_size(where: str, width: int, height: int) -> None:
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ConfigError(f"{where}: image size must be positive integers, got {width}x{height}")


def merged_section(cls: type[T], key: str, params: dict[str, Any], changes: dict[str, Any]) -> T:
    """Section ``key`` of ``params`` with the partial mapping ``changes`` merged in
    (nested mappings merge key by key), validated like a params value."""

    def merge(base: dict, extra: dict) -> dict:
        out = copy.deepcopy(base)
        for k, v in extra.items():
            out[k] = merge(out.get(k) or {}, v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
        return out

    return from_dict(cls, merge(params.get(key) or {}, changes or {}), where=f"{key} (with a variant's changes)")


def from_dict(cls: type[T], data: dict[str, Any] | None, where: str = "") -> T:
    """Build a dataclass from a mapping, rejecting unknown keys (typos fail loudly)."""
    data = dict(data or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown} in config section {where or cls.__name__}")
    return cls(**data)


def nested_sections(config: Any, where: str, **classes: type) -> None:
    """Turn the nested sections of ``config`` that are still mappings (as read from YAML)
    into their dataclasses, in place; unknown keys fail as in :func:`from_dict`."""
    for name, cls in classes.items():
        value = getattr(config, name)
        if isinstance(value, dict) or value is None:
            setattr(config, name, from_dict(cls, value, where=f"{where}.{name}"))


def load_params(path: str | Path | None = None) -> dict[str, Any]:
    """Read a params file. Default: ``params.yaml`` of the working directory (DVC runs each
    stage in its project's root), else this repository's."""
    if path is None:
        path = Path("params.yaml") if Path("params.yaml").is_file() else PARAMS_PATH
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"{path}: params file not found")
    with open(path) as fh:
        return yaml.safe_load(fh) or {}


def section(cls: type[T], key: str, params: dict[str, Any] | None = None,
            overrides: dict[str, Any] | None = None) -> T:
    """Typed, validated config for one top-level key of params.yaml.

    ``overrides`` (command-line values) maps field names to values, dotted for nested
    sections (``{"mast3r.model": path}``); ``None`` values are not given and leave the
    params value. They are merged into the section's mapping *before* the dataclass is
    built, so an override is validated like a params value and a misspelt name fails."""
    params = load_params() if params is None else params
    data = copy.deepcopy(params.get(key) or {})
    for name, value in (overrides or {}).items():
        if value is None:
            continue
        *parents, leaf = name.split(".")
        node = data
        for parent in parents:
            node = node.setdefault(parent, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{key}.{name}: {parent} is not a section")
        node[leaf] = value
    return from_dict(cls, data, where=key)


def compose_params(overrides: list[str] | None = None) -> dict[str, Any]:
    """Compose ``conf/config.yaml`` with Hydra's compose API."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides or [])
    return OmegaConf.to_container(cfg, resolve=True)


def dump_params(params: dict[str, Any]) -> str:
    header = "# Generated from conf/ by `gcgs params --write`; do not edit by hand.\n"
    return header + yaml.safe_dump(params, sort_keys=False, default_flow_style=False)
