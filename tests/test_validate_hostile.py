"""Sweep files, overrides and run configs that passed validation and failed late (issue 43,
findings 4 and 7): each is now refused where it enters, through the CLI (``spot sweep FILE
--dry-run``, ``spot run [CONFIG] k=v``), with exit code 2, one ``error:`` line naming the file or
key and what was expected, and nothing written. The limits (runs per sweep, YAML depth, layers,
string length, memory) are checked at and around their boundaries with the constants the code
exposes; a non-finite loss names the config keys that scale it (one tiny real run).

No test here trains except the last; the others resolve configs only.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from spot import NonFiniteError, SpotError, cli, config, loop
from spot.sweep import spec

SWEEP = "name: hostile\nbase: {method: oracle, budget: tiny}\n"
PT_SWEEP = "name: hostile\nbase: {method: pt, budget: tiny}\n"


def _nested(depth: int) -> str:
    """A flow list nested ``depth`` deep: ``[[...[1]...]]``."""
    return "[" * depth + "1" + "]" * depth


def _values(n: int, scale: float) -> str:
    return "[" + ", ".join(f"{scale * (i + 1):.6g}" for i in range(n)) + "]"


# (id, argv, files {name: text}, what the one error line must contain)
CASES = [
    # ---- finding 4: resources that Ray waits on for ever, grids too large to check
    (
        "resources-nan-cpu",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP + "resources: {cpu: .nan}\n"},
        "sweep file 's.yaml': 'resources.cpu': expected a finite non-negative number, got nan",
    ),
    (
        "resources-inf-gpu",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP + "resources: {gpu: .inf}\n"},
        "sweep file 's.yaml': 'resources.gpu': expected a finite non-negative number, got inf",
    ),
    (
        "smoke-resources-nan",
        ["sweep", "s.yaml", "--dry-run", "--smoke"],
        {"s.yaml": SWEEP + "smoke: {resources: {cpu: .nan}}\n"},
        "'resources.cpu': expected a finite non-negative number, got nan",
    ),
    (
        "grid-of-a-million",
        ["sweep", "s.yaml", "--dry-run"],
        {
            "s.yaml": SWEEP
            + f"grid: {{iql.lr: {_values(100, 1e-5)}, iql.tau: {_values(100, 1e-4)}, "
            + f"iql.expectile: {_values(100, 1e-3)}}}\n"
        },
        "sweep file 's.yaml': 'grid.iql.lr': the sweep expands to 1,000,000 runs = 100 (grid.iql.lr) x 100 "
        "(grid.iql.tau) x 100 (grid.iql.expectile) x 1 (zip) x 1 (seeds); expected at most 10,000",
    ),
    (
        "grid-times-seeds",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP + f"grid: {{iql.lr: {_values(101, 1e-5)}}}\nseeds: {list(range(100))}\n"},
        "the sweep expands to 10,100 runs = 101 (grid.iql.lr) x 1 (zip) x 100 (seeds); expected at most 10,000",
    ),
    (
        "zip-rows-times-grid",
        ["sweep", "s.yaml", "--dry-run"],
        {
            "s.yaml": SWEEP
            + f"grid: {{iql.lr: {_values(20, 1e-5)}}}\nzip: {{iql.tau: {_values(600, 1e-6)}, "
            + f"iql.expectile: {_values(600, 1e-3)}}}\n"
        },
        "sweep file 's.yaml': 'zip': the sweep expands to 12,000 runs",
    ),
    # ---- finding 7: grid points and zip rows that resolve to one config
    (
        "grid-1e3-is-1000",  # YAML reads 1e3 as a string; the config as the integer 1000
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP + "grid: {iql.steps: [1000, 1e3]}\n"},
        "sweep file 's.yaml': trials iql.steps=1000 and iql.steps='1e3' resolve to the same config",
    ),
    (
        "grid-1000.0-is-1000",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP + "grid: {iql.steps: [1.0e+3, 1000]}\n"},
        "sweep file 's.yaml': trials iql.steps=1000.0 and iql.steps=1000 resolve to the same config",
    ),
    (
        "grid-string-number",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP + "grid: {iql.lr: [0.1, '0.1']}\n"},
        "trials iql.lr=0.1 and iql.lr='0.1' resolve to the same config",
    ),
    (
        "zip-rows-written-differently",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP + "zip: {iql.hidden: [[64, 64], '64, 64'], iql.lr: [0.1, 0.1]}\n"},
        "trials iql.hidden=[64, 64] iql.lr=0.1 and iql.hidden='64, 64' iql.lr=0.1 resolve to the same config",
    ),
    (
        "zip-v2-dataset-name",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP + "zip: {data.name: [hopper-medium-replay, hopper-medium-replay-v2]}\n"},
        "trials data.name='hopper-medium-replay' and data.name='hopper-medium-replay-v2' resolve to the same config",
    ),
    # ---- finding 7: nesting, sizes and counts of files and overrides
    (
        "sweep-10000-deep",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP + f"grid: {{iql.hidden: {_nested(10_000)}}}\n"},
        "sweep file 's.yaml': not valid YAML: nested deeper than 16 levels",
    ),
    (
        "config-10000-deep",
        ["run", "c.yaml"],
        {"c.yaml": f"iql: {{hidden: {_nested(10_000)}}}\n"},
        "config file 'c.yaml': not valid YAML: nested deeper than 16 levels",
    ),
    (
        "config-deep-mapping",
        ["run", "c.yaml"],
        {"c.yaml": "a: " + "{a: " * 40 + "1" + "}" * 40 + "\n"},
        "config file 'c.yaml': not valid YAML: nested deeper than 16 levels; expected at most 16 at line 1",
    ),
    (
        "override-10000-deep",
        ["run", f"iql.hidden={_nested(10_000)}"],
        {},
        "override 'iql.hidden': value nested deeper than 16 levels",
    ),
    ("override-65-layers", ["run", f"iql.hidden={[8] * 65}"], {}, "config key 'iql.hidden': 65 layer sizes"),
    ("pt-1000-layers", ["run", "pt.n_layer=1000"], {}, "config key 'pt.n_layer': value 1000 is out of range"),
    ("hpl-1000-layers", ["run", "hpl.n_layer=1000"], {}, "expected 1 <= value <= 64"),
    (
        "string-of-5000",
        ["run", f"data.name={'x' * 5000}"],
        {},
        "config key 'data.name': a string of 5000 characters; expected at most 4096",
    ),
    (
        "nul-in-a-name",
        ["run", "c.yaml"],
        {"c.yaml": 'data: {name: "hopper\\0medium"}\n'},
        "config key 'data.name': value 'hopper\\x00medium' holds the control character '\\x00'",
    ),
    (
        "newline-in-experiment",
        ["run", "c.yaml"],
        {"c.yaml": 'tracking: {experiment: "a\\nb"}\n'},
        "config key 'tracking.experiment'",
    ),
    (
        "sweep-name-of-300",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP.replace("hostile", "n" * 300)},
        "sweep file 's.yaml': 'name': 300 characters; expected at most 200",
    ),
    (
        "int-of-5000-digits",
        ["run", f"iql.steps={'9' * 5000}"],
        {},
        "config key 'iql.steps': value '99999999999999999999999999999999999999999999... (5002 characters) is not int",
    ),
    (
        "yaml-int-of-5000-digits",
        ["run", "c.yaml"],
        {"c.yaml": f"iql: {{steps: {'9' * 5000}}}\n"},
        "config file 'c.yaml': not valid YAML: Exceeds the limit (4300 digits) for integer string conversion",
    ),
    # ---- finding 7: real finite numbers (float32)
    (
        "beyond-float32",
        ["run", "relabel.scale=1e39"],
        {},
        "config key 'relabel.scale': value '1e39' is beyond float32 (|value| <= 3.403e+38)",
    ),
    (
        "sweep-beyond-float32",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP + "grid: {cvae.beta: [1.0, 1.0e+300]}\n"},
        "trial cvae.beta=1e+300: config key 'cvae.beta': value 1e+300 is beyond float32",
    ),
    # ---- finding 7: model shapes that cannot work
    (
        "pt-heads-do-not-divide",
        ["run", "method=pt", "pt.embd_dim=64", "pt.n_head=3"],
        {},
        "config: pt.embd_dim=64 is not divisible by pt.n_head=3",
    ),
    (
        "hpl-heads-do-not-divide",
        ["run", "method=hpl", "hpl.embd_dim=30", "hpl.n_head=4"],
        {},
        "config: hpl.embd_dim=30 is not divisible by hpl.n_head=4",
    ),
    (
        "sweep-heads-axis",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": PT_SWEEP + "grid: {pt.n_head: [2, 3]}\n"},
        "sweep file 's.yaml': trial pt.n_head=3: config: pt.embd_dim=16 is not divisible by pt.n_head=3",
    ),
    (
        "one-query-no-training",
        ["run", "method=pt", "labels.num_queries=1"],
        {},
        "config: labels.eval_fraction=0.1 of labels.num_queries=1 holds out 1 queries and leaves none for training",
    ),
    (
        "two-queries-90-percent-held-out",
        ["run", "method=mr", "labels.num_queries=2", "labels.eval_fraction=0.9"],
        {},
        "holds out 2 queries and leaves none for training",
    ),
    # ---- finding 7: sizes that cannot fit in memory (each needs terabytes: no machine passes them)
    (
        "mlp-of-a-million",
        ["run", "iql.hidden=[1000000, 1000000, 1000000]"],
        {},
        "config: the policy stage needs at least 89,418.6 GiB",  # 4 x 12 x 2.000005e12 + 16 x 256 x 3e6 bytes
    ),
    (
        "pt-segments-of-100000",
        ["run", "method=pt", "labels.segment_length=100000"],
        {},
        "config: the reward stage needs at least",
    ),
    (
        "pt-timestep-table",
        ["run", "method=pt", "pt.max_timestep=2000000000", "pt.embd_dim=4096"],
        {},
        "pt.max_timestep=2000000000",
    ),
    (
        "hpl-batch",
        ["run", "method=hpl", "hpl.vae_batch=2000000000"],
        {},
        "config: the reward stage needs at least",
    ),
    (
        "sweep-memory-axis",
        ["sweep", "s.yaml", "--dry-run"],
        {"s.yaml": SWEEP + "grid: {iql.batch_size: [64, 2000000000], iql.hidden: [[1000000, 1000000]]}\n"},
        "trial iql.batch_size=64 iql.hidden=[1000000, 1000000]: config: the policy stage needs at least",
    ),
]


def _write(folder: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        (folder / name).write_text(text)


@pytest.mark.parametrize(("argv", "files", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_hostile_input_is_one_clear_error(tmp_path, monkeypatch, capsys, argv, files, expected):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    _write(tmp_path, files)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    rc = cli.main(argv)
    _, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert rc == 2, err[-2000:]
    assert len(lines) == 1 and lines[0].startswith("error: "), err[-2000:]
    assert expected in lines[0], lines[0]
    assert len(lines[0]) < 600, lines[0]  # a value of megabytes is cut in the message
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # nothing written, inputs unchanged


# --------------------------------------------------------------------------- run cap and progress
def _sweep_file(tmp_path: Path, grid: str, name: str = "s.yaml") -> Path:
    path = tmp_path / name
    path.write_text(SWEEP + grid)
    return path


def test_a_grid_over_the_cap_is_refused_before_any_config_resolves(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(config, "resolve", lambda *a, **k: calls.append(a))
    path = _sweep_file(tmp_path, f"grid: {{iql.lr: {_values(1000, 1e-6)}, iql.tau: {_values(1000, 1e-6)}}}\n")
    with pytest.raises(SpotError, match=r"expands to 1,000,000 runs") as err:
        spec.load(path)
    assert calls == [] and str(path) in str(err.value)


def test_the_cap_counts_runs_at_its_boundary(tmp_path, monkeypatch):
    monkeypatch.setattr(spec, "MAX_RUNS", 6)
    at = _sweep_file(tmp_path, "grid: {iql.lr: [0.1, 0.2, 0.3]}\nseeds: [0, 1]\n", "at.yaml")
    assert len(spec.load(at).runs()) == 6  # 3 configs x 2 seeds: exactly the cap
    over = _sweep_file(tmp_path, "grid: {iql.lr: [0.1, 0.2, 0.3]}\nseeds: [0, 1, 2]\n", "over.yaml")
    with pytest.raises(SpotError, match=r"expands to 9 runs = 3 \(grid.iql.lr\) x 1 \(zip\) x 3 \(seeds\)"):
        spec.load(over)
    # sequential: one trial per config, but still a run per seed
    seq = _sweep_file(tmp_path, "grid: {iql.lr: [0.1, 0.2, 0.3]}\nseeds: [0, 1, 2]\nseed_mode: sequential\n", "q.yaml")
    with pytest.raises(SpotError, match="expands to 9 runs"):
        spec.load(seq)


def test_a_large_grid_shows_progress_and_a_small_one_does_not(tmp_path, monkeypatch, capsys):
    path = _sweep_file(tmp_path, "grid: {iql.lr: [0.1, 0.2, 0.3, 0.4]}\n")
    spec.load(path, progress=True)
    err = capsys.readouterr().err
    assert "checking s.yaml" in err and "/4" in err
    monkeypatch.setattr(spec, "PROGRESS_FROM", 4)
    spec.load(path)  # progress=None: a bar only on a terminal; pytest's stderr is not one
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(spec, "PROGRESS_FROM", 5)
    spec.load(path, progress=None)
    assert capsys.readouterr().err == ""


def test_a_grid_of_distinct_configs_still_loads(tmp_path):
    # values that differ once resolved are kept: 1000 and 1001 steps, two widths, two dataset names
    path = _sweep_file(
        tmp_path,
        "grid: {iql.steps: [1000, 1001]}\nzip: {iql.hidden: [[64, 64], [64]], data.name: [hopper-medium-replay, "
        "walker2d-medium-replay-v2]}\n",
    )
    assert len(spec.load(path).trials()) == 4


# --------------------------------------------------------------------------- YAML depth at its boundary
def test_yaml_nesting_is_refused_one_level_past_the_limit(tmp_path):
    path = tmp_path / "d.yaml"
    # the root mapping is one level; each '[' another
    path.write_text(f"x: {_nested(config.MAX_YAML_DEPTH - 1)}\n")
    assert config.read_yaml(path, "file 'd.yaml'")["x"] is not None
    path.write_text(f"x: {_nested(config.MAX_YAML_DEPTH)}\n")
    with pytest.raises(SpotError, match=r"^file 'd.yaml': not valid YAML: nested deeper than 16 levels"):
        config.read_yaml(path, "file 'd.yaml'")


def test_every_repo_config_is_within_the_depth_limit():
    repo = Path(__file__).resolve().parents[1]
    files = [*repo.glob("configs/*.yaml"), *repo.glob("sweeps/*.yaml")]
    assert files
    for path in files:
        config.read_yaml(path, str(path))  # raises past the limit


# --------------------------------------------------------------------------- memory estimate
def test_memory_needs_of_iql_counted_by_hand():
    cfg = config.resolve({"method": "oracle", "budget": "tiny", "iql.hidden": (1000, 2000), "iql.batch_size": 10})
    need, keys = config.memory_needs(cfg)["policy"]
    # one MLP 1 -> 1000 -> 2000 -> 1: weights and biases
    per_net = 2 * 1000 + 1001 * 2000 + 2001 * 1
    # actor, two critics and the value net, float32 with Adam's two moments; activations of a batch
    assert need == 4 * per_net * 4 * 3 + 4 * 4 * 10 * 3000
    assert "iql.hidden=(1000, 2000)" in keys and "iql.batch_size=10" in keys


def test_check_memory_refuses_just_above_and_passes_at_the_need():
    cfg = config.resolve({"method": "pt", "budget": "tiny"})
    need = max(b for b, _ in config.memory_needs(cfg).values())
    config.check_memory(cfg, available=need)
    with pytest.raises(SpotError, match=r"config: the \w+ stage needs at least .* GiB .* more than this machine's"):
        config.check_memory(cfg, available=need - 1)


def test_repo_budgets_fit_a_laptop():
    # every method, budget and variant of the presets needs under 1 GiB by this bound
    for method in config.METHODS:
        for budget in config.BUDGETS:
            for variant in config.VARIANTS:
                cfg = config.resolve({"method": method, "budget": budget, "variant": variant})
                assert max(b for b, _ in config.memory_needs(cfg).values()) < 2**30


def test_resolving_is_fast_enough_to_check_a_capped_sweep():
    import time

    config.resolve({"method": "oracle"})
    t0 = time.perf_counter()
    for i in range(200):
        config.resolve({"method": "oracle", "budget": "tiny", "iql.steps": 100 + i})
    per = (time.perf_counter() - t0) / 200
    # MAX_RUNS configs in well under a minute (was ~14 ms each: 140 s; now ~1 ms)
    assert per * spec.MAX_RUNS < 60, per


# --------------------------------------------------------------------------- non-finite losses
def test_a_non_finite_loss_names_the_keys_that_scale_it():
    cfg = config.resolve({"method": "pt", "budget": "small", "pt.lr": 0.9})
    err = loop.name_keys(NonFiniteError(7, "reward/train_loss", math.nan), cfg)
    assert str(err) == (
        "non-finite loss 'reward/train_loss' = nan at step 7; the config keys that scale this loss: "
        "pt.lr=0.9 (default 0.0001), pt.peak_factor=10.0, pt.b2=0.99"
    )
    assert loop.name_keys(err, cfg) is err and str(err).count("pt.lr") == 1  # named once
    mr = config.resolve({"method": "mr", "mr.lr": 0.5})
    assert "mr.lr=0.5 (default 0.0003)" in str(loop.name_keys(NonFiniteError(3, "reward/eval_loss"), mr))
    cvae = loop.name_keys(NonFiniteError(3, "cvae/loss"), config.resolve({"cvae.beta": 1e30}))
    assert "keys that scale this loss: cvae.beta=1e+30 (default 1.0), cvae.lr=" in str(cvae)
    assert str(loop.name_keys(NonFiniteError(3, "something/else"), cfg)).endswith("at step 3")


def test_an_overflowing_run_names_the_key_in_its_error_and_failure_reason(
    tmp_path, spot_dirs, tiny_drawer, monkeypatch
):
    """A real overflow: relabel.scale near float32's largest makes the oracle's rewards ~1e38 and
    IQL's critic loss inf at its first check (step 100); the key comes first, with its default."""
    import mlflow

    from spot import pipeline
    from tests.conftest import TINY_RUN

    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "cache"))
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = config.load(
        None, [*TINY_RUN, "method=oracle", "relabel.scale=3e38", f"tracking.uri={uri}", "tracking.experiment=t"]
    )
    with pytest.raises(NonFiniteError) as err:
        pipeline.run(cfg, progress=False)
    assert err.value.loss_name == "iql/critic_loss"
    assert "the config keys that scale this loss: relabel.scale=3e+38 (default 0.0), iql.lr=" in str(err.value)
    mlflow.set_tracking_uri(uri)
    failed = mlflow.search_runs(experiment_names=["t"], filter_string="attributes.status = 'FAILED'")
    assert len(failed) == 1 and "relabel.scale=3e+38" in failed["tags.failure_reason"].iloc[0]
