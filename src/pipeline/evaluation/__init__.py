"""Measuring: DTU Chamfer evaluation (accuracy / completeness / overall, mm), its ground-truth
files, and the other measures of a result. Nothing here runs a stage or writes a report.

* :mod:`pipeline.evaluation.sampling` -- triangle sampling and greedy radius downsampling.
* :mod:`pipeline.evaluation.gt` -- the ground-truth folder (official DTU layout) reader/writer.
* :mod:`pipeline.evaluation.dtu_eval` -- the evaluation protocol itself.
* :mod:`pipeline.evaluation.clouds` -- a point cloud against the ground truth.
* :mod:`pipeline.evaluation.heldout` -- held-out-view mask IoU and masked PSNR (no GT).
"""
