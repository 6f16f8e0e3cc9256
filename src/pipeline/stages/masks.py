"""``gcgs masks``: object masks derived per input view for a prepared scene without masks,
from the init folder computed on it (or the init's MVS run here), written as a new scene
marked ``"masks": "derived"`` (:func:`pipeline.runs.masks.derive_scene_masks`; docs/inputs.md,
"Derived masks"). The labelling's settings come from params ``mesh``, the MVS's from ``init``."""
from __future__ import annotations

import argparse
import sys

from pipeline.config.init import InitConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.params import load_params, section
from pipeline.runs.masks import derive_scene_masks


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="prepared scene folder without masks")
    p.add_argument("--init-dir", default=None,
                   help="init stage output computed on that scene (its depth maps); default: run its MVS here")
    p.add_argument("--out-scene", required=True, help="new scene folder: the scene with the derived masks")
    p.add_argument("--overlays", default=None, help="also write each view's mask over its image here (NNN.png)")
    p.add_argument("--model", default=None,
                   help="salient-object ONNX model (U2-Net / IS-Net / BiRefNet export) refining the masks inside "
                        "the band around the 3D labelling, in place of GrabCut (docs/inputs.md)")
    p.add_argument("--params", default=None, help="params.yaml to read `mesh` and `init` from (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    record = derive_scene_masks(args.scene, args.init_dir, args.out_scene, section(MeshConfig, "mesh", params),
                                args.overlays, init_cfg=section(InitConfig, "init", params), model=args.model)
    views = record["views"]
    fallbacks = sum(v["method"] == "fallback_region" for v in views.values())
    coverage = ", ".join(f"{k}: {v['coverage']:.1%}" for k, v in views.items())
    print(f"masks: derived for views {list(map(int, views))} (coverage {coverage}; {fallbacks} fell back to the "
          f"region's silhouette) -> {args.out_scene}" + (f", overlays -> {args.overlays}" if args.overlays else ""), file=sys.stderr)
    return 0
