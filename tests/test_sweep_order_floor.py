"""Issue 40, items 2 and 3: the order a sweep's trials start in (spot.sweep.order) and the floor
that ``spot bench sweep`` prints each phase's ratio to (spot.sweep.floor). No trial runs here."""

import pytest

from spot import config as config_lib
from spot import sweep
from spot.sweep import floor, order
from spot.sweep.spec import run_key
from spot.sweep.summary import PHASE_COLUMNS, Row

BASE = """
base:
  budget: small
  data: {name: hopper-medium-replay, size: small}
  labels: {source: script}
  iql: {steps: 10000}
  reward: {steps: 400}
"""


def load(tmp_path, grid: str, seeds: str = "[0]"):
    path = tmp_path / "s.yaml"
    path.write_text(f"name: s{BASE}grid:\n  method: {grid}\nseeds: {seeds}\nresources: {{cpu: 1, gpu: 0}}\n")
    return sweep.load(str(path))


def methods(trials) -> list[tuple[str, tuple[int, ...]]]:
    return [(t.axes["method"], t.seeds) for t in trials]


def test_spot_reuses_pts_reward_model_and_oracle_none():
    cfg = {m: config_lib.resolve({"method": m, "budget": "small"}, {"seed": 0}) for m in ("oracle", "pt", "spot", "mr")}
    assert order.reward_identity(cfg["oracle"]) is None
    assert order.reward_identity(cfg["pt"]) == order.reward_identity(cfg["spot"]) is not None
    assert order.reward_identity(cfg["mr"]) not in (None, order.reward_identity(cfg["pt"]))
    other_seed = config_lib.resolve({"method": "spot", "budget": "small"}, {"seed": 1})
    assert order.reward_identity(other_seed) != order.reward_identity(cfg["spot"])


def test_the_quickstart_starts_pt_beside_oracle_and_spot_last(tmp_path):
    spec = load(tmp_path, "[oracle, pt, spot]", "[0, 1]")
    grid = spec.trials()
    assert methods(grid) == [
        ("oracle", (0,)),
        ("pt", (0,)),
        ("spot", (0,)),
        ("oracle", (1,)),
        ("pt", (1,)),
        ("spot", (1,)),
    ]
    ordered = order.trial_order(grid)
    assert methods(ordered) == [
        ("pt", (0,)),
        ("pt", (1,)),
        ("oracle", (0,)),
        ("oracle", (1,)),
        ("spot", (0,)),
        ("spot", (1,)),
    ]
    # only the order changes: the same trials (configs, seeds) and so the same run keys
    assert sorted(str(t.to_config()) for t in ordered) == sorted(str(t.to_config()) for t in grid)


def test_the_first_user_of_a_shared_model_trains_it_and_unshared_trials_keep_their_order(tmp_path):
    assert methods(order.trial_order(load(tmp_path, "[spot, oracle, pt]").trials())) == [
        ("spot", (0,)),
        ("oracle", (0,)),
        ("pt", (0,)),
    ]
    assert methods(order.trial_order(load(tmp_path, "[mr, oracle, pt]").trials())) == [
        ("mr", (0,)),
        ("oracle", (0,)),
        ("pt", (0,)),
    ]


def timing(values: tuple[float, ...], cpus: float) -> dict[str, float]:
    t = {f"time/trial_{p}_s": float(v) for p, v in zip(PHASE_COLUMNS, values, strict=True)}
    return {**t, "time/trial_wall_s": sum(values), "time/trial_cpus": cpus}


def rows_of(spec, timings: dict[str, dict[str, float]]) -> list[Row]:
    out = []
    for trial, seed in spec.runs():
        m = trial.axes["method"]
        out.append(Row(trial.axes, seed, run_key(trial.overrides, seed), "FINISHED", 1.0, "", m, 1, m, timings[m]))
    return out


def test_floor_and_each_phases_ratio_by_hand(tmp_path):
    spec = load(tmp_path, "[oracle, pt, spot]")
    # per phase (startup, data, compile, train, evaluate, tracking, other) and the CPUs each trial had
    rows = rows_of(
        spec,
        {
            "oracle": timing((4, 1, 15, 90, 1, 2, 1), 1.0),  # 114 s
            "pt": timing((4, 1, 29, 106, 1, 2, 1), 1.0),  # 144 s
            "spot": timing((0, 0, 1, 60, 1, 2, 0), 1.5),  # 64 s on 1.5 CPUs on average: 96 core-seconds
        },
    )
    work = floor.work_of(spec, rows)
    # 3 runs x 10,000 IQL updates; PT and SPOT share one reward model of 400 steps
    assert (work.iql_updates, work.reward_steps, work.reward_models, work.approximate) == (30_000, 400, 1, False)
    rates = floor.Rates(iql_per_s=250.0, reward_per_s=40.0, how="given")
    assert floor.floor_s(work, rates) == pytest.approx(30_000 / 250 + 400 / 40)  # 120 + 10 = 130 s
    r = floor.ratios(rows, 130.0, wall_s=200.0, cores=2)  # the floor's core-seconds: 260
    assert r["train"] == pytest.approx((90 + 106 + 60 * 1.5) / 260)  # 286 / 260 = 1.1
    assert r["compile"] == pytest.approx((15 + 29 + 1 * 1.5) / 260)
    assert r["startup"] == pytest.approx(8 / 260) and r["data"] == pytest.approx(2 / 260)
    assert r["outside"] == pytest.approx((400 - (114 + 144 + 96)) / 260)  # 46 core-seconds outside the trials
    assert r["total"] == pytest.approx(200 / 130)
    assert sum(r[p] for p in (*PHASE_COLUMNS, "outside")) == pytest.approx(r["total"])
    text = floor.format_floor(work, rates, rows, 200.0, 2)
    assert text.splitlines()[0] == (
        "floor: 30,000 IQL updates at 250 updates/s + 400 reward-model steps (1 model) at 40.0 steps/s "
        "= 130.0 s on 2 cores (rates given)"
    )
    assert (
        "train 1.10x" in text
        and "outside 0.18x" in text
        and text.splitlines()[1].endswith("= 1.54x (200.0 s / 130.0 s)")
    )


def test_runs_found_finished_do_not_count(tmp_path):
    spec = load(tmp_path, "[oracle, pt, spot]")
    rows = rows_of(spec, {m: timing((0, 0, 0, 10, 0, 0, 0), 1.0) for m in ("oracle", "pt", "spot")})
    rows = [r if r.axes["method"] != "pt" else Row(r.axes, r.seed, r.key, "FINISHED", 1.0, "", "x", 1) for r in rows]
    work = floor.work_of(spec, rows)  # PT's run was found finished: SPOT trained the reward model
    assert (work.iql_updates, work.reward_steps, work.reward_models) == (20_000, 400, 1)
    only_oracle = [
        r if r.axes["method"] == "oracle" else Row(r.axes, r.seed, r.key, "FINISHED", 1.0, "", "x", 1) for r in rows
    ]
    assert (floor.work_of(spec, only_oracle).reward_steps, floor.work_of(spec, only_oracle).reward_cfg) == (0, None)


def test_datasets_of_one_environment_do_not_start_together(tmp_path):
    # hopper's two datasets compile the same programs: the second waits for walker2d's first
    path = tmp_path / "s.yaml"
    path.write_text(
        "name: s\nbase: {budget: tiny, data.size: tiny}\n"
        "zip:\n  data.name: [hopper-medium-replay, hopper-medium-expert, walker2d-medium-replay]\n"
        "grid:\n  method: [pt, oracle]\nseeds: [0, 1]\nresources: {cpu: 1, gpu: 0}\n"
    )
    grid = sweep.load(str(path)).trials()
    short = {"hopper-medium-replay": "hr", "hopper-medium-expert": "he", "walker2d-medium-replay": "wr"}
    named = [(t.axes["method"], short[t.axes["data.name"]], t.seeds[0]) for t in grid]
    assert named[:3] == [("pt", "hr", 0), ("pt", "he", 0), ("pt", "wr", 0)]  # the grid: hopper's two together
    ordered = [named[grid.index(t)] for t in order.trial_order(grid)]
    assert ordered == [  # no trial here reuses another's reward model: one group
        ("pt", "hr", 0), ("pt", "wr", 0), ("oracle", "hr", 0), ("oracle", "wr", 0),
        ("pt", "he", 0), ("oracle", "he", 0),
        ("pt", "hr", 1), ("pt", "he", 1), ("pt", "wr", 1),
        ("oracle", "hr", 1), ("oracle", "he", 1), ("oracle", "wr", 1),
    ]  # fmt: skip


def test_program_identity_names_the_environment_not_the_dataset():
    def ident(**kw):
        return order.program_identity(
            config_lib.resolve({"method": "pt", "budget": "tiny", **kw}, {"seed": kw.pop("seed", 0)})
        )

    hopper = ident(**{"data.name": "hopper-medium-replay"})
    assert (
        ident(**{"data.name": "hopper-medium-expert"})
        == hopper
        == ident(**{"data.name": "hopper-medium-replay", "seed": 3})
    )
    assert ident(**{"data.name": "walker2d-medium-replay"}) != hopper
    assert ident(**{"data.name": "hopper-medium-replay", "labels.num_queries": 7}) != hopper  # other label shapes
    assert ident(**{"data.name": "lift-mh"}) == ident(**{"data.name": "lift-ph"})
