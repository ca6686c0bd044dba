"""Sweeps: a YAML file of axes over run configs -> Ray Tune trials -> one MLflow run per (config, seed).

* :mod:`spot.sweep.spec`: the file format, validation (:func:`load`), expansion into trials, and
  the keys that name a config and a (config, seed) run.
* :mod:`spot.sweep.trial`: what runs in a trial's process (CPU slots, XLA settings, each seed's
  run, skipping seeds that already finished, recording failures).
* :mod:`spot.sweep.launch`: the driver (``spot sweep FILE``): the launch's flow, from the file to
  the summary, and resume.
* :mod:`spot.sweep.api`: the Python entry (docs/python.md): :func:`run_sweep` from a file or a dict,
  :func:`resolve` (a file or dict -> its validated :class:`Sweep`, launching nothing).
* :mod:`spot.sweep.uris`: which tracking URIs and ``--tracking-host`` values a sweep takes.
* :mod:`spot.sweep.tracking_store`: the launch's store (a server given by URI, or a SQLite store
  served by :mod:`spot.sweep.mlflow_server`), the watch on that server, closing the launch's runs.
* :mod:`spot.sweep.tune`: Ray (local on loopback, or a cluster) and the Tune experiment.
* :mod:`spot.sweep.launch_record`: the record of the last launch and the lock a running one holds.
* :mod:`spot.sweep.parent`: the launch's parent run (created, reopened on resume, closed).
* :mod:`spot.sweep.signals`: SIGINT/SIGTERM: :class:`Interrupted`, a SIGTERM's stepped cleanup.
* :mod:`spot.sweep.summary`: the per-(config, seed) summary and the sweep's paper table.
* :mod:`spot.sweep.status`: where the last launch stands (``spot sweep FILE --status``), from MLflow.

MLflow is the record: the driver creates the experiment and a parent run; each (config, seed) is
a child run tagged with the sweep id, the Ray trial id, a ``trial_key`` (hash of the override dict
and seed) and one ``axis.<key>`` tag per axis. With no tracking URI the driver serves a SQLite
store through a loopback ``mlflow server`` (:mod:`spot.sweep.mlflow_server`), so no trial writes SQLite
itself; for a cluster sweep ``--tracking-host`` binds that server where other nodes reach it.

Multi-node: a store named by the file's ``store:`` or ``--store`` (:mod:`spot.store`, passed to
every trial as ``$SPOT_STORE``) holds the datasets the driver built and the stage-cache entries,
so a trial on any node finds them, and each shared stage is computed once (a lock on its key).

Resume and failures: ``--resume`` restores the Ray experiment (``Tuner.restore``) after closing
the runs an interrupted launch left RUNNING (they become KILLED). A trial first looks in MLflow
for a FINISHED run with its sweep id and trial key and reports that instead of running again, so a
trial that Ray re-runs after a crash is not duplicated: every (config, seed) ends with exactly one
FINISHED run. A trial that raises is marked FAILED with its ``failure_reason``, the others go on,
and the summary lists it.
"""

from spot.sweep.api import resolve, run_sweep
from spot.sweep.launch import DEFAULT_STORAGE, prebuild_datasets
from spot.sweep.signals import Interrupted
from spot.sweep.spec import Sweep, Trial, config_key, load, load_dict, run_key, tag_value
from spot.sweep.summary import Row, format_summary, paper_table, summarize
from spot.sweep.trial import SweepContext, configure_process, run_trial

__all__ = [
    "DEFAULT_STORAGE",
    "Interrupted",
    "Row",
    "Sweep",
    "SweepContext",
    "Trial",
    "config_key",
    "configure_process",
    "format_summary",
    "load",
    "load_dict",
    "paper_table",
    "prebuild_datasets",
    "resolve",
    "run_key",
    "run_sweep",
    "run_trial",
    "summarize",
    "tag_value",
]
