"""Reports: tables, the index, renders and plots made from the runs' JSON and meshes.

* :mod:`read` -- the one reader of report JSON (a missing file or figure is named).
* :mod:`table1`, :mod:`table2`, :mod:`baseline_table` -- Markdown and CSV tables.
* :mod:`index` -- ``reports/index.md``; :mod:`renders` -- per-scene pictures;
  :mod:`speed_accuracy` -- the speed-accuracy CSV and Pareto plot.
"""
