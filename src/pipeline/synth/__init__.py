"""Synthetic scenes with exact ground truth (see docs/synthetic.md)."""
from pipeline.synth.scenes import SCENES, Renderer, SynthScene, build_scene, raycast_depth, write_synth_scene

__all__ = ["SCENES", "Renderer", "SynthScene", "build_scene", "raycast_depth", "write_synth_scene"]
