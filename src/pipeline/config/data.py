"""The training views and resolution (conf/data)."""
from __future__ import annotations

from dataclasses import dataclass

from pipeline.config.params import FromConf, check_image_size
from pipeline.errors import ConfigError


@dataclass
class DataConfig(FromConf):
    """Training views and resolution (values: conf/data/default.yaml). ``height`` must keep
    the source images' aspect ratio (``gcgs prepare`` refuses to squash)."""

    SECTION = "data"

    views: list[int]
    width: int
    height: int

    def __post_init__(self) -> None:
        if not self.views or any(int(v) != v or v < 0 for v in self.views) or len(set(self.views)) != len(self.views):
            raise ConfigError(f"data.views must be distinct view ids >= 0, got {self.views}")
        check_image_size("data", self.width, self.height)
