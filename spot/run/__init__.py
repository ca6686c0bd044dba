"""One run of a method: its stages, their typed outputs, the table that picks them per method.

A run is ``labels -> reward -> relabel -> [subgoals -> cvae -> shaping -> diagnostics] -> policy``
(docs/design.md draws it). Each stage is a function ``stage(ctx, *inputs) -> output`` over a
:class:`~spot.run.context.Context` (config, dataset, keys, tracker, stage cache) and the typed
outputs of earlier stages. ``Context.stage`` wraps every stage the same way: it times it
(``time/<stage>_s``) and the stage's expensive part goes through ``Context.cached``, which tags the
run ``spot.cache.<stage> = hit | miss``. The trained models are saved as run artifacts
(``models/reward_model``, ``models/cvae``, ``models/policy``, data only, with a JSON header), so a
run can be evaluated again (``spot eval``) without the stage cache. Which functions fill the
reward, relabel and policy slots is read from :data:`spot.run.methods.REWARD_KINDS` by
``reward.kind`` (set by the method preset); adding a method is one ``register`` call plus the
module with its stage functions.

The modules, by role:

- :mod:`spot.run.context`: the Context, the typed slot outputs (Labelled, RewardModel, Rewards,
  Subgoals, Shaped, Policy) and the helpers every stage uses (``save_model``, ``untimed``,
  ``dataset_deps``);
- :mod:`spot.run.label_stages`, :mod:`spot.run.reward_stages` (reward and relabel slots),
  :mod:`spot.run.subgoal_stages` (subgoals, CVAE, shaping, diagnostics),
  :mod:`spot.run.policy_stages` (IQL, IPL, the evaluation helpers): the stage functions by slot;
- :mod:`spot.run.methods`: ``RewardKind``, ``REWARD_KINDS``, ``register``, ``load_plugins``;
- :mod:`spot.run.finish`: the learning curve, ``models/policy`` and the final metrics;
- :mod:`spot.run.pipeline`: ``run``, the data flow, and ``evaluate_run`` (``spot eval``);
- :mod:`spot.run.multiseed`: several seeds (or methods) with IQL as one vmapped program.

:mod:`spot.stages` (the method-plugin API) and :mod:`spot.pipeline` (``run``, the public entry
point) re-export what users and plugins call.

Where normalisation sits: the reward model's per-step output is relabelled over the whole dataset,
normalised (``relabel.normalize``), and only then is the shaping term added,
``r = norm(r_model) + λ r_shape`` (eq. 13), so that λ = 1 adds a bonus in [0, 1] beside a reward of
the scale IQL's hyperparameters expect.
"""
