"""Synthetic scenes with exact ground truth (see docs/synthetic.md)."""
from pipeline.synth.render import Renderer, raycast_depth
from pipeline.synth.scenes import SCENES, SynthScene, build_scene, table_frame, write_synth_scene

__all__ = ["SCENES", "Renderer", "SynthScene", "build_scene", "raycast_depth", "table_frame", "write_synth_scene"]
