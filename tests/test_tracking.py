"""The tracker interface: the in-memory and the MLflow implementation."""

import math

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from spot import config, tracking


def test_memory_tracker_keeps_steps_and_drops_non_finite(tmp_path):
    tr = tracking.MemoryTracker()
    tr.log_metrics({"a": 1, "b": float("nan"), "c": None, "d": np.float32(2.5)}, step=3)
    tr.log_series("s", [10, 20, 30], [1.0, math.inf, 3.0])
    f = tmp_path / "x.txt"
    f.write_text("hello")
    tr.log_artifact(f)
    tr.set_tags({"k": 1})
    assert tr.metrics == {"a": [(3, 1.0)], "d": [(3, 2.5)], "s": [(10, 1.0), (30, 3.0)]}
    assert tr.artifacts["x.txt"] == b"hello" and tr.tags == {"k": "1"}
    assert isinstance(tr, tracking.Tracker)


def test_mlflow_tracker_batches_and_marks_failures(tmp_path):
    cfg = config.load(None, [f"tracking.uri=sqlite:///{tmp_path / 'm.db'}", "tracking.experiment=t"])
    with tracking.start_run(cfg, {"name": "hopper-medium-replay", "source": "recipe"}) as tr:
        tr.log_series("curve", range(1500), np.arange(1500.0))  # more than one log_batch request
        tr.log_metrics({"x": 1.0, "nan": float("nan")})
        run_id = tr.run_id
    client = MlflowClient(cfg.tracking.uri)
    run = client.get_run(run_id)
    assert run.info.status == "FINISHED" and run.data.metrics["x"] == 1.0 and "nan" not in run.data.metrics
    history = client.get_metric_history(run_id, "curve")
    assert len(history) == 1500 and {m.step for m in history} == set(range(1500))
    assert config.from_flat(run.data.params) == cfg  # every param, across several batches
    with pytest.raises(RuntimeError), tracking.start_run(cfg, {"name": "x"}) as tr:
        raise RuntimeError("boom")
    failed = client.get_run(tr.run_id)
    assert failed.info.status == "FAILED" and failed.data.tags["failure_reason"] == "RuntimeError: boom"


