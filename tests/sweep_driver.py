"""``spot sweep`` (the real CLI, Ray, Tune and MLflow server) whose trials run a stand-in for the
pipeline, for the fault tests in tests/test_hardening.py.

Usage: ``python tests/sweep_driver.py GATE_DIR ARGS...`` where ARGS are ``spot sweep``'s. Each seed
opens a real MLflow run through :func:`spot.tracking.start_run` (tags, params, parent run, host and
pid, as the pipeline does), touches ``GATE_DIR/started-<pid>-<trial_key>``, waits while
``GATE_DIR/hold`` exists (at most 300 s), reports one evaluation and ends FINISHED. The function is
defined here, in ``__main__``, so Ray ships it to the trials by value.
"""

from __future__ import annotations

import functools
import os
import sys
import time
from pathlib import Path
from typing import Any


def stand_in_run(
    cfg: Any, *, progress: bool, parent_run_id: str | None, extra_tags: dict[str, str], on_eval: Any, gate: str = ""
) -> dict[str, Any]:
    from spot import tracking

    folder = Path(gate)
    with tracking.start_run(
        cfg, {"name": cfg.data.name}, extra_tags=extra_tags, parent_run_id=parent_run_id
    ) as tracker:
        (folder / f"started-{os.getpid()}-{extra_tags['trial_key']}").touch()
        deadline = time.monotonic() + 300
        while (folder / "hold").exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        on_eval({"score": 1.0, "step": 1})
        tracker.log_metrics({"eval/score_final": 1.0, "eval/score_best": 1.0}, step=1)
        run_id = tracker.run_id
    return {"run_id": run_id, "eval/score_final": 1.0, "eval/score_best": 1.0}


if __name__ == "__main__":
    from spot import cli, sweep

    gate_dir, *argv = sys.argv[1:]
    sweep.run_sweep = functools.partial(sweep.run_sweep, run_fn=functools.partial(stand_in_run, gate=gate_dir))
    sys.exit(cli.main(["sweep", *argv]))
