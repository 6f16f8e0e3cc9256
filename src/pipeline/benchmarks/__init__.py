"""Benchmarks and measured checks, one ``gcgs bench-*`` subcommand each; their figures go
under ``reports/`` (which holds outputs only). Time and memory come from
:mod:`pipeline.measure`; speed is never asserted in tests (each has a smoke test on a tiny
case instead, tests/test_bench_*.py).

* :mod:`.evaluation` -- ``gcgs bench-eval``: ``gcgs evaluate`` on a ~1 M-vertex mesh
  (``reports/benchmarks/evaluation.{json,md}``).
* :mod:`.rasterizer` -- ``gcgs bench-raster``: the surfel rasterizer's cpu and reference
  backends (``reports/benchmarks/rasterizer*.{json,md}``).
* :mod:`.training` -- ``gcgs bench-train``: a training iteration's time split between the
  rasterizer's kernels, torch's autograd and the loss terms
  (``reports/benchmarks/training*.{json,md}``).
* :mod:`.priors` -- ``gcgs bench-priors``: the priors stage and the prior losses on the
  bundled scan (``reports/priors/stage_benchmark.json``).
* :mod:`.gcf_offset` -- ``gcgs bench-gcf``: the GCF loss against a depth offset
  (``reports/priors/gcf_vs_depth_offset.{json,png}``).
"""
