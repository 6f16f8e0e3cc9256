"""Files-to-files runs, one module per stage: read the stage's input folders, call the
libraries, write its output folder through :mod:`pipeline.atomic`. A stage script
(:mod:`pipeline.stages`) parses arguments and calls one function here.

* :mod:`init`, :mod:`priors`, :mod:`optimize`, :mod:`mesh` -- the per-scene method.
* :mod:`score` -- a scene's metrics (Chamfer or held-out views, and what training cost).
* :mod:`baseline` (+ :mod:`baseline_steps`, run in child processes) -- the classical baseline.
* :mod:`variant` -- one ablation cell trained, meshed and scored.
* :mod:`limit` -- the 3-view limit mesh and its score.
"""
