"""The init stage's backends: a dense (or sparse) point cloud from the input views and
their known cameras. The backends are named in :mod:`pipeline.init.backends`; file
formats are in :mod:`pipeline.init.io` and ``docs/init.md``. This package's ``__init__``
imports nothing, so reading the init's files does not pull in the backends."""
