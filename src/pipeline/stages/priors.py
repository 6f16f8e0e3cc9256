"""``gcgs priors``: per-view normal and feature priors of a prepared scene (docs/priors.md).

Writes ``OUT/normals/{view:03d}.npz``, ``OUT/features/{view:03d}.npz`` and
``OUT/priors.json`` into a temporary sibling folder renamed into place at the end. Only
what the loss uses is computed: no features when ``loss.lambda_gcf`` is 0, no normals
when ``loss.lambda_nor`` is 0.
"""
from __future__ import annotations

import argparse
import time

from pipeline.config.ablation import losses_in_use
from pipeline.config.params import load_params, section
from pipeline.config.priors import PriorsConfig
from pipeline.measure import peak_rss_mb
from pipeline.runs.priors import run_priors


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="prepared scene folder (DTU layout)")
    p.add_argument("--init-dir", default=None, help="init stage output (depth/ maps), needed by default normals")
    p.add_argument("--out-dir", required=True, help="output folder (normals/, features/, priors.json)")
    p.add_argument("--normals", choices=PriorsConfig.NORMALS, default=None, help="default: priors.normals")
    p.add_argument("--features", choices=PriorsConfig.FEATURES, default=None, help="default: priors.features")
    p.add_argument("--dsine-model", default=None, help="default: priors.dsine_model")
    p.add_argument("--vismvsnet-model", default=None, help="default: priors.vismvsnet_model")
    p.add_argument("--params", default=None, help="params.yaml to read `priors`, `loss` and `ablation` from (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    cfg = section(PriorsConfig, "priors", params, {key: getattr(args, key) for key in
                                                   ("normals", "features", "dsine_model", "vismvsnet_model")})
    losses = losses_in_use(params)
    t0 = time.perf_counter()
    info = run_priors(args.scene, args.out_dir, cfg, losses, init_dir=args.init_dir)
    print(f"priors: normals {info['normals']}, features {info['features']} (what the main loss and the ablation "
          f"cells weight) for views {info['views']} in {time.perf_counter() - t0:.2f} s "
          f"(peak RSS {peak_rss_mb()} MB) -> {args.out_dir}")
    return 0
