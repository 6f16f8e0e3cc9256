"""DTU Chamfer evaluation (accuracy / completeness / overall, mm) and its ground-truth files.

* :mod:`pipeline.evaluation.sampling` -- triangle sampling and greedy radius downsampling.
* :mod:`pipeline.evaluation.gt` -- the ground-truth folder (official DTU layout) reader/writer.
* :mod:`pipeline.evaluation.dtu_eval` -- the evaluation protocol itself.
"""
