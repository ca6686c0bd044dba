"""The public entry point of one run: ``pipeline.run(cfg, tracker=...)`` (docs/design.md).

:func:`run` runs one seed of a config end to end and returns its final metrics; :func:`evaluate_run`
evaluates a logged run's policy again (``spot eval``); :func:`open_dataset` opens a config's
dataset once per process. They live in :mod:`spot.run.pipeline` (the data flow) and are
re-exported here, the same functions.
"""

from spot.run.pipeline import evaluate_run, open_dataset, run

__all__ = ["evaluate_run", "open_dataset", "run"]
