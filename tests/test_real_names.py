"""Real D4RL and robomimic file names resolve to their datasets (issue 43, finding 5).

The names are not copied from the code: they come from the fetch registry (``spot/data/sources.json``,
what ``spot data fetch`` writes: ``d4rl/hopper_medium_replay-v2.hdf5``, ``robomimic/lift/ph/low_dim.hdf5``)
and the PT label folders it pairs them with. Files in those layouts are built here (the real ones
are not downloaded), read through ``spot.data.registry.load``, their PT human labels looked up,
and one tiny ``spot run`` of the README's quickstart config runs on ``hopper_medium_replay-v2.hdf5``
to FINISHED.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import mlflow
import numpy as np
import pytest

from spot import SpotError, cli, config, envs
from spot.data import fetch, labels, registry
from spot.run import label_stages

ROOT = Path(__file__).resolve().parents[1]
SOURCES = fetch.load_registry()
DATA_SOURCES = [s for s in SOURCES.values() if s.kind in ("d4rl", "robomimic")]
HOPPER_MR = "d4rl/hopper_medium_replay-v2.hdf5"  # the path sources.json gives D4RL's file


def _hopper_d4rl(path: Path, n: int = 1000, episode: int = 100, seed: int = 0) -> Path:
    """A file in D4RL's real layout (no spot card): float32 arrays, bool flags, ``infos/`` and a
    ``metadata/`` group with a string and policy weights, Hopper's sizes (11-D observations, 3-D
    actions in [-1, 1]); observations a bounded random walk and the reward a noisy function of them
    (as scripts/make_synthetic_d4rl.py), ``episode``-step episodes ending in a timeout."""
    rng = np.random.default_rng(seed)
    obs = np.cumsum(rng.normal(scale=0.05, size=(n, 11)), axis=0).astype(np.float32) % 3.0
    timeouts = np.zeros(n, bool)
    timeouts[episode - 1 :: episode] = True
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        f["observations"] = obs
        f["next_observations"] = np.roll(obs, -1, axis=0)
        f["actions"] = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
        f["rewards"] = (obs[:, 5] + 0.1 * rng.normal(size=n)).astype(np.float32)
        f["terminals"] = np.zeros(n, bool)
        f["timeouts"] = timeouts
        f["infos/qpos"] = rng.normal(size=(n, 6)).astype(np.float32)
        f["infos/qvel"] = rng.normal(size=(n, 6)).astype(np.float32)
        f["metadata/algorithm"] = np.bytes_("SAC")
        f["metadata/policy/fc0/weight"] = rng.normal(size=(256, 11)).astype(np.float32)
    return path


_ROBOT_DIMS = (7, 7, 7, 7, 3, 4, 2, 2)  # robot0_* keys of ROBOMIMIC_OBS_KEYS, after "object"
_OBJECT_DIM = {"Lift": 10, "PickPlaceCan": 14}  # robomimic low_dim: Lift 49-D, Can 53-D


def _robomimic(path: Path, env_name: str = "Lift", demos: int = 3, steps: int = 6) -> Path:
    """A file in robomimic's low_dim layout: ``data/demo_N/{obs,next_obs}/<key>``, actions in
    [-1, 1], rewards, dones and ``data.attrs['env_args']``."""
    from spot.data.formats import ROBOMIMIC_OBS_KEYS

    rng = np.random.default_rng(1)
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = json.dumps({"env_name": env_name, "type": 1, "env_kwargs": {}})
        for d in range(demos):
            demo = data.create_group(f"demo_{d}")
            for key, dim in zip(ROBOMIMIC_OBS_KEYS, (_OBJECT_DIM[env_name], *_ROBOT_DIMS), strict=True):
                value = rng.normal(size=(steps + 1, dim))
                demo[f"obs/{key}"] = value[:-1]
                demo[f"next_obs/{key}"] = value[1:]
            demo["actions"] = rng.uniform(-1, 1, (steps, 7))
            demo["rewards"] = np.r_[np.zeros(steps - 1), 1.0]
            demo["dones"] = np.r_[np.zeros(steps - 1, np.int64), 1]
    return path


# ------------------------------------------------------------------ names of every fetched file
@pytest.mark.parametrize("source", DATA_SOURCES, ids=[s.name for s in DATA_SOURCES])
def test_every_fetched_file_name_resolves_to_its_dataset(tmp_path, source):
    """The dataset each file of the fetch registry is (the source's name after its kind) comes back
    from the file's path under the fetch destination, with its evaluation env and PT labels."""
    want = source.name.split("/", 1)[1]  # d4rl/hopper-medium-replay-v2 -> hopper-medium-replay-v2
    (file,) = source.files
    path = tmp_path / "real" / file.path
    assert registry.file_dataset_name(path) == want
    spec = envs.env_spec(want)
    env = want.split("-")[0]
    assert (
        spec.env_id
        == {
            "hopper": "Hopper-v5",
            "walker2d": "Walker2d-v5",
            "lift": "Lift",
            "can": "PickPlaceCan",
        }[env]
    )
    label_folder = labels.pt_label_folder(want, label_stages.PT_HUMAN_LABELS)
    if source.labels:  # the PT label source the fetch registry pairs with this file
        assert labels.pt_label_name(want) == source.labels.split("/", 1)[1]
        assert label_folder == label_stages.PT_HUMAN_LABELS / source.labels.split("/", 1)[1]
    else:
        assert label_folder is None


def test_d4rl_file_stems_are_accepted_as_names_and_other_files_are_not():
    assert envs.env_spec("hopper_medium_replay-v2").name == "hopper-medium-replay"
    assert envs.env_spec("walker2d_medium_expert-v2").env_id == "Walker2d-v5"
    assert registry.canonical("hopper_full_replay-v2") == "hopper-full-replay"
    assert registry.file_dataset_name("/x/hopper-medium-replay-v2.hdf5") == "hopper-medium-replay-v2"
    assert registry.file_dataset_name("/x/Lift/PH/low_dim_v15.hdf5") == "lift-ph"
    for other in ("/x/low_dim.hdf5", "/x/lift/mg/low_dim.hdf5", "/x/square/ph/low_dim.hdf5", "/x/data.hdf5"):
        assert registry.file_dataset_name(other) is None, other
    with pytest.raises(SpotError, match="unknown dataset name 'low_dim'.*robomimic's <task>/<ph\\|mh>/low_dim.hdf5"):
        envs.env_spec("low_dim")
    # spot's own locally built datasets are not the files PT's indices point into
    assert labels.pt_label_name("hopper-medium-replay") is None
    assert labels.pt_label_name("hopper_medium_replay-v2") == "hopper-medium-replay-v2"


# ------------------------------------------------------------------ files in the real layouts
def test_a_d4rl_file_under_its_real_name_loads_as_that_dataset(tmp_path):
    path = _hopper_d4rl(tmp_path / "real" / HOPPER_MR)
    ds, card = registry.load(str(path))
    assert card["name"] == ds.name == "hopper-medium-replay-v2" and card["source"] == "file"
    assert card["path"] == str(path.resolve())
    envs.check_fits_env(ds, card, card["name"])  # Hopper-v5's sizes and action space
    shipped = label_stages.PT_HUMAN_LABELS / "hopper-medium-replay-v2"
    assert label_stages.human_label_folder(card) == shipped
    cfg = config.load(ROOT / "configs" / "quickstart.yaml", [f"data.name={path}", "labels.source=auto"])
    assert label_stages.label_source(cfg, card) == ("human", str(shipped))
    # PT's 500 human queries index the real 402,000 rows; this 1,000-row stand-in is refused clearly
    with pytest.raises(SpotError, match="past the end of dataset 'hopper-medium-replay-v2'"):
        label_stages.make_preferences(cfg, ds, card)


@pytest.mark.parametrize("task, kind, env_name", [("lift", "ph", "Lift"), ("can", "mh", "PickPlaceCan")])
def test_a_robomimic_file_resolves_from_its_folders(tmp_path, task, kind, env_name):
    path = _robomimic(tmp_path / "real" / "robomimic" / task / kind / "low_dim.hdf5", env_name)
    raw, card = registry.load_raw(str(path))
    assert card["name"] == f"{task}-{kind}" and raw.metadata["format"] == "robomimic"
    assert envs.env_spec(card["name"]).env_id == env_name
    pt = {"lift-ph": "Lift_ph", "can-mh": "Can_mh"}[card["name"]]
    shipped = label_stages.PT_HUMAN_LABELS / pt
    assert label_stages.human_label_folder(card) == shipped
    assert label_stages.human_label_folder({**card, "name": "low_dim"}) == shipped  # by path too


def test_a_robomimic_file_under_another_tasks_folder_is_refused(tmp_path):
    path = _robomimic(tmp_path / "real" / "robomimic" / "lift" / "ph" / "low_dim.hdf5", env_name="PickPlaceCan")
    with pytest.raises(SpotError, match=r"names env 'PickPlaceCan'; expected 'Lift' for a file under lift/ph/"):
        registry.load_raw(str(path))


def test_the_documented_real_data_command_runs_to_finished(tmp_path, monkeypatch, capsys):
    """docs/datasets.md's `spot run configs/quickstart.yaml data.name=$SPOT_DATA_DIR/real/d4rl/
    hopper_medium_replay-v2.hdf5` on a file built here under that name, at a tiny size."""
    monkeypatch.setenv("SPOT_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    path = _hopper_d4rl(tmp_path / "data" / "real" / HOPPER_MR)
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    argv = [
        "run",
        str(ROOT / "configs" / "quickstart.yaml"),
        f"data.name={path}",
        "budget=tiny",
        "iql.steps=200",
        "eval.every=100",
        "eval.episodes=1",
        "eval.max_steps=50",
        "labels.num_queries=30",
        "labels.segment_length=25",
        f"tracking.uri={uri}",
        "--quiet",
    ]
    rc = cli.main(argv)
    out, err = capsys.readouterr()
    assert rc == 0, err
    run_id = out.split()[1].rstrip(":")
    run = mlflow.tracking.MlflowClient(uri).get_run(run_id)
    assert run.info.status == "FINISHED"
    assert run.data.tags["dataset"] == "hopper-medium-replay-v2" and run.data.tags["spot.dataset_source"] == "file"
    assert np.isfinite(run.data.metrics["eval/score_final"])
