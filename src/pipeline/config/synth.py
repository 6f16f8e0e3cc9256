"""The synthetic scenes (conf/synth)."""
from __future__ import annotations

from dataclasses import dataclass

from pipeline.config.params import FromConf, check_image_size, require_min


@dataclass
class SynthConfig(FromConf):
    """The synthetic scenes and their rendering (values: conf/synth/default.yaml)."""

    SECTION = "synth"

    scenes: list[str]
    seed: int
    width: int
    height: int
    camera_source: str  # the scan whose cameras (all 49 views) render the scenes

    def __post_init__(self) -> None:
        check_image_size("synth", self.width, self.height)
        require_min("synth", self, "seed")
