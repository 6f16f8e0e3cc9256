"""``gcgs limit NAME``: the 3-view limit of a synthetic scene (:mod:`pipeline.evaluation.limit`):
its ground truth cut to what the input views see, written as a mesh and scored like the
method's -> ``reports/limit/NAME.json``, the yardstick row of Table II."""
from __future__ import annotations

import argparse
import json

from pipeline import atomic
from pipeline.config.data import DataConfig
from pipeline.data import dtu
from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.params import load_params, section
from pipeline.runs.limit import run_limit


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help="scene name")
    p.add_argument("--synth-dir", required=True, help="the `gcgs synth` output (exact geometry, gt/)")
    p.add_argument("--scene", required=True, help="prepared scene folder (masks for culling, as the method's)")
    p.add_argument("--out-dir", required=True, help="writes mesh.ply")
    p.add_argument("--report", required=True, help="metrics JSON to write")
    p.add_argument("--views", type=int, nargs="+", default=None, help="input views (default: the scene's own, else data.views)")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    atomic.check_output_file(args.report, inputs=(args.synth_dir, args.scene))
    params = load_params(args.params)
    views = section(DataConfig, "data", params, {"views": args.views or dtu.prepared_views(args.scene)}).views
    report = {"scene": args.name, **run_limit(args.synth_dir, args.scene, args.out_dir,
                                              section(EvaluateConfig, "evaluate", params),
                                              section(MeshConfig, "mesh", params), views)}
    atomic.write_text(args.report, json.dumps(report, indent=2, sort_keys=True) + "\n")
    c = report["chamfer"]
    print(f"limit {args.name}: views {views} see {report['gt_area_seen_fraction']:.0%} of the GT area; "
          f"accuracy {c['accuracy_mm']:.3f} / completeness {c['completeness_mm']:.3f} / overall {c['overall_mm']:.3f} mm"
          f"; exact depth through the meshing: {report['exact_depth']['overall_mm']:.3f} mm -> {args.report}")
    return 0
