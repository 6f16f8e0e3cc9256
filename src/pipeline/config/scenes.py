"""params.yaml ``scenes``: each scene's source folder and ground truth."""
from __future__ import annotations

from dataclasses import dataclass

from pipeline.config.params import from_dict
from pipeline.errors import ConfigError


@dataclass
class SceneEntry:
    """One entry of ``scenes`` in params.yaml. An entry is data, not a setting with a value in
    conf/: ``gt`` may be left out (no ground truth), the one default of the config dataclasses
    besides :class:`~pipeline.config.ablation.VariantConfig`'s (tests/test_config_defaults.py)."""

    src: str
    gt: str | None = None


def scene_entry(params: dict, name: str) -> SceneEntry:
    """Scene ``name`` of params ``scenes``; a ConfigError naming the known ones if absent."""
    scenes = params.get("scenes") or {}
    if name not in scenes:
        raise ConfigError(f"scene {name!r} is not in params `scenes` ({sorted(scenes)})")
    return from_dict(SceneEntry, scenes[name], where=f"scenes.{name}")
