"""Issue 40 item 4 (a paper-budget Table 1 row as one program): the evaluations of a vmapped IQL
program run on the CPU device, beside the training in a worker thread (``overlap``: the default on
an accelerator), and whole chunks run as loops of static length (``static``: the same default),
with the numbers of the evaluations made in line and of the traced chunks."""

from __future__ import annotations

import functools
import threading

import pytest

from spot import config, evaluation
from spot.run import multiseed
from spot.tracking import MemoryTracker

TINY = [
    "budget=tiny",
    "data.name=drawer-open",
    "iql.steps=170",
    "iql.chunk=50",
    "eval.every=50",
    "eval.episodes=2",
]


@pytest.mark.slow  # two tiny two-seed Oracle programs (~30 s of CPU)
def test_overlapped_evaluations_equal_evaluations_in_line(tmp_path, spot_dirs, tiny_drawer, monkeypatch):
    """Seeds 0 and 1 of Oracle as one vmapped program, evaluated in line with traced chunks, and
    in a worker thread while the training goes on with static-length chunks (170 updates: three
    whole chunks of 50, then 20 in the traced program): every logged series (chunk metrics,
    eval/score at 0, 50, 100, 150, 170) and every final score is equal to the last digit; the
    worker made every evaluation of the overlapped run, and each was logged from the caller's
    thread, in step order."""
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    original = multiseed.train_iql
    threads: list[str] = []
    evaluate_runs = evaluation.evaluate_runs

    def spy(*args, **kwargs):
        threads.append(threading.current_thread().name)
        return evaluate_runs(*args, **kwargs)

    monkeypatch.setattr(evaluation, "evaluate_runs", spy)
    out, trackers = {}, {}
    full_calls = []
    static_call = multiseed._StaticChunks.__call__

    def counted(self, state, n, *args):
        full_calls.append(n == self.length)
        return static_call(self, state, n, *args)

    monkeypatch.setattr(multiseed._StaticChunks, "__call__", counted)
    for overlap in (False, True):
        monkeypatch.setattr(multiseed, "train_iql", functools.partial(original, overlap=overlap, static=overlap))
        trackers[overlap] = [MemoryTracker(f"{overlap}-{s}") for s in (0, 1)]
        logged_from: list[str] = []
        for t in trackers[overlap]:
            t.log_metrics = functools.partial(_logged, t.log_metrics, logged_from)
        cfgs = [config.load(None, [*TINY, "method=oracle", f"seed={s}"]) for s in (0, 1)]
        out[overlap] = multiseed.run(cfgs, progress=False, trackers=trackers[overlap])
        assert set(logged_from) == {threading.current_thread().name}
    assert threads[:5] == [threading.current_thread().name] * 5  # in line: 5 evaluations
    assert len(threads) == 10 and all(name.startswith("spot-eval") for name in threads[5:])
    assert full_calls == [True, True, True, False]
    for s in (0, 1):
        a, b = trackers[False][s], trackers[True][s]
        assert [st for st, _ in b.metrics["eval/score"]] == [0, 50, 100, 150, 170]
        assert set(a.metrics) == set(b.metrics)
        for name in a.metrics:
            if not name.startswith("time/"):
                assert b.metrics[name] == a.metrics[name], name
        assert out[True][s]["eval/score_final"] == out[False][s]["eval/score_final"]
        assert out[True][s]["eval/score_best"] == out[False][s]["eval/score_best"]
    # the returns (drawer-open scores success, 0 this early) differ by seed: the two are not one copy
    assert trackers[True][0].metrics["eval/return"] != trackers[True][1].metrics["eval/return"]


def _logged(log_metrics, logged_from, *args, **kwargs):
    logged_from.append(threading.current_thread().name)
    return log_metrics(*args, **kwargs)
