"""Issue 40 item 4 (a paper-budget Table 1 row as one program): the vmapped reward models follow the
one-seed training's evaluation period and best-checkpoint rule (the PT protocol of budget paper:
``reward.eval_epochs``, ``reward.best_min_delta``, ``reward.eval_initial``)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from spot.config import MRConfig, RewardConfig
from spot.reward import train, vmapped
from spot.reward.mr import MR
from tests.test_reward import synthetic_pairs

MR_TINY = MRConfig(hidden=(32, 32), lr=3e-3)


@pytest.mark.parametrize("min_delta", [1e-3, 10.0])
def test_vmapped_reward_models_keep_the_pt_protocols_checkpoint(min_delta):
    """32 training pairs at batch 8 and ``eval_epochs=1``: an evaluation every 32 // 8 + 1 = 5 steps
    (not ``eval_every``); the untrained loss is each seed's first best; with ``min_delta = 10`` no
    evaluation beats it, and each seed keeps its last evaluation (``best_improved`` False), as
    ``train_reward_model`` does for that seed alone."""
    cfg = RewardConfig(
        steps=25, batch_size=8, eval_every=100, eval_epochs=1, best_min_delta=min_delta, eval_initial=True
    )
    model = MR(MR_TINY)
    keys = [jax.random.key(5), jax.random.key(9)]
    trains = [synthetic_pairs(32, 5, 0), synthetic_pairs(32, 5, 3)]
    evals = [synthetic_pairs(12, 5, 1), synthetic_pairs(12, 5, 4)]
    together = vmapped.train_reward_models(model, keys, trains, evals, cfg, progress=False)
    for s in range(2):
        params, want = train.train_reward_model(model, keys[s], trains[s], evals[s], cfg, progress=False)
        got_params, got = together[s]
        assert got["step"] == want["step"] == [5, 10, 15, 20, 25]
        assert got["best_improved"] == want["best_improved"] == (min_delta < 1)
        assert got["best_step"] == want["best_step"]
        if min_delta > 1:
            assert got["best_step"] == 25  # the last evaluation, not the lowest held-out loss
        np.testing.assert_allclose(got["initial_eval_loss"], want["initial_eval_loss"], rtol=1e-5)
        np.testing.assert_allclose(got["eval_loss"], want["eval_loss"], rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(got["best_eval_loss"], want["best_eval_loss"], rtol=1e-4, atol=1e-5)
        seg = (evals[s]["obs_1"], evals[s]["act_1"], evals[s]["timesteps_1"], np.ones((12, 5), np.float32))
        have = np.asarray(train.model_fn(model, got_params)(*seg)[0])
        ref = np.asarray(train.model_fn(model, params)(*seg)[0])
        np.testing.assert_allclose(have - have.mean(), ref - ref.mean(), rtol=1e-3, atol=1e-4)
