"""The synthetic scenes (conf/synth)."""
from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.config.params import check_image_size


@dataclass
class SynthConfig:
    scenes: list[str] = field(default_factory=list)
    seed: int = 0
    width: int = 800
    height: int = 600
    camera_source: str = "data/raw/dtu/scan24"

    def __post_init__(self) -> None:
        check_image_size("synth", self.width, self.height)
