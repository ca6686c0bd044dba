"""Reward-model training from preferences: the PT/MR training loop. The loss (eq. 1-2) and the
jitted programs it runs (one update, a chunk of updates, the held-out evaluation) are
:mod:`spot.reward.update`'s.

Training (reference/algorithms.md §1.2, §1.5; paper Table 5):

* PT: AdamW, ``b1 = 0.9, b2 = pt.b2`` (Table 5: 0.99; the PT repo keeps optax's 0.999), weight
  decay ``PTConfig.weight_decay``; by default (``pt.schedule=warmup_constant``) the learning rate
  rises linearly from 0 to ``PTConfig.lr`` over ``warmup_steps``, then stays **constant** (Table 5
  lists warmup only). ``pt.schedule=warmup_cosine`` is the PT repo's schedule: from ``lr`` up to
  ``pt.peak_factor * lr`` (10x) over the warmup (PT repo: 10 % of the steps,
  ``pt.warmup_fraction=0.1``), then a cosine back down to ``lr`` at the last step. Dropout on.
* MR: Adam, ``MRConfig.lr``, constant.
* Minibatches of ``min(batch_size, Q)`` pairs drawn without replacement on device at every step
  (PT repo: shuffled epochs, which with ``Q <= batch_size`` means the whole set every step).
* :mod:`spot.loop` chunks of ``eval_every`` steps (state donated, per-step keys
  ``fold_in(key, step)``); a run does exactly ``steps`` steps, the last partial chunk running the
  same compiled program. The jitted chunk is kept per model and sizes, so later runs with the
  same config and shapes in this process compile nothing.
* Each minibatch's gradient is accumulated over micro-batches of ~64 pairs: the same loss and
  gradient as one pass, with less peak memory and faster on CPU (docs/benchmarks.md).
* After each chunk: held-out loss/accuracy; the parameters with the best held-out loss are kept
  (PT repo ``best_model.pkl``). A non-finite loss raises :class:`NonFiniteError` naming the step.
  A chunk is ``reward.eval_every`` steps, or with ``reward.eval_epochs`` that many epochs as the PT
  repo counts them (:func:`eval_period`; PT repo: 5). The best-checkpoint rule (:class:`BestRule`):
  a new best needs a held-out loss below the best so far by more than ``reward.best_min_delta``
  (PT repo: flax ``EarlyStopping(min_delta=1e-3)``), and with ``reward.eval_initial`` the
  untrained model's loss is the first best, never kept itself (PT repo: the epoch-0 evaluation;
  ``train_offline.py`` loads ``model.pkl``, the last parameters, when no ``best_model.pkl`` was
  saved). Defaults (0, false): the lowest held-out loss over the chunks.
* Minibatches are drawn i.i.d. at every step (each ``min(batch_size, Q)`` distinct pairs); the
  PT repo shuffles once per epoch and walks the permutation in ``⌊Q / B⌋ + 1`` batches (the last
  one ``Q mod B`` pairs): the same whenever ``Q <= B``, a different order and batch sizes above
  (docs/fidelity.md).
* A companion learner (``companion=``, :class:`Companion`; the online CVAE of
  ``cvae.schedule=online``, built by the stages from ``spot.subgoal.online``) takes one step after
  every update on that update's training forward pass (:class:`spot.reward.update.ForwardPass`: the minibatch, PT's
  per-step rewards and preference attention, dropout on, parameters before the update), with its
  own key; the reward model's keys, minibatches and parameters are the same as without it. Its
  state rides in the scan state, its metrics in the chunk rows, and its final state is returned.

The model is any :class:`spot.reward.models.RewardModel` (``MR(cfg)``, ``PT(cfg)``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import numpy as np

from spot import NonFiniteError, SpotError, loop  # noqa: F401  (NonFiniteError: raised by loop.run)
from spot.config import RewardConfig
from spot.nets import Params
from spot.reward.models import RewardModel
from spot.reward.update import ForwardPass, PrefPairs, init_state, make_evaluate, make_train_chunk, num_pairs

PAIR_KEYS = ("obs_1", "act_1", "timesteps_1", "obs_2", "act_2", "timesteps_2", "label")


class Companion(NamedTuple):
    """A learner trained alongside the reward model: ``step(state, ForwardPass, key) -> (state,
    metrics)`` (hashable: compiled programs are kept per step function), its initial ``state``, and
    the metrics to check for NaN/inf (metric -> reported name)."""

    step: Callable[[Any, ForwardPass, jax.Array], tuple[Any, dict]]
    state: Any
    losses: Mapping[str, str]


def pref_pairs(batch: Mapping[str, np.ndarray], where: str = "preference batch") -> PrefPairs:
    """Check a ``segment_batch`` dict (see :mod:`spot.data.labels`) and cast it to a host
    :class:`spot.reward.update.PrefPairs` (numpy; ``jax.device_put`` moves it).

    Optional keys ``mask_1``/``mask_2`` mark padded steps; without them every step is real.
    """
    missing = [k for k in PAIR_KEYS if k not in batch]
    if missing:
        raise SpotError(f"{where}: missing key(s) {', '.join(missing)}; expected {', '.join(PAIR_KEYS)}")
    q, t = np.shape(batch["obs_1"])[:2]
    for s in ("1", "2"):
        obs, act, ts = (np.shape(batch[f"{k}_{s}"]) for k in ("obs", "act", "timesteps"))
        if len(obs) != 3 or len(act) != 3 or obs[:2] != (q, t) or act[:2] != (q, t) or ts != (q, t):
            raise SpotError(
                f"{where}: segment {s} has obs {obs}, act {act}, timesteps {ts}; expected "
                f"[{q}, {t}, obs_dim], [{q}, {t}, act_dim] and [{q}, {t}]"
            )
    if np.shape(batch["label"]) != (q,):
        raise SpotError(f"{where}: 'label' has shape {np.shape(batch['label'])}; expected [{q}]")
    if not np.all(np.isin(batch["label"], (0.0, 0.5, 1.0))):
        raise SpotError(f"{where}: labels must be 0, 0.5 or 1 (1 = segment 2 preferred)")
    ones = np.ones((q, t), np.float32)
    fields: dict[str, np.ndarray] = {}
    for s in ("1", "2"):
        fields[f"obs_{s}"] = np.asarray(batch[f"obs_{s}"], np.float32)
        fields[f"act_{s}"] = np.asarray(batch[f"act_{s}"], np.float32)
        fields[f"timesteps_{s}"] = np.asarray(batch[f"timesteps_{s}"], np.int32)
        fields[f"mask_{s}"] = np.asarray(batch.get(f"mask_{s}", ones), np.float32)
    return PrefPairs(**fields, label=np.asarray(batch["label"], np.float32))


def clip_actions(batch: Mapping[str, np.ndarray] | None, clip: float) -> Mapping[str, np.ndarray] | None:
    """``batch`` with ``act_1``/``act_2`` clipped to ``±clip`` (``reward.clip_action``: the PT repo
    clips its reward-model data to ±0.999); ``clip = 0`` or no batch: unchanged."""
    if batch is None or clip <= 0:
        return batch
    return {**batch, **{k: np.clip(batch[k], -clip, clip) for k in ("act_1", "act_2") if k in batch}}


def eval_period(reward_cfg: RewardConfig, num_pairs: int) -> int:
    """Steps between held-out evaluations: ``reward.eval_every``, or with ``reward.eval_epochs > 0``
    that many PT-repo epochs, ``eval_epochs * (floor(N / batch_size) + 1)`` steps (PT repo
    ``new_preference_reward_main.py``: ``eval_period`` 5 epochs)."""
    if reward_cfg.eval_epochs > 0:
        return reward_cfg.eval_epochs * (num_pairs // reward_cfg.batch_size + 1)
    return reward_cfg.eval_every


class BestRule:
    """Which evaluated parameters are kept: a held-out loss ``L`` is a new best when ``best - L >
    min_delta`` (flax ``EarlyStopping.update``; ``best`` starts at ``inf``, or at the untrained
    model's loss with ``baseline``); the best parameters are copied to the host. When nothing
    beat the baseline, :meth:`result` is the last evaluation (the PT repo's ``model.pkl``)."""

    def __init__(self, min_delta: float, baseline: float | None, params_of: Callable[[Any], Any]):
        self.min_delta, self.params_of = min_delta, params_of
        self.best_value = math.inf if baseline is None else baseline
        self.best: dict[str, Any] | None = None
        self.params: Any = None
        self.last: tuple[dict[str, Any], Any] | None = None

    def update(self, row: dict[str, Any], state: Any) -> None:
        """``loop.run``'s ``on_chunk``: the chunk's row (with ``eval_loss``) and state."""
        improved = self.best_value - row["eval_loss"] > self.min_delta
        if improved or self.best is None:
            host = jax.tree.map(lambda a: np.array(a, copy=True), self.params_of(state))
            if improved:
                self.best_value, self.best, self.params = row["eval_loss"], row, host
            else:
                self.last = (row, host)

    def result(self) -> tuple[dict[str, Any], Any, bool]:
        """``(row, params, improved)``: the best row and its parameters, or the last evaluation's
        when no evaluation was a new best (``improved`` False)."""
        if self.best is not None:
            return self.best, self.params, True
        assert self.last is not None
        return (*self.last, False)


def training_steps(reward_cfg: RewardConfig, num_pairs: int) -> int:
    """Gradient steps of a reward-model run: ``reward.steps``, or with ``reward.length=epochs`` the
    PT repo's count ``epochs * (floor(N / batch_size) + 1)`` for ``N`` training pairs
    (``new_preference_reward_main.py``: ``interval = int(data_size / batch_size) + 1`` steps per epoch)."""
    if reward_cfg.length == "epochs":
        return reward_cfg.epochs * (num_pairs // reward_cfg.batch_size + 1)
    return reward_cfg.steps


# --------------------------------------------------------------------------- driver
def _checked_pairs(
    model: RewardModel, train_batch: Mapping[str, np.ndarray], eval_batch: Mapping[str, np.ndarray] | None
) -> tuple[PrefPairs, PrefPairs, str]:
    """Train and held-out pairs (the training pairs when there is no eval batch) and ``eval_on``."""
    train = pref_pairs(train_batch, "train preference batch")
    eval_on = "eval" if eval_batch is not None and np.size(eval_batch.get("label", 1)) > 0 else "train"
    held_out = pref_pairs(eval_batch, "eval preference batch") if eval_on == "eval" else train
    if held_out.obs_1.shape[2:] != train.obs_1.shape[2:] or held_out.act_1.shape[2:] != train.act_1.shape[2:]:
        raise SpotError(
            f"eval pairs have obs/act dims {held_out.obs_1.shape[2:]}/{held_out.act_1.shape[2:]} but "
            f"train pairs have {train.obs_1.shape[2:]}/{train.act_1.shape[2:]}"
        )
    for name, p in (("train", train), ("eval", held_out)):
        lo = int(min(p.timesteps_1.min(), p.timesteps_2.min()))
        hi = int(max(p.timesteps_1.max(), p.timesteps_2.max()))
        model.check_timesteps(lo, hi, f"{name} pairs")
    return train, held_out, eval_on


def train_reward_model(
    model: RewardModel,
    key: jax.Array,
    train_batch: Mapping[str, np.ndarray],
    eval_batch: Mapping[str, np.ndarray] | None,
    reward_cfg: RewardConfig,
    progress: bool = True,
    micro_batch: int = 64,
    companion: Companion | None = None,
) -> tuple[Params, dict[str, Any]]:
    """Train a reward model (``MR(cfg)`` or ``PT(cfg)``) on preference pairs for exactly
    :func:`training_steps` steps (``reward.steps``, or ``reward.epochs`` counted as the PT repo does).

    Args:
      model: the :class:`spot.reward.models.RewardModel` (``models.from_config(cfg)``).
      key: PRNG key (split here into init and training keys).
      train_batch, eval_batch: ``segment_batch`` dicts (:func:`pref_pairs`); an empty or missing
        eval batch evaluates on the training pairs (``history["eval_on"] = "train"``).
      reward_cfg: steps, batch size, evaluation period and best-checkpoint rule.
      progress: show a tqdm bar over steps.
      micro_batch: gradient-accumulation slice size in pairs (:func:`spot.reward.update.make_update`; speed only).
      companion: a learner that takes one step per update on its forward pass (module
        docstring); the reward model trains exactly as without it.

    Returns:
      ``(params, history)``: the parameters with the lowest held-out loss, and a dict with per-chunk
      lists ``step`` (steps done), ``train_loss``, ``train_acc`` (chunk means), ``eval_loss``,
      ``eval_acc``, and ``best_step``, ``best_eval_loss``, ``best_eval_acc``, ``batch_size``,
      ``eval_on``, ``compile_s`` (next to nothing when this process compiled the same programs
      before), ``train_s``, ``steps_per_s``, ``steps`` (steps taken), ``initial_eval_loss``,
      ``best_improved`` (:class:`BestRule`; False: the last evaluation's). With a companion also
      ``companion_state`` (its state after the last update) and ``companion`` (its metrics: one
      list of chunk means per name).

    Raises:
      NonFiniteError: a train or eval loss is NaN/inf.
      SpotError: malformed batches or a config that does not fit the data.
    """
    train, held_out, eval_on = _checked_pairs(model, train_batch, eval_batch)
    init_key, train_key = jax.random.split(key)
    del key
    steps = training_steps(reward_cfg, num_pairs(train))
    state = init_state(model, init_key, train.obs_1.shape[-1], train.act_1.shape[-1], steps)
    batch_size = min(reward_cfg.batch_size, num_pairs(train))
    length = loop.chunk_length(steps, eval_period(reward_cfg, num_pairs(train)))
    eval_data, eval_weight = jax.device_put(
        loop.pad_minibatches(held_out, min(reward_cfg.batch_size, num_pairs(held_out)))
    )
    train = jax.device_put(train)

    step_fn = companion.step if companion is not None else None
    train_chunk = make_train_chunk(model, batch_size, length, steps, micro_batch, step_fn)
    evaluate = make_evaluate(model)
    params_of = (lambda st: st[0].params) if companion is not None else (lambda st: st.params)
    if companion is not None:
        state = (state, companion.state)
    compile_s = loop.compile_seconds(train_chunk, state, length, train, train_key) + loop.compile_seconds(
        evaluate, params_of(state), eval_data, eval_weight
    )
    baseline = float(evaluate(params_of(state), eval_data, eval_weight)[0]) if reward_cfg.eval_initial else None
    rule = BestRule(reward_cfg.best_min_delta, baseline, params_of)
    out = loop.run(
        train_chunk,
        state,
        (train, train_key),
        steps=steps,
        length=length,
        losses={"loss": "reward/train_loss", **(companion.losses if companion is not None else {})},
        evaluate=lambda st: dict(
            zip(("eval_loss", "eval_acc"), evaluate(params_of(st), eval_data, eval_weight), strict=True)
        ),
        eval_loss=("eval_loss", "reward/eval_loss"),
        on_chunk=rule.update,
        progress=progress,
        desc=f"reward ({model.kind})",
    )
    out.best, out.best_params, improved = rule.result()
    history = _history(out, batch_size, eval_on, compile_s, steps, companion=companion is not None)
    history.update(best_improved=improved, initial_eval_loss=baseline)
    return jax.device_put(out.best_params), history


def _history(
    out: Any, batch_size: int, eval_on: str, compile_s: float, steps: int, companion: bool = False
) -> dict[str, Any]:
    """The training history :func:`train_reward_model` returns, from the loop's rows and best row
    (with a companion: its metric columns and final state)."""
    history: dict[str, Any] = {"step": loop.column(out.rows, "step")}
    for name, col in (
        ("train_loss", "loss"),
        ("train_acc", "acc"),
        ("eval_loss", "eval_loss"),
        ("eval_acc", "eval_acc"),
    ):
        history[name] = loop.column(out.rows, col)
    history.update(
        best_step=out.best["step"],
        best_eval_loss=out.best["eval_loss"],
        best_eval_acc=out.best["eval_acc"],
        batch_size=batch_size,
        eval_on=eval_on,
        compile_s=compile_s,
        train_s=out.loop_s,
        steps_per_s=steps / out.loop_s,
        steps=steps,
    )
    if companion:
        names = [k for k in out.rows[0] if k not in ("step", "loss", "acc", "eval_loss", "eval_acc")]
        history["companion"] = {k: loop.column(out.rows, k) for k in names}
        history["companion_state"] = jax.device_get(out.state[1])
    return history


def model_fn(
    model: RewardModel, params: Params
) -> Callable[[jax.Array, jax.Array, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]:
    """Trained model as ``f(obs [B, T, o], act [B, T, a], timesteps [B, T], mask [B, T]) -> (r_hat, w)``.

    Deterministic (no dropout) and jitted (compiles once per input shape and model); ``w`` is PT's
    importance weight (column mean of the preference attention), or uniform ``1/T`` over real
    steps for MR.
    """
    return functools.partial(_apply_fn(model), params)


@functools.lru_cache(maxsize=16)
def _apply_fn(model: RewardModel) -> Callable:
    @jax.jit
    def apply(
        params: Params, obs: jax.Array, act: jax.Array, timesteps: jax.Array, mask: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        r_hat, w, _ = model.apply(params, obs, act, timesteps, mask)
        return r_hat, w

    return apply
