"""Typed configs mirroring ``conf/`` and the composed ``params.yaml``, one module per
concept so that a stage depends only on the configs it reads (an edit to the init's
settings does not rerun the stages that never read them).

``conf/`` is the source of truth (Hydra); ``params.yaml`` is its composition, committed
because ``dvc repro`` reads params.yaml without composing. :func:`pipeline.config.params.
compose_params` recomposes ``conf/`` and a test checks that the two agree. ``conf/`` is also
the one source of every default value: the dataclasses' fields have none, and
``SomeConfig.default(**changes)`` (:class:`pipeline.config.params.FromConf`) builds a config
from ``conf/``'s default composition (tests/test_config_defaults.py keeps the two in step).
This package imports nothing: import from the concept's module.
"""
