"""The `variant` presets (docs/fidelity.md): each row whose variants differ resolves to the value
its source gives, for every variant (only rows whose values differ are listed: a value shared by all
three variants could not fail here; tests/test_fidelity_pins.py pins the behaviour those values
select). The expected values are written here, from the paper, the reference code and the authors'
code (SGPbrl), not read back from spot.config."""

import re
from pathlib import Path

import pytest

from spot import SpotError, config

ROOT = Path(__file__).resolve().parents[1]

# Row of docs/fidelity.md -> {key: (spot, paper, authors)} at method=spot, budget=small, on a
# locomotion dataset (hopper-medium-replay). Only keys whose three values are not all equal.
ROWS = {
    # PT README / SGPbrl hyperparameter.sh --use_human_label True: the PT human files where they exist
    # (labels.source=auto: only for the real D4RL/robomimic file; a locally built dataset gets the teacher)
    2: {"labels.source": ("script", "auto", "auto")},
    # PT README / SGPbrl num_query: 500 for medium-replay (spot: the small budget's 200)
    3: {"labels.query_counts": ("budget", "pt", "pt"), "labels.num_queries": (200, 500, 500)},
    # PT new_preference_reward_main.py: train on all N, evaluate on the last 10 % of them (also row 40)
    7: {"labels.eval_split": ("holdout", "pt_subset", "pt_subset")},
    # PT new_preference_reward_main.py: eval_period 5 epochs, EarlyStopping(min_delta=1e-3), epoch 0 evaluated
    8: {
        "reward.eval_epochs": (0, 5, 5),
        "reward.best_min_delta": (0.0, 1e-3, 1e-3),
        "reward.eval_initial": (False, True, True),
    },
    # PT reward data clip_action 0.999; IQL D4RLDataset clip_to_eps 1e-5
    9: {"reward.clip_action": (0.0, 0.999, 0.999), "iql.clip_action": (0.0, 0.99999, 0.99999)},
    10: {"pt.n_layer": (1, 1, 3), "pt.n_head": (4, 4, 1)},  # Table 5 / SGPbrl get_default_config
    14: {
        "pt.schedule": ("warmup_constant", "warmup_constant", "warmup_cosine"),  # Table 5 / PT repo
        "pt.b2": (0.99, 0.99, 0.999),
        "pt.warmup_fraction": (0.0, 0.0, 0.1),
    },
    # Table 5: 10k steps (reward.steps); SGPbrl --n_epochs 10000 counted as the PT repo does
    15: {"reward.length": ("steps", "steps", "epochs")},
    17: {
        "relabel.mode": ("chunked", "sliding", "sliding"),  # PT repo / SGPbrl seq_len 25
        "relabel.window": (50, 25, 25),
    },  # spot: the small budget's chunk length
    20: {"subgoal.weight": ("column_mean", "column_mean", "diagonal")},
    21: {"subgoal.filter_on": ("r_hat", "r_hat", "z")},
    23: {"subgoal.filter_groups": ("top", "all", "top")},
    24: {"subgoal.selection": ("quantile", "quantile", "authors")},  # a5b03df: sort(w)[int(p T)], first in time
    25: {"subgoal.last_step": (False, False, True)},
    26: {"subgoal.triplets": ("next_subgoal", "next_subgoal", "interval")},
    # SGPbrl a5b03df PrefTransformer.train: one CVAE step per PT step on that minibatch's triplets (also row 29)
    28: {"cvae.schedule": ("offline", "offline", "online")},
    30: {"cvae.loss": ("mse_cos", "mse_cos", "authors")},  # eq. 7 + 8 / SGPbrl a5b03df vae_train_step
    31: {"cvae.inputs": ("zscore", "zscore", "raw")},
    32: {"shaping.subgoal": ("mean", "mean", "sample")},  # SGPbrl: a prior sample (fixed-key noise)
    35: {"shaping.potential_sign": ("neg", "neg", "pos"), "shaping.potential_terminal": (True, True, False)},
    38: {"iql.order": ("parallel", "sequential", "sequential")},
    45: {"cvae.log_std_clip": (True, True, False)},  # subgoal_cvae_model.py: log_var unclipped
    46: {"cvae.holdout": (0.1, 0.0, 0.0)},  # §4.1.3 trains on the triplets
}
# Keys whose override also moves another key (labels.query_counts sets labels.num_queries).
DERIVED = {"labels.query_counts": {"labels.num_queries"}}
VARIANTS = ("spot", "paper", "authors")
CASES = [
    (row, key, v, values[i])
    for row, keys in ROWS.items()
    for key, values in keys.items()
    for i, v in enumerate(VARIANTS)
]


def _flat(*overrides: str) -> dict:
    return config.to_flat(
        config.load(None, ["method=spot", "budget=small", "data.name=hopper-medium-replay", *overrides])
    )


def test_listed_rows_differ_between_variants():
    """The table above lists only keys a variant changes (a row of equal values could not fail)."""
    for row, keys in ROWS.items():
        for key, values in keys.items():
            assert len(set(values)) > 1, (row, key)


@pytest.mark.parametrize("row,key,variant,expected", CASES, ids=[f"{r}-{k}-{v}" for r, k, v, _ in CASES])
def test_variant_resolves_each_row(row, key, variant, expected):
    assert _flat(f"variant={variant}")[key] == expected


def test_each_key_overrides_alone():
    """A sweep can vary one choice on top of a variant: overriding one key changes only that key."""
    base = _flat("variant=authors")
    for keys in ROWS.values():
        for key, (spot_value, _, authors_value) in keys.items():
            if spot_value == authors_value:
                continue
            one = _flat("variant=authors", f"{key}={spot_value}")
            changed = {k for k in base if base[k] != one[k]}
            assert changed == {key} | DERIVED.get(key, set()), (key, changed)


def test_variants_differ_only_in_listed_keys():
    """Nothing outside the matrix's implemented rows changes with the variant."""
    listed = {key for keys in ROWS.values() for key in keys} | {"variant"}
    spot = _flat("variant=spot")
    for variant in ("paper", "authors"):
        other = _flat(f"variant={variant}")
        changed = {k for k in spot if spot[k] != other[k]}
        assert changed <= listed, changed - listed


def test_experiment_era_choices_are_keys_on_top_of_authors():
    """The authors variant follows a5b03df; b6d94e2's loss sign and its 5-seed script's state+action
    shaping are keys a sweep sets on top of it, each changing only itself."""
    base = _flat("variant=authors")
    assert (base["cvae.cos_sign"], base["shaping.state_action"]) == ("minus", False)
    era = _flat("variant=authors", "cvae.cos_sign=plus", "shaping.state_action=true")
    assert {k for k in base if base[k] != era[k]} == {"cvae.cos_sign", "shaping.state_action"}


def test_variant_applies_on_every_budget_and_from_yaml(tmp_path):
    tiny = config.to_flat(config.load(None, ["budget=tiny", "variant=authors"]))
    assert tiny["pt.n_layer"] == 3 and tiny["subgoal.weight"] == "diagonal" and tiny["pt.embd_dim"] == 16
    path = tmp_path / "run.yaml"
    path.write_text("variant: paper\nrelabel:\n  window: 10\n")
    cfg = config.load(path, [])
    assert cfg.variant == "paper" and cfg.relabel.mode == "sliding" and cfg.relabel.window == 10
    assert config.from_flat(config.to_flat(cfg)) == cfg
    with pytest.raises(SpotError, match="variant"):
        config.load(None, ["variant=reference"])


def test_matrix_names_every_implemented_key():
    text = (ROOT / "docs" / "fidelity.md").read_text()
    rows = {int(m.group(1)): m.group(0) for m in re.finditer(r"^\| (\d+) \|.*$", text, re.M)}
    assert len(rows) >= 50 and sorted(rows) == list(range(1, len(rows) + 1))
    for row, keys in ROWS.items():
        for key in keys:
            assert f"`{key}" in rows[row] or key.split(".")[1] in rows[row], (row, key)
    for row, line in rows.items():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        assert len(cells) == 10 and all(cells), (row, cells)  # every column filled


def test_config_show_prints_the_variant(tmp_path):
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "spot.cli", "config", "show", "method=spot", "variant=authors"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert "variant: authors" in out.stdout and "weight: diagonal" in out.stdout
    assert "triplets: interval" in out.stdout and "n_layer: 3" in out.stdout


def test_fidelity_sweep_file_resolves():
    from spot.sweep import spec

    sweep = spec.load(ROOT / "experiments" / "fidelity" / "sweeps" / "fidelity.yaml")
    assert [axes["variant"] for axes in sweep.configs()] == ["spot", "paper", "authors"]
    assert list(sweep.seeds) == [0, 1, 2]


def test_authors_variant_runs_end_to_end(tmp_path, spot_dirs, tiny_drawer, monkeypatch):
    """The authors' subgoal path (diagonal weights, z filter, last step, interval triplets,
    warmup-cosine PT, sliding relabelling, the CVAE trained online: one step per reward-model step)
    trains through to a policy at the tiny budget; a second run that changes only shaping.weight
    reuses the reward stage's entry and the CVAE in it."""
    import mlflow

    from spot import pipeline

    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    cfg = config.load(
        None,
        [
            "method=spot",
            "variant=authors",
            "budget=tiny",
            "data.name=drawer-open",
            "labels.num_queries=30",
            "labels.segment_length=25",
            "pt.n_layer=1",
            f"tracking.uri=sqlite:///{tmp_path / 'mlflow.db'}",
            "tracking.experiment=test",
        ],
    )
    out = pipeline.run(cfg, progress=False)
    mlflow.set_tracking_uri(cfg.tracking.uri)
    run = mlflow.get_run(out["run_id"])
    assert run.info.status == "FINISHED" and run.data.params["variant"] == "authors"
    m = run.data.metrics
    assert cfg.cvae.schedule == "online" and m["cvae/steps"] == m["reward/steps"] > 0
    assert (
        "spot.cache.cvae" not in run.data.tags and run.data.tags["spot.cache.reward"] == "miss"
    )  # no CVAE entry of its own
    again = mlflow.get_run(pipeline.run(config.replace(cfg, **{"shaping.weight": 0.5}), progress=False)["run_id"])
    assert again.data.tags["spot.cache.reward"] == "hit" and again.data.metrics["cvae/loss"] == m["cvae/loss"]
    assert again.data.metrics["shaping/r_shape_mean"] == m["shaping/r_shape_mean"]  # the same CVAE
    # the online CVAE trained on its minibatches' own triplets: per step at most one per interval,
    # i.e. per preferred segment at most its 3 top-group steps (25 - int(0.9 x 25)), the last step and
    # step 0 as an interval start; the offline extraction below feeds the diagnostics only
    assert 0 < m["cvae/triplets"] <= 4 * cfg.reward.batch_size
    assert m["subgoal/num_triplets"] > 0 and m["subgoal/num_triplets"] % 10 == 0  # interval_draws 10
    assert m["subgoal/num_subgoals"] >= m["subgoal/num_segments"]  # the last step is a subgoal
    assert "eval/score_final" in m


# --------------------------------------------------------------------------- rows 2, 3, 7/40, 9, 15
def test_query_counts_per_dataset_and_override_wins():
    def queries(*overrides):
        return _flat(*overrides)["labels.num_queries"]

    assert queries("variant=paper", "data.name=hopper-medium-expert") == 100  # PT README: medium-expert
    assert queries("variant=authors", "data.name=walker2d-medium-replay") == 500
    assert queries("variant=paper", "data.name=drawer-open") == 200  # no PT count: the budget's
    assert queries("variant=paper", "data.name=/data/d4rl/hopper_medium_expert-v2.hdf5", "data.source=file") == 100
    assert queries("variant=paper", "data.name=hopper-medium-expert", "labels.num_queries=30") == 30  # Table 4
    assert queries("variant=spot", "data.name=hopper-medium-expert") == 200


def _prefs(q: int):
    import numpy as np

    from spot.data.labels import Preferences

    return Preferences(np.arange(q) * 3, np.arange(q) * 3 + 1, np.zeros(q, np.float32), 2, "test")


def test_eval_split_pt_subset_trains_on_all_and_evaluates_on_the_last_tenth():
    import numpy as np

    from spot.run import label_stages

    prefs = _prefs(30)
    train, held = label_stages.split_queries(prefs, config.load(None, ["variant=paper", "labels.eval_fraction=0.1"]))
    np.testing.assert_array_equal(train.starts_1, prefs.starts_1)  # all N
    np.testing.assert_array_equal(held.starts_1, [81, 84, 87])  # queries 27, 28, 29
    train, held = label_stages.split_queries(prefs, config.load(None, ["variant=spot"]))
    assert len(train) == 27 and len(held) == 3 and not set(train.starts_1) & set(held.starts_1)
    assert len(label_stages.pt_eval_subset(_prefs(5), 0.1)) == 1  # at least one
    assert len(label_stages.pt_eval_subset(_prefs(5), 0.0)) == 0


def test_reward_training_length_in_pt_epochs():
    from spot.reward import train

    def steps(n, **kw):
        return train.training_steps(config.RewardConfig(**kw), n)

    # PT repo: 10000 epochs x (floor(N / 256) + 1) steps: 10k steps at N = 100, 20k at N = 500
    assert steps(100, length="epochs", epochs=10_000) == 10_000
    assert steps(500, length="epochs", epochs=10_000) == 20_000
    assert steps(200, length="epochs", epochs=43, batch_size=32) == 43 * 7
    assert steps(500, length="steps", steps=123) == 123


def test_action_clipping_by_hand(tiny_drawer):
    import numpy as np

    from spot.data import registry
    from spot.reward import train
    from spot.run import policy_stages

    batch = {"act_1": np.array([[[1.0, -1.0, 0.5]]]), "act_2": np.array([[[-0.9995, 0.9995, 0.0]]]), "x": 1}
    out = train.clip_actions(batch, 0.999)
    np.testing.assert_array_equal(out["act_1"], [[[0.999, -0.999, 0.5]]])
    np.testing.assert_array_equal(out["act_2"], [[[-0.999, 0.999, 0.0]]])
    assert train.clip_actions(batch, 0.0) is batch and train.clip_actions(None, 0.999) is None

    ds, _ = registry.load("drawer-open", "tiny")
    reward = np.zeros(len(ds), np.float32)
    cfg = config.load(None, ["variant=paper"])
    data = policy_stages.policy_transitions(cfg, ds, reward)
    eps = 1e-5
    assert np.abs(data.act).max() <= 1 - eps + 1e-7
    np.testing.assert_allclose(data.act, np.clip(ds.actions, -(1 - eps), 1 - eps), rtol=0, atol=1e-7)
    unclipped = policy_stages.policy_transitions(config.load(None, ["variant=spot"]), ds, reward)
    np.testing.assert_array_equal(unclipped.act, ds.actions.astype(np.float32))


# --------------------------------------------------------------------------- row 2: human labels
# The PT repo's human_label/ files at f71647b, shipped unchanged (PROVENANCE.md)
SHIPPED = ROOT / "spot" / "data" / "pt_human_labels"


def test_human_label_folder_only_for_the_real_file():
    from spot.run import label_stages

    real = {"source": "file", "name": "hopper_medium_replay-v2", "path": "/d/d4rl/hopper_medium_replay-v2.hdf5"}
    assert label_stages.human_label_folder(real) == SHIPPED / "hopper-medium-replay-v2"
    robomimic = {"source": "file", "name": "low_dim", "path": "/d/robomimic/can/mh/low_dim.hdf5"}
    assert label_stages.human_label_folder(robomimic) == SHIPPED / "Can_mh"
    # a spot-built dataset, read by path or by name: its card names the recipe
    built = {"source": "file", "recipe": "d4rl-sac-locomotion", "path": "/d/hopper_medium_replay-v2.hdf5"}
    assert label_stages.human_label_folder(built) is None
    assert label_stages.human_label_folder({"source": "recipe", "recipe": "x", "name": "hopper-medium-replay"}) is None
    assert label_stages.human_label_folder({"source": "file", "path": "/d/hopper_medium-v2.hdf5"}) is None  # no labels
    cfg = config.load(None, ["variant=authors"])
    assert label_stages.label_source(cfg, real) == ("human", str(SHIPPED / "hopper-medium-replay-v2"))
    assert label_stages.label_source(cfg, built) == ("script", "")
    assert label_stages.label_source(config.load(None, ["variant=spot"]), real) == ("script", "")


@pytest.mark.parametrize(
    "folder,queries,length",
    [
        ("hopper-medium-replay-v2", 500, 100),
        ("hopper-medium-expert-v2", 100, 100),
        ("walker2d-medium-replay-v2", 500, 100),
        ("walker2d-medium-expert-v2", 100, 100),
        ("Lift_ph", 100, 50),
        ("Can_mh", 500, 100),
    ],
)
def test_shipped_human_labels_read_safely(folder, queries, length):
    """The shipped files go through spot's restricted unpickler, with PT's counts (PROVENANCE.md);
    the query preset gives the same counts for the matching datasets."""
    import numpy as np

    from spot.data import labels

    prefs = labels.read_pt_labels(SHIPPED / folder)
    assert len(prefs) == queries and prefs.segment_length == length
    assert set(np.unique(prefs.labels)) <= {0.0, 0.5, 1.0} and len(np.unique(prefs.labels)) >= 2
    if folder.endswith("-v2"):
        assert config.pt_query_count(folder) == queries


def test_shipped_human_labels_are_package_data():
    text = (ROOT / "pyproject.toml").read_text()
    assert "data/pt_human_labels/*/*" in text
    names = sorted(p.parent.name for p in SHIPPED.glob("*/label_human"))
    assert len(names) == 8 and (SHIPPED / "PROVENANCE.md").is_file()


# --------------------------------------------------------------------------- row 41: HPL's own IQL
# WiseRL scripts/configs/hpl/tuned/*: batch 512, 3x256, squashed Gaussian, state-dependent log-std in
# [-7, 2]; the sizes at budget paper only (presets set no sizes below it).
HPL_ROW = {
    "iql.actor_std": ("state_independent", "state_dependent", "state_dependent"),
    "iql.log_std_min": (-5.0, -7.0, -7.0),
    "iql.actor_dist": ("gaussian", "tanh_gaussian", "tanh_gaussian"),
}


@pytest.mark.parametrize("variant", VARIANTS)
def test_hpl_iql_settings_per_variant(variant):
    i = VARIANTS.index(variant)
    for budget, sizes in (("paper", (512, (256, 256, 256))), ("small", (256, (256, 256)))):
        flat = config.to_flat(
            config.load(
                None, ["method=hpl", f"budget={budget}", "data.name=hopper-medium-replay", f"variant={variant}"]
            )
        )
        for key, values in HPL_ROW.items():
            assert flat[key] == values[i], (key, budget)
        want = sizes if variant != "spot" else (256, (256, 256))
        assert (flat["iql.batch_size"], flat["iql.hidden"]) == want, budget
    spot_run = _flat(f"variant={variant}")  # other methods keep the reference IQL actor
    assert spot_run["iql.actor_std"] == "state_independent" and spot_run["iql.actor_dist"] == "gaussian"


# --------------------------------------------------------------------------- row 39: actor dropout
@pytest.mark.parametrize("variant", VARIANTS)
def test_actor_dropout_on_robomimic_only(variant):
    """PT repo adroit/robomimic configs and IPL's robomimic configs: actor dropout 0.1."""
    want = 0.0 if variant == "spot" else 0.1
    for name, expected in (
        ("lift-ph", want),
        ("can-mh", want),
        ("/d/robomimic/lift/ph/low_dim.hdf5", want),
        ("hopper-medium-replay", 0.0),
        ("drawer-open", 0.0),
    ):
        for method in ("pt", "ipl"):
            flat = config.to_flat(config.load(None, [f"method={method}", f"variant={variant}", f"data.name={name}"]))
            assert flat["iql.actor_dropout"] == expected, (name, method)


def test_auto_labels_are_the_human_files_only_on_the_real_file():
    """labels.source=auto (paper/authors): the shipped PT human queries for the real
    hopper-medium-replay-v2 file; the scripted teacher for a spot-built dataset of the same name."""
    import numpy as np

    from spot.data import labels
    from spot.run import label_stages
    from tests.conftest import make_dataset

    ds = make_dataset([1000] * 402, obs_dim=2, act_dim=1)  # rows past PT's largest index (401337 + 100)
    cfg = config.load(None, ["method=pt", "variant=paper", "data.name=hopper-medium-replay"])
    assert cfg.labels.num_queries == 500 and cfg.labels.source == "auto"
    real = {"source": "file", "name": "hopper_medium_replay-v2", "path": "/d/d4rl/hopper_medium_replay-v2.hdf5"}
    prefs = label_stages.make_preferences(cfg, ds, real)
    shipped = labels.read_pt_labels(SHIPPED / "hopper-medium-replay-v2")
    np.testing.assert_array_equal(prefs.starts_1, shipped.starts_1)
    np.testing.assert_array_equal(prefs.labels, shipped.labels)
    assert prefs.segment_length == 100 and prefs.source == str(SHIPPED / "hopper-medium-replay-v2")
    built = {**real, "recipe": "d4rl-sac-locomotion"}
    scripted = label_stages.make_preferences(cfg, ds, built)
    assert len(scripted) == 500 and scripted.segment_length == cfg.labels.segment_length
    assert not np.array_equal(scripted.starts_1, shipped.starts_1)
