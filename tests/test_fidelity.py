"""The `variant` presets (docs/fidelity.md): each implemented row of the fidelity matrix resolves to
the value its source gives, for every variant. The expected values are written here, from the
paper, the reference code and the authors' code (SGPbrl), not read back from spot.config."""

import re
from pathlib import Path

import pytest

from spot import SpotError, config

ROOT = Path(__file__).resolve().parents[1]

# Row of docs/fidelity.md -> {key: (spot, paper, authors)} at method=spot, budget=small, on a
# locomotion dataset (hopper-medium-replay).
ROWS = {
    10: {"pt.n_layer": (1, 1, 3), "pt.n_head": (4, 4, 1)},  # Table 5 / SGPbrl get_default_config
    14: {
        "pt.schedule": ("warmup_constant", "warmup_constant", "warmup_cosine"),  # Table 5 / PT repo
        "pt.peak_factor": (10.0, 10.0, 10.0),
        "pt.b2": (0.99, 0.99, 0.999),
        "pt.warmup_fraction": (0.0, 0.0, 0.1),
    },
    17: {
        "relabel.mode": ("chunked", "sliding", "sliding"),  # PT repo / SGPbrl seq_len 25
        "relabel.window": (50, 25, 25),
    },  # spot: the small budget's chunk length
    20: {"subgoal.weight": ("column_mean", "column_mean", "diagonal")},
    21: {"subgoal.filter_on": ("r_hat", "r_hat", "z")},
    22: {"subgoal.reward_filter": (True, True, True)},
    23: {"subgoal.filter_groups": ("top", "all", "top")},
    25: {"subgoal.last_step": (False, False, True)},
    26: {"subgoal.triplets": ("next_subgoal", "next_subgoal", "interval"), "subgoal.interval_draws": (10, 10, 10)},
    30: {"cvae.loss": ("mse_cos", "mse_cos", "authors")},  # eq. 7 + 8 / SGPbrl vae_train_step
    31: {"cvae.inputs": ("zscore", "zscore", "raw")},
    32: {"shaping.subgoal": ("mean", "mean", "sample")},  # SGPbrl: a prior sample (fixed-key noise)
    33: {"shaping.kind": ("cosine", "cosine", "cosine")},  # state-only cosine on s'
    34: {"shaping.weight": (1.0, 1.0, 1.0)},
    35: {"shaping.potential_sign": ("neg", "neg", "pos"), "shaping.potential_terminal": (True, True, False)},
    38: {"iql.order": ("parallel", "sequential", "sequential")},
}
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


@pytest.mark.parametrize("row,key,variant,expected", CASES, ids=[f"{r}-{k}-{v}" for r, k, v, _ in CASES])
def test_variant_resolves_each_row(row, key, variant, expected):
    assert _flat(f"variant={variant}")[key] == expected


def test_default_variant_is_spot_and_spot_is_the_defaults():
    assert _flat()["variant"] == "spot"
    assert _flat() == _flat("variant=spot")


def test_each_key_overrides_alone():
    """A sweep can vary one choice on top of a variant: overriding one key changes only that key."""
    base = _flat("variant=authors")
    for keys in ROWS.values():
        for key, (spot_value, _, authors_value) in keys.items():
            if spot_value == authors_value:
                continue
            one = _flat("variant=authors", f"{key}={spot_value}")
            changed = {k for k in base if base[k] != one[k]}
            assert changed == {key}, (key, changed)


def test_variants_differ_only_in_listed_keys():
    """Nothing outside the matrix's implemented rows changes with the variant."""
    listed = {key for keys in ROWS.values() for key in keys} | {"variant"}
    spot = _flat("variant=spot")
    for variant in ("paper", "authors"):
        other = _flat(f"variant={variant}")
        changed = {k for k in spot if spot[k] != other[k]}
        assert changed <= listed, changed - listed


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
    assert len(rows) >= 40 and sorted(rows) == list(range(1, len(rows) + 1))
    for row, keys in ROWS.items():
        for key in keys:
            assert f"`{key}" in rows[row] or key.split(".")[1] in rows[row], (row, key)
    for row, line in rows.items():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        assert len(cells) == 8 and all(cells), (row, cells)  # every column filled


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

    sweep = spec.load(ROOT / "sweeps" / "fidelity.yaml")
    assert [axes["variant"] for axes in sweep.configs()] == ["spot", "paper", "authors"]
    assert list(sweep.seeds) == [0, 1, 2]


def test_authors_variant_runs_end_to_end(tmp_path, spot_dirs, tiny_drawer, monkeypatch):
    """The authors' subgoal path (diagonal weights, z filter, last step, interval triplets,
    warmup-cosine PT, sliding relabelling) trains through to a policy at the tiny budget."""
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
    # interval triplets: interval_draws (10) per interval, so a multiple of 10
    assert m["subgoal/num_triplets"] > 0 and m["subgoal/num_triplets"] % 10 == 0
    # the last step of every preferred segment is a subgoal
    assert m["subgoal/num_subgoals"] >= m["subgoal/num_segments"]
    assert "eval/score_final" in m
