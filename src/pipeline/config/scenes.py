"""params.yaml ``scenes``: each scene's source folder, ground truth and masks."""
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
    masks: str  # gcgs prepare --masks: auto | capture | derive | none
    gt: str | None = None

    def __post_init__(self) -> None:
        if self.masks not in ("auto", "capture", "derive", "none"):
            raise ConfigError(f"scenes: masks must be auto, capture, derive or none, got {self.masks!r}")


def scene_entry(params: dict, name: str) -> SceneEntry:
    """Scene ``name`` of params ``scenes``; a ConfigError naming the known ones if absent."""
    scenes = params.get("scenes") or {}
    if name not in scenes:
        raise ConfigError(f"scene {name!r} is not in params `scenes` ({sorted(scenes)})")
    return from_dict(SceneEntry, scenes[name], where=f"scenes.{name}")
