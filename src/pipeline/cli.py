"""The ``gcgs`` command. Each subcommand lives in its own module, imported on use so
that ``gcgs --help`` stays fast; a module provides ``add_arguments(parser)`` and
``run(args) -> int``."""
from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading

from pipeline.errors import InputError, Interrupted
from pipeline.heap import keep_freed_memory
from pipeline.threads import configure_threads

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "params": ("pipeline.stages.params", "compose conf/ into params.yaml (or check it)"),
    "prepare": ("pipeline.stages.prepare", "load, check and resize a DTU-layout scan for training"),
    "synth": ("pipeline.stages.synth", "render a synthetic scene with exact ground truth"),
    "evaluate": ("pipeline.stages.evaluate", "DTU Chamfer distance of a mesh (mm)"),
    "init": ("pipeline.stages.init", "initial point cloud of a scene (mvs, sfm, mast3r or random)"),
    "masks": ("pipeline.stages.masks", "object masks derived per input view for a scene without masks (new scene)"),
    "tsdf": ("pipeline.stages.tsdf", "TSDF-fuse an init folder's depth maps into a cleaned mesh (mm)"),
    "baseline": ("pipeline.stages.baseline", "one scene's init clouds of every backend and MVS+TSDF mesh vs GT, timed"),
    "baseline-report": ("pipeline.stages.baseline_report", "combine the per-scene baseline reports into one table"),
    "table1": ("pipeline.stages.table1", "Table I: Chamfer per scene measured here next to published figures"),
    "render-scene": ("pipeline.stages.render_scene", "a scene's input view, surfel colour and normal, mesh (PNG)"),
    "report-index": ("pipeline.stages.report_index", "reports/index.md: tables, plots, renders, curves"),
    "priors": ("pipeline.stages.priors", "per-view normal and feature priors (default, dsine, vismvsnet)"),
    "optimize": ("pipeline.stages.optimize", "train 2D Gaussian surfels with the GCGS losses"),
    "mesh": ("pipeline.stages.mesh", "TSDF mesh (mm) of depth rendered from trained surfels"),
    "score": ("pipeline.stages.score", "per-scene metrics of the method (Chamfer or held-out views, cost)"),
    "limit": ("pipeline.stages.limit", "the 3-view limit of a synthetic scene: its GT seen by the input views, scored"),
    "table2": ("pipeline.stages.table2", "Table II: the ablation on the synthetic suite (Markdown + CSV)"),
    "variant": ("pipeline.stages.variant", "one ablation cell: a variant trained, meshed and scored on one scene"),
    "variant-train": ("pipeline.stages.variant_train", "the training half of an ablation cell (a DVC stage)"),
    "variant-score": ("pipeline.stages.variant_score", "the meshing and scoring half of an ablation cell (a DVC stage)"),
    "bench-eval": ("pipeline.benchmarks.evaluation", "benchmark the Chamfer evaluation"),
    "bench-raster": ("pipeline.benchmarks.rasterizer", "benchmark the surfel rasterizer"),
    "bench-train": ("pipeline.benchmarks.training", "where a training iteration's time goes (kernels, autograd, losses)"),
    "bench-priors": ("pipeline.benchmarks.priors", "benchmark the priors stage and the prior losses"),
    "bench-gcf": ("pipeline.benchmarks.gcf_offset", "GCF loss against a depth offset (minimum at the true depth?)"),
    "bench-layouts": ("pipeline.benchmarks.layouts", "one synthetic scene from the DTU, COLMAP and nerfstudio layouts: same Chamfer?"),
}

NO_THREADS = {"params"}  # composes YAML only


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gcgs", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == only:
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    name = argv[0] if argv and argv[0] in COMMANDS else None
    parser = build_parser(only=name)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    module = importlib.import_module(COMMANDS[args.command][0])
    # Signal handlers belong to the main thread (a sweep may call main from others).
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate_as_interrupt) if main_thread else None
    try:
        if args.command not in NO_THREADS:
            configure_threads()
            keep_freed_memory()
        return int(module.run(args) or 0)
    except InputError as exc:
        # Bad input (SceneError, CameraError, ConfigError, OutputError ...) names the file and
        # the problem: one line. Anything else is a bug and keeps its traceback.
        print(f"gcgs {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except Interrupted as exc:
        print(f"gcgs {args.command}: {exc}", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print(f"gcgs {args.command}: interrupted; nothing was written (outputs appear only when complete)",
              file=sys.stderr)
        return 130
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


def _terminate_as_interrupt(signum, frame) -> None:
    """SIGTERM (what SLURM, ``docker stop`` and ``timeout`` send) ends a command as Ctrl-C
    does: the training keeps its checkpoint and names it, nothing half-written is left."""
    raise KeyboardInterrupt


if __name__ == "__main__":
    sys.exit(main())
