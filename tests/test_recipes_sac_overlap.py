"""Issue 40, item 4: the locomotion recipe's SAC evaluates beside its training (a worker thread,
:class:`spot.recipes.sac_train._Evaluations`) when no stop rule reads the evaluations, and the
built data stay byte-equal: the dataset's fingerprint equals the sequential loop's, and the one the
old code (sequential only, commit 7877892) built on the project's 2-core machine."""

import threading

import pytest

from spot.recipes import locomotion, sac_train

# hopper-medium-replay, size tiny, seed 0, built with the sequential loop of commit 7877892
OLD_FINGERPRINT = "889c92369b5ea5acf71fe638d129e5873cdc0a56ac4fd619eef9f8cd115c05bd"


def build(tmp_path, monkeypatch, overlap: bool | None) -> tuple[str, list, set[str]]:
    """Build in a fresh SAC cache; ``overlap`` None: as the recipe decides. Returns the
    fingerprint, the eval curve and the threads the evaluations ran in."""
    threads: set[str] = set()
    returns = sac_train._Run.returns

    def spy(self, step, params):
        threads.add(threading.current_thread().name)
        return returns(self, step, params)

    monkeypatch.setattr(sac_train._Run, "returns", spy)
    if overlap is not None:
        evaluations, forced = sac_train._Evaluations, overlap
        monkeypatch.setattr(
            sac_train, "_Evaluations", lambda run, on_eval, bar, overlap: evaluations(run, on_eval, bar, forced)
        )
    raw, card = locomotion.build("hopper-medium-replay", "tiny", 0, tmp_path, progress=False)
    monkeypatch.undo()
    return raw.qlearning().fingerprint(), card["behaviour"]["eval_curve"], threads


def test_overlapped_evaluations_leave_the_data_byte_equal(tmp_path, monkeypatch):
    assert locomotion.SIZES["tiny"].sac_config("hopper").target_return is None  # no stop rule: overlapped
    fp, curve, threads = build(tmp_path / "overlapped", monkeypatch, None)
    assert threads and all(t.startswith("sac-eval") for t in threads)  # the evaluations ran beside the training
    fp_seq, curve_seq, threads_seq = build(tmp_path / "sequential", monkeypatch, False)
    assert threads_seq == {threading.main_thread().name}
    assert (fp, curve) == (fp_seq, curve_seq) and len(curve) == 6  # every 500 of 3000 steps
    if fp_seq != OLD_FINGERPRINT:
        pytest.skip("this machine's XLA computes other bits than the machine the old fingerprint was recorded on")
    assert fp == OLD_FINGERPRINT


def test_a_run_with_a_stop_rule_evaluates_before_it_goes_on(tmp_path, monkeypatch):
    """The stop rule reads each evaluation before the next chunk: no overlap, and the run stops at
    the first evaluation that reaches the target (-inf: the first)."""
    import dataclasses

    cfg = dataclasses.replace(locomotion.SIZES["tiny"].sac_config("hopper"), target_return=-1e9, total_steps=2000)
    seen: list[str] = []
    returns = sac_train._Run.returns
    monkeypatch.setattr(
        sac_train._Run,
        "returns",
        lambda self, s, p: seen.append(threading.current_thread().name) or returns(self, s, p),
    )
    result = sac_train.train_sac("Hopper-v5", cfg, 0, progress=False)
    assert seen == [threading.main_thread().name] and [s.step for s in result.snapshots] == [500]
    assert len(result.replay["rewards"]) == 500
