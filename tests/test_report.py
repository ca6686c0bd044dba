"""Results files, tables and claim verdicts rebuilt from a committed fixture, without MLflow.

The claims are the lab's claims file (experiments/lab-hopper-medium-replay/claims.yaml, which
extends the package's paper_claims.yaml): the fixture's runs carry the lab's experiment names."""

import functools
import itertools
import re
import shlex
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import run_cli

from spot import SpotError
from spot.results import claims, compare, load, report, stats, table_format, tables
from spot.results.dose import format_dose

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = Path(__file__).parent / "data" / "results_fixture.csv"
LAB = ROOT / "experiments" / "lab-hopper-medium-replay" / "claims.yaml"
SET_P = (
    "lab_fidelity+lab_variant_rows+lab_paper+lab_paper_random+lab_paper_ablations+lab_paper_shaping"
    "+lab_paper_queries+lab_walker+lab_walker_controls"
)


@functools.cache
def _claims(use: tuple = ()) -> claims.ClaimsFile:
    return claims.load(LAB, dict(use))


def build(frame, use=None, high=compare.HIGH_MODE):
    """The lab claims file's rows on ``frame`` (``use``: sets replaced, {key: (experiment, ...)})."""
    return report.build(frame, _claims(tuple(sorted((use or {}).items()))), high).rows


def doses(frame):
    return report.build(frame, _claims()).doses


def text_of(rows):
    return report.format_report(report.Report(list(rows)))


@pytest.fixture(scope="module")
def runs():
    return load.read(FIXTURE)


def test_fixture_rebuilds_table1(runs):
    t = tables.build_table(runs, 1)
    # hopper SPOT: 61, 64, 66 -> mean 63.67; walker PT: 58, 61, 60 (the FAILED seed 3 is not counted)
    assert t.loc[("hopper-medium-replay", "recipe"), ("spot", "mean")] == pytest.approx(191 / 3)
    assert t.loc[("walker2d-medium-replay", "recipe"), ("pt", "n")] == 3


def _row(rows, claim, comparison, stat="last"):
    return next(r for r in rows if r.claim == claim and r.comparison.startswith(comparison) and r.stat == stat)


def test_claim1_effect_and_ci_against_an_independent_bootstrap(runs):
    rows = build(runs)
    r = _row(rows, "1", "spot vs pt")
    # hopper: mean(61, 64, 66) - mean(50, 52, 57) = 63.667 - 53 = 10.667
    # walker: mean(65, 69, 64) - mean(58, 61, 60) = 66 - 59.667 = 6.333   -> mean 8.5
    assert r.effect.value == pytest.approx(8.5)
    assert r.means == pytest.approx(((191 / 3 + 66) / 2, (53 + 179 / 3) / 2))  # each arm's mean of dataset means
    x = [np.array([61.0, 64, 66]), np.array([65.0, 69, 64])]
    y = [np.array([50.0, 52, 57]), np.array([58.0, 61, 60])]
    rng = np.random.default_rng(7)
    boot = [np.mean([rng.choice(x[i], 3).mean() - rng.choice(y[i], 3).mean() for i in range(2)]) for _ in range(20000)]
    lo, hi = np.percentile(boot, [2.5, 97.5])
    assert abs(r.effect.low - lo) < 0.3 and abs(r.effect.high - hi) < 0.3
    assert r.verdict == stats.SUPPORTED and r.n_x == 6 and r.n_y == 6
    assert r.poi.value == 1.0  # every SPOT seed beats every PT seed on both datasets
    assert any("1 FAILED" in n for n in r.notes)


def test_claim_verdicts_mr_inconclusive_ood_supported_missing_tables_say_no_runs(runs):
    rows = build(runs)
    mr = _row(rows, "1", "spot vs mr")
    assert mr.effect.value == pytest.approx(((191 / 3 - 59) + (66 - 197 / 3)) / 2)
    assert mr.verdict == stats.INCONCLUSIVE
    ood = _row(rows, "6", "pt", stat="ood")
    assert ood.effect.value == pytest.approx(0.25) and ood.verdict == stats.SUPPORTED
    assert _row(rows, "2", "group").verdict == "no runs"
    text = text_of(rows)
    assert "| 1 | SPOT ≥ PT on average (Table 1) | spot vs pt | lab_table1+lab_table1_fr | 8.5 [" in text


def test_claim6_under_variant_paper_reads_only_that_variants_runs(runs):
    """Row 6P is claim 6 on set P's variant-paper runs: the fixture relabelled as variant paper gives
    row 6's effect there, and row 6 (default variant) then has no runs."""
    paper = runs.assign(**{"params.variant": "paper"})
    rows = build(paper, {"P": ("lab_table1",)})
    ood = _row(rows, "6P", "pt", stat="ood")
    assert ood.effect.value == pytest.approx(0.25) and ood.verdict == stats.SUPPORTED
    assert ood.text.endswith("(variant paper)")
    assert _row(rows, "6", "pt", stat="ood").verdict == "no runs"
    # a PT run of another variant never enters 6P's PT arm: one at an OOD error far off moves nothing
    far_off = {"params.variant": "authors", "run_id": "run900", "config_hash": "0ther", claims.OOD_METRIC: 99.0}
    other = paper[paper["method"] == "pt"].head(1).assign(**far_off)
    again = _row(build(pd.concat([paper, other]), {"P": ("lab_table1",)}), "6P", "pt", stat="ood")
    assert again.effect.value == pytest.approx(0.25) and again.n_x == ood.n_x


def test_aggregate_iqm_by_hand(runs):
    agg = table_format.aggregate(runs).set_index("method")
    # SPOT pooled: 61 64 64 65 66 69 -> trim one from each end -> mean(64, 64, 65, 66) = 64.75
    assert agg.loc["spot", "iqm"].startswith("64.8 [")
    assert agg.loc["pt", "P(spot > method)"].startswith("1.00")


def test_claim4_difference_in_differences():
    import pandas as pd

    rows = []
    for m, few, most in (("spot", [70.0, 72], [71.0, 73]), ("pt", [50.0, 52], [60.0, 62])):
        for q, vals in ((30, few), (100, most)):
            for s, v in enumerate(vals):
                rows.append(
                    {
                        "run_id": f"{m}{q}{s}",
                        "experiment": "lab_table4",
                        "status": "FINISHED",
                        "method": m,
                        "dataset": "h",
                        "paper_dataset": "h",
                        "seed": s,
                        "config_hash": f"{m}{q}",
                        "params.labels.num_queries": str(q),
                        "metrics.eval/score_final": v,
                        "metrics.eval/score_best": v,
                        "data_digest": "d-rebuilt" if (m, q, s) == ("pt", 30, 1) else "d-original",
                    }
                )
    killed = dict(rows[0], run_id="spot30k", seed=5, status="KILLED", **{"metrics.eval/score_final": 0.0})
    r = _row(build(pd.DataFrame(rows + [killed])), "4", "(spot")
    # SPOT: 71 - 72 = -1; PT: 51 - 61 = -10; difference +9 (the killed run at 0 is not counted)
    assert r.effect.value == pytest.approx(9.0)
    assert r.means == pytest.approx((-1.0, -10.0))  # each method's change, fewest minus most queries
    assert r.notes == [
        "spot: 1 KILLED (not counted)",
        "h: the runs span 2 data digests (7 on d-original, 1 on d-rebuilt); they may not share their data",
        "permutation p from the seed-matched gains (SPOT − PT of one seed at one query count; 2 at the fewest "
        "vs 2 at the most queries), exchanged between the query counts within each dataset",
        "its planning numbers (Runs for a verdict) count seeds per query count, each a SPOT and a PT run, "
        "and their time is both runs'",
    ]
    # gains SPOT − PT: few 20, 20; most 11, 11. Of the C(4, 2) = 6 ways to pick the two "few" gains, one
    # gives +9 and one -9: two-sided p = 2/6
    assert r.perm_p == pytest.approx(2 / 6)


def test_claim4_permutation_test_on_the_seed_matched_gains_by_hand():
    # PT and SPOT at 50 queries (seeds 0-2) and 500 (seeds 0-4), SPOT = PT + the gain of its seed; one
    # SPOT run at 500 without a PT partner (seed 7) enters the effect but not the test
    few_gain, most_gain = [1.2, 8.4, 26.1], [28.9, 14.4, 73.4, 74.6, 6.8]
    rows = []
    for q, gain in ((50, few_gain), (500, most_gain)):
        for s, g in enumerate(gain):
            base = 10.0 + s
            for m, v in (("pt", base), ("spot", base + g)):
                rows.append({"run_id": f"{m}{q}{s}", "method": m, "seed": s, "q": q, "v": v})
    rows.append({"run_id": "spot500s7", "method": "spot", "seed": 7, "q": 500, "v": 50.0})
    frame = pd.DataFrame(rows).assign(experiment="lab_table4", status="FINISHED", dataset="h", paper_dataset="h")
    frame = frame.assign(
        config_hash=frame["method"] + frame["q"].astype(str),
        **{"params.labels.num_queries": frame["q"].astype(str), "metrics.eval/score_final": frame["v"]},
        **{"metrics.eval/score_best": frame["v"]},
    )
    r = _row(build(frame), "4", "(spot")
    # the gains pooled, ascending: 1.2 6.8 8.4 14.4 26.1 28.9 73.4 74.6. A split's statistic falls with the
    # sum of its three "few" gains; the observed sum is 35.7, and of the C(8, 3) = 56 triples six sum to
    # at most that (1.2 with 6.8+8.4, 6.8+14.4, 6.8+26.1, 8.4+14.4 or 8.4+26.1; and 6.8+8.4+14.4):
    # p = 2 * 6/56
    assert r.perm_p == pytest.approx(12 / 56)
    test_note = next(n for n in r.notes if n.startswith("permutation p"))
    assert "5 at the most queries" in test_note and test_note.endswith("in the effect, not in the test")
    assert r.verdict.startswith(stats.INCONCLUSIVE)
    # its planning numbers are the gains': within-count sum of squares 328.38 (few, mean 11.9) + 4192.81
    # (most, mean 39.62) over 3 + 5 - 2 = 6 dof: sd sqrt(753.53) = 27.45; counted in seeds per query count
    assert r.plan.sd == pytest.approx(27.45, abs=0.01) and r.sizes == ([3], [5])
    line = next(x for x in report.format_plan([r]) if x.startswith("| 4 |"))
    assert "| 3 vs 5 seeds, 1 dataset |" in line and line.endswith("seeds (time not logged) |")
    # twenty unpartnered SPOT runs at 50 queries scoring 200 turn the effect positive while the gains'
    # difference stays -27.7: the test cannot back that verdict, and the row says so instead
    lone = pd.concat([frame[frame["run_id"] == "spot500s7"]] * 20, ignore_index=True)
    lone = lone.assign(
        run_id=[f"lone{i}" for i in range(20)], seed=range(100, 120), q=50, **{"params.labels.num_queries": "50"}
    )
    lone = lone.assign(config_hash="spot50", **{"metrics.eval/score_final": 200.0})
    r = _row(build(pd.concat([frame, lone], ignore_index=True)), "4", "(spot")
    assert r.effect.value > 0 and np.isnan(r.perm_p) and r.verdict.endswith("no permutation test for this effect)")
    assert any(n.startswith("no permutation test: the seed-matched gains' difference (-27.7)") for n in r.notes)
    # two SPOT runs of one seed at 500 queries (two configs in the cell): no pairs there, no test, and a note
    twin = frame[frame["run_id"] == "spot5000"].assign(run_id="twin", config_hash="spot500b")
    r = _row(build(pd.concat([frame, twin], ignore_index=True)), "4", "(spot")
    assert np.isnan(r.perm_p) and "no permutation test: h at 500 queries has no seed-matched SPOT and PT runs" in (
        " ".join(r.notes)
    )


def test_bad_results_files_are_clear_errors(tmp_path):
    with pytest.raises(SpotError, match="does not exist"):
        load.read(tmp_path / "nope.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(SpotError, match=r"bad.csv: missing columns"):
        load.read(bad)
    (tmp_path / "empty").mkdir()
    with pytest.raises(SpotError, match="no results CSV"):
        load.read(tmp_path / "empty")


def test_export_from_a_real_mlflow_store_round_trips(tmp_path):
    from mlflow.tracking import MlflowClient

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(uri)
    exp = client.create_experiment("lab_table1")
    for seed, score in enumerate((10.0, 20.0)):
        run = client.create_run(
            exp,
            tags={
                "method": "pt",
                "dataset": "hopper-medium-replay",
                "seed": str(seed),
                "dataset_source": "recipe",
                "git_commit": "abc",
                "data_digest": "d1",
            },
        )
        client.log_param(run.info.run_id, "seed", str(seed))
        client.log_param(run.info.run_id, "iql.steps", "1000")
        client.log_metric(run.info.run_id, "eval/score_final", score)
        for step, value in ((20000, score + 0.5), (0, 1.0), (10000, 60.0 * seed)):  # out of step order
            client.log_metric(run.info.run_id, "eval/score", value, step=step)
        client.log_metric(run.info.run_id, "iql/awr_clip_frac", 0.25)  # IQL's AWR diagnostics are exported
        client.log_metric(run.info.run_id, "labels/ties", 1.0)  # not a results metric
        client.set_terminated(run.info.run_id)
    out = tmp_path / "r.csv"
    p = run_cli("results", "export", "--experiment", "lab_table1", "--tracking-uri", uri, "--out", str(out))
    assert p.returncode == 0, p.stderr
    df = load.read(out)
    assert sorted(df["metrics.eval/score_final"]) == [10.0, 20.0]
    assert "metrics.labels/ties" not in df and df["metrics.iql/awr_clip_frac"].tolist() == [0.25, 0.25]
    assert df["config_hash"].nunique() == 1 and set(df["data_digest"]) == {"d1"}
    curves = dict(zip(df["seed"], df[load.CURVE_COLUMN], strict=True))
    assert curves[0] == "0:1.0000;10000:0.0000;20000:10.5000"  # in step order
    steps, values = load.parse_curve(curves[1], "x")
    assert steps.tolist() == [0, 10000, 20000] and values.tolist() == [1.0, 60.0, 20.5]
    # seed 1's evaluation at 10k (60) is in the high mode; step 0 is not an evaluation of training
    assert compare.high_mode(df, 50.0) == compare.Mode(evals_high=1, evals=4, runs_high=1, runs=2)
    p = run_cli("tables", "--table", "1", "--results", str(out))
    assert p.returncode == 0 and "15.00 ± 7.07** (2)" in p.stdout, p.stdout + p.stderr


def test_tables_cli_prints_cis_and_the_across_datasets_summary():
    p = run_cli("tables", "--table", "1", "--results", str(FIXTURE))
    assert p.returncode == 0, p.stderr
    # hopper PT 50, 52, 57: a resample of all 50s (or all 57s) has probability 1/27 > 2.5 %, so the
    # percentile interval of the mean is exactly [50, 57]
    assert "53.00 ± 3.61 (3) CI 50.00–57.00" in p.stdout
    assert "**Across datasets**" in p.stdout and "| spot | 2 | 6 | 64.8 [" in p.stdout


def test_text_table_fits_the_terminal_and_rounds(runs):
    t = tables.build_table(runs, 1)
    for width in (120, 60):
        text = table_format.format_table(t, "text", width=width)
        body = text.splitlines()[2:]  # the title and legend lines may be longer
        assert all(len(line) <= width for line in body), width
    text = table_format.format_table(t, "text", width=120)
    assert "63.7±2.5* (85.1)" in text  # SPOT hopper: mean 63.67 rounds up; paper 85.08
    assert len([ln for ln in table_format.format_table(t, "text", width=60).splitlines() if "hopper" in ln]) > 1


def test_controls_take_spot_from_table1_and_never_count_as_spot(runs):
    # the control sweep (experiment lab_controls) holds only the two controls, on hopper; SPOT's arm
    # of each control is SPOT's Table 1 runs, and a control run (method spot too) never joins SPOT's arm
    spot = runs[(runs["method"] == "spot") & (runs["dataset"] == "hopper-medium-replay")]
    random_sg = spot.assign(experiment="lab_controls", **{"params.subgoal.source": "random"})
    constant = spot.assign(experiment="lab_controls", **{"params.shaping.kind": "constant"})
    random_sg = random_sg.assign(
        run_id=["c1", "c2", "c3"], config_hash="random", **{"metrics.eval/score_final": [40.0, 44.0, 45.0]}
    )
    constant = constant.assign(
        run_id=["c4", "c5", "c6"], config_hash="constant", **{"metrics.eval/score_final": [70.0, 71.0, 75.0]}
    )
    mixed = runs.assign(**{"params.subgoal.source": "attention"})
    both = pd.concat([mixed, random_sg, constant], ignore_index=True)
    rows = build(both)
    rnd = _row(rows, "C", "spot vs random")
    # hopper only (the controls ran there): mean(61, 64, 66) - mean(40, 44, 45) = 63.667 - 43 = 20.667
    assert rnd.experiment == "lab_table1+lab_controls" and rnd.datasets == ["hopper-medium-replay"]
    assert rnd.effect.value == pytest.approx(191 / 3 - 43) and rnd.effect.low > 0
    # 3 vs 3 runs on one dataset, every SPOT run above every control run: of the C(6, 3) = 20 ways to
    # split the six runs, only this one and its mirror are as far apart, p = 2/20; the CI alone would
    # say supported, the permutation test cannot pass at this n
    assert rnd.perm_p == pytest.approx(0.1)
    assert rnd.verdict == "inconclusive (the CI alone: supported; permutation p = 0.1)"
    const = _row(rows, "C", "spot vs constant")
    assert const.effect.value == pytest.approx(191 / 3 - 72) and const.effect.high < 0
    assert const.verdict == "inconclusive (the CI alone: not supported; permutation p = 0.1)"
    assert any("walker2d-medium-replay left out" in n for n in const.notes)
    # the bonus alone on hopper: mean(70, 71, 75) - mean(50, 52, 57) = 72 - 53 = 19
    assert _row(rows, "C", "constant bonus vs pt").effect.value == pytest.approx(19.0)
    # claim 1 with the controls in the same frame: SPOT's arm is still the six Table 1 runs
    moved = pd.concat([mixed, random_sg.assign(experiment="lab_table1")], ignore_index=True)
    assert _row(build(moved), "1", "spot vs pt").effect.value == pytest.approx(8.5)


def test_a_verdict_needs_three_runs_per_arm_and_dataset(runs):
    # two seeds of each arm still get an effect and an interval, but no verdict
    two = runs[~((runs["method"] == "spot") & (runs["seed"] == 2)) & ~((runs["method"] == "pt") & (runs["seed"] == 2))]
    r = _row(build(two), "1", "spot vs pt")
    assert r.min_n == 2 and r.effect is not None and not np.isnan(r.effect.low)
    assert r.verdict == stats.TOO_FEW
    assert _row(build(runs), "1", "spot vs pt").min_n == 3


def test_fidelity_rows_compare_variants_with_table1_as_the_spot_variant(runs):
    # lab_fidelity holds the paper and authors variants on hopper; the spot variant's arm is Table 1's
    # SPOT runs (no params.variant column there: logged before the key, so `spot`)
    spot = runs[(runs["method"] == "spot") & (runs["dataset"] == "hopper-medium-replay")]
    paper = spot.assign(experiment="lab_fidelity", config_hash="paper", **{"params.variant": "paper"})
    paper = paper.assign(run_id=["f1", "f2", "f3"], **{"metrics.eval/score_final": [70.0, 72.0, 77.0]})
    authors = spot.assign(experiment="lab_fidelity", config_hash="authors", **{"params.variant": "authors"})
    authors = authors.assign(run_id=["f4", "f5", "f6"], **{"metrics.eval/score_final": [60.0, 62.0, 65.0]})
    rows = build(pd.concat([runs, paper, authors], ignore_index=True))
    ap = _row(rows, "F", "variant authors vs paper")
    # mean(60, 62, 65) - mean(70, 72, 77) = 62.333 - 73 = -10.667; every paper seed beats every authors seed
    assert ap.experiment == "lab_fidelity+lab_table1" and ap.effect.value == pytest.approx(187 / 3 - 73)
    # the CI lies below 0, but 3 vs 3 separated runs on one dataset give permutation p = 2/20
    assert ap.effect.high < 0 and ap.poi.value == 0.0 and ap.perm_p == pytest.approx(0.1)
    assert ap.verdict == "inconclusive (the CI alone: not supported; permutation p = 0.1)"
    ps = _row(rows, "F", "variant paper vs spot")
    # hopper only (the variants ran there): 73 - mean(61, 64, 66) = 73 - 63.667 = 9.333
    assert ps.effect.value == pytest.approx(73 - 191 / 3) and ps.datasets == ["hopper-medium-replay"]
    assert ps.n_x == 3 and ps.n_y == 3 and ps.verdict.startswith("inconclusive (the CI alone: supported")
    assert any("walker2d-medium-replay left out" in n for n in ps.notes)


def _paper_arm(runs, experiment, tag, scores, **cols):
    """Three runs of one arm under variant paper: Table 1's hopper SPOT runs renamed, ``cols`` set."""
    hop = runs[(runs["method"] == "spot") & (runs["dataset"] == "hopper-medium-replay")]
    out = hop.assign(experiment=experiment, config_hash=tag, run_id=[f"{tag}{i}" for i in range(3)])
    return out.assign(**{"params.variant": "paper", "metrics.eval/score_final": scores, **cols})


def test_paper_variant_rows_take_each_arm_from_its_own_sweep_and_variant(runs):
    # rows 1P/CP: SPOT under variant paper (lab_fidelity) against PT and Oracle (lab_variant_rows), MR and the
    # constant bonus (lab_paper) and random subgoals (lab_paper_random), all under variant paper; lab_fidelity's
    # variant-spot SPOT runs and Table 1's runs never enter these rows
    arm = functools.partial(_paper_arm, runs)

    frame = pd.concat(
        [
            runs,
            arm("lab_fidelity", "sp", [70.0, 80.0, 90.0]),
            arm("lab_fidelity", "ss", [1.0, 2.0, 3.0], **{"params.variant": "spot"}),
            arm("lab_variant_rows", "pt", [20.0, 25.0, 30.0], method="pt"),
            arm("lab_variant_rows", "or", [21.0, 22.0, 23.0], method="oracle"),
            arm("lab_paper", "mr", [30.0, 40.0, 50.0], method="mr"),
            arm("lab_paper", "cb", [75.0, 85.0, 86.0], **{"params.shaping.kind": "constant"}),
            arm("lab_paper_random", "rs", [60.0, 61.0, 62.0], **{"params.subgoal.source": "random"}),
        ],
        ignore_index=True,
    )
    rows = build(frame)
    pt = _row(rows, "1P", "spot vs pt")
    # mean(70, 80, 90) = 80 against mean(20, 25, 30) = 25: 55
    assert pt.experiment == "set P" and pt.listed == ("set P", SET_P) and pt.effect.value == pytest.approx(55.0)
    assert pt.n_x == 3 and pt.n_y == 3 and pt.effect.low > 0 and pt.perm_p == pytest.approx(0.1)
    assert _row(rows, "1P", "spot vs mr").effect.value == pytest.approx(80 - 40)
    assert _row(rows, "1P", "spot vs oracle").effect.value == pytest.approx(80 - 22)
    assert _row(rows, "CP", "spot vs random").effect.value == pytest.approx(80 - 61)
    const = _row(rows, "CP", "spot vs constant")
    # 80 - mean(75, 85, 86) = 80 - 82 = -2; the CI spans 0
    assert const.effect.value == pytest.approx(-2.0) and const.verdict == stats.INCONCLUSIVE
    # the bonus alone: the constant control (PT's reward plus the bonus) against PT: 82 - 25 = 57
    assert _row(rows, "CP", "constant bonus vs pt").effect.value == pytest.approx(57.0)
    # the default-variant rows are unchanged by the paper runs in the frame
    assert _row(rows, "1", "spot vs pt").effect.value == pytest.approx(8.5)
    assert _row(rows, "C", "spot vs constant").effect is None


def test_paper_variant_ablation_rows_change_one_key_and_stay_out_of_the_spot_arm(runs):
    # rows 2P/5P: lab_fidelity's SPOT runs (top group, mse_cos; logged with those params) against
    # lab_paper_ablations' bottom-group arm and MSE-only arm; neither ablation counts as SPOT in 1P/CP
    arm = functools.partial(_paper_arm, runs, **{"params.subgoal.group": "top", "params.cvae.loss": "mse_cos"})

    frame = pd.concat(
        [
            runs,
            arm("lab_fidelity", "sp", [70.0, 80.0, 90.0]),
            arm("lab_variant_rows", "pt", [20.0, 25.0, 30.0], method="pt"),
            arm("lab_paper_ablations", "bo", [50.0, 55.0, 66.0], **{"params.subgoal.group": "bottom"}),
            arm("lab_paper_ablations", "ms", [81.0, 85.0, 89.0], **{"params.cvae.loss": "mse"}),
        ],
        ignore_index=True,
    )
    rows = build(frame)
    bottom = _row(rows, "2P", "group top vs bottom")
    # mean(70, 80, 90) = 80 against mean(50, 55, 66) = 57: 23
    assert bottom.experiment == "set P" and bottom.effect.value == pytest.approx(23.0)
    assert bottom.n_x == 3 and bottom.n_y == 3
    mse = _row(rows, "5P", "mse_cos vs mse")
    # 80 - mean(81, 85, 89) = 80 - 85 = -5; the arms overlap, the CI spans 0
    assert mse.effect.value == pytest.approx(-5.0) and mse.verdict == stats.INCONCLUSIVE
    # SPOT in 1P is lab_fidelity's three runs only: 80 - 25 = 55, n 3
    pt = _row(rows, "1P", "spot vs pt")
    assert pt.effect.value == pytest.approx(55.0) and pt.n_x == 3
    # the default-variant claims 2 and 5 read lab_table2/lab_table7 only
    assert _row(rows, "2", "group top vs bottom").effect is None and _row(rows, "5", "mse_cos vs mse").effect is None


def test_high_mode_counts_each_arms_evaluations_from_the_curves(runs, tmp_path):
    # Table 1's hopper runs, SPOT's and PT's with curves: SPOT reaches 50 in 3 of its 6 evaluations
    # after step 0 (in two of its three runs), PT in none (49.9 is below); MR's runs have no curve
    curves = {61.0: "0:1;10000:55;20000:20", 64.0: "10000:20;20000:20", 66.0: "0:2;10000:80;20000:90"}
    hop = (runs["dataset"] == "hopper-medium-replay") & (runs["status"] == "FINISHED")
    frame = runs.copy()
    frame[load.CURVE_COLUMN] = ""
    spot = hop & (frame["method"] == "spot")
    frame.loc[spot, load.CURVE_COLUMN] = frame.loc[spot, "metrics.eval/score_final"].map(curves)
    pt = hop & (frame["method"] == "pt")
    frame.loc[pt, load.CURVE_COLUMN] = "10000:30;20000:49.9"
    frame = frame[frame["dataset"] == "hopper-medium-replay"]
    path = tmp_path / "r.csv"
    frame.to_csv(path, index=False)
    rows = build(load.read(path))
    r = _row(rows, "1", "spot vs pt")
    assert r.high == (compare.Mode(3, 6, 2, 3), compare.Mode(0, 6, 0, 3))
    text = text_of(rows)
    assert "| 1 | spot vs pt | 3 of 6 (2 of 3 runs) | 0 of 6 (0 of 3 runs) |" in text
    # a higher threshold counts fewer; the CLI option reaches it
    assert _row(build(load.read(path), high=85.0), "1", "spot vs pt").high[0] == compare.Mode(1, 6, 1, 3)
    p = run_cli("report", "--claims", str(LAB), "--results", str(path), "--high-mode", "85")
    assert p.returncode == 0 and "scoring ≥ 85 (the high mode)" in p.stdout, p.stderr
    # an arm without curves shows no counts (MR's hopper runs have none)
    assert _row(rows, "1", "spot vs mr").high is None


def test_a_malformed_curve_is_a_clear_error_naming_the_file_and_run(runs, tmp_path):
    frame = runs.copy()
    frame[load.CURVE_COLUMN] = ""
    frame.loc[0, load.CURVE_COLUMN] = "10000:20;oops"
    path = tmp_path / "bad.csv"
    frame.to_csv(path, index=False)
    run_id = frame.loc[0, "run_id"]
    with pytest.raises(SpotError, match=rf"bad.csv, run {run_id}: curve.eval/score item 'oops' is not STEP:VALUE"):
        load.read(path)


def test_paper_variant_table3_row_takes_the_runner_up_among_spot_proper_runs(runs):
    # row 3P: lab_fidelity's SPOT runs (cosine λ=1) against lab_paper_shaping's other arms; the
    # best-scoring other arm is the runner-up. Control and ablation runs at cosine λ=1 are neither
    # arm, and the λ/kind arms never count as SPOT in 1P.
    arm = functools.partial(_paper_arm, runs, **{"params.shaping.kind": "cosine", "params.shaping.weight": "1.0"})

    frame = pd.concat(
        [
            runs,
            arm("lab_fidelity", "sp", [70.0, 80.0, 90.0]),
            arm("lab_variant_rows", "pt", [20.0, 25.0, 30.0], method="pt", **{"params.shaping.kind": "none"}),
            arm("lab_paper_shaping", "c01", [20.0, 25.0, 30.0], **{"params.shaping.weight": "0.1"}),
            arm("lab_paper_shaping", "nd1", [40.0, 50.0, 60.0], **{"params.shaping.kind": "neg_distance"}),
            arm("lab_paper_random", "rs", [99.0, 99.0, 99.0], **{"params.subgoal.source": "random"}),
            arm("lab_paper_ablations", "bo", [98.0, 98.0, 98.0], **{"params.subgoal.group": "bottom"}),
        ],
        ignore_index=True,
    )
    rows = build(frame)
    r = _row(rows, "3P", "cosine λ=1 vs runner-up")
    # runner-up: neg_distance λ=1 (mean 50) over cosine λ=0.1 (25); effect 80 - 50 = 30
    assert r.comparison == "cosine λ=1 vs runner-up neg_distance λ=1.0"
    assert r.effect.value == pytest.approx(30.0) and r.n_x == 3 and r.n_y == 3
    assert (
        "only 2 of the design's 8 other arms have finished runs: cosine λ=0.1, neg_distance λ=1.0; "
        "the verdict is against those alone"
    ) in r.notes
    pt = _row(rows, "1P", "spot vs pt")
    assert pt.effect.value == pytest.approx(80 - 25) and pt.n_x == 3
    # the default-variant claim 3 reads lab_table3 only
    assert _row(rows, "3", "cosine").effect is None


def test_paper_variant_table4_row_takes_spot_proper_and_pt_under_variant_paper(runs):
    # row 4P: SPOT (lab_fidelity) and PT (lab_variant_rows) at 500 queries, both at 50 (lab_paper_queries),
    # all under variant paper; a control at 50 queries and default-variant runs at 50 queries are neither arm
    arm = functools.partial(_paper_arm, runs)

    frame = pd.concat(
        [
            runs,
            arm("lab_fidelity", "sp", [70.0, 80.0, 90.0], **{"params.labels.num_queries": "500"}),
            arm("lab_variant_rows", "pt", [20.0, 25.0, 30.0], method="pt", **{"params.labels.num_queries": "500"}),
            arm("lab_paper_queries", "sp50", [60.0, 70.0, 77.0], **{"params.labels.num_queries": "50"}),
            arm("lab_paper_queries", "pt50", [10.0, 12.0, 20.0], method="pt", **{"params.labels.num_queries": "50"}),
            arm(
                "lab_paper_queries",
                "cb50",
                [0.0, 0.0, 0.0],
                **{"params.labels.num_queries": "50", "params.shaping.kind": "constant"},
            ),
            arm(
                "lab_paper_queries",
                "ss50",
                [99.0, 99.0, 99.0],
                **{"params.labels.num_queries": "50", "params.variant": "spot"},
            ),
        ],
        ignore_index=True,
    )
    rows = build(frame)
    r = _row(rows, "4P", "(spot")
    # SPOT: mean(60, 70, 77) - mean(70, 80, 90) = 69 - 80 = -11; PT: mean(10, 12, 20) - 25 = 14 - 25 = -11
    assert r.effect.value == pytest.approx(0.0)
    assert r.n_x == 6 and r.n_y == 6 and r.datasets == ["hopper-medium-replay (50 vs 500 queries)"]
    # every other row compares the arms at the set's most queries: 1P is mean(70, 80, 90) - mean(20, 25, 30) = 55
    # on 3 vs 3 runs (with the 50-query runs it would be 74.5 - 19.5), and says what it left out
    p = _row(rows, "1P", "spot vs pt")
    assert p.effect.value == pytest.approx(55.0) and p.n_x == 3 and p.n_y == 3
    assert "runs at fewer queries than their dataset's most left out (12 at 50; claim 4's arms)" in p.notes
    assert not any("fewer queries" in n for n in _row(rows, "1", "spot vs pt").notes)  # one query count
    shaped = frame.assign(**{"metrics.shaping/r_model_mean": 0.5, "metrics.shaping/r_final_mean": 0.5})
    (dose,) = doses(shaped)
    assert {a["label"]: a["runs"] for a in dose.arms} == {"PT": 3, "SPOT, cosine λ=1": 3}
    assert any("12 at 50" in n for n in dose.notes)
    # without the 50-query runs the row says what it needs
    rows = build(frame[frame["experiment"] != "lab_paper_queries"])
    r = _row(rows, "4P", "(spot")
    assert r.effect is None and any("needs spot and pt runs at two query counts" in n for n in r.notes)


def test_dose_response_table_and_rank_correlation_against_an_independent_bootstrap(runs):
    # PT (added 0) and three SPOT arms under variant paper with shaping metrics: added = r_final - r_model.
    # Scores ranked by added: 2 1 3 4 6 5 8 7 9 -> rank differences 1 1 0 0 1 1 1 1 0, sum of squares 6:
    # Spearman's rho = 1 - 6 * 6 / (9 * 80) = 0.95 (no ties)
    arm = functools.partial(_paper_arm, runs)

    def shaped(frame, added):
        return frame.assign(
            **{"metrics.shaping/r_model_mean": 0.5, "metrics.shaping/r_final_mean": [0.5 + a for a in added]}
        )

    frame = pd.concat(
        [
            runs,
            shaped(arm("lab_variant_rows", "pt", [12.0, 10.0, 14.0], method="pt"), [0.0, 0.01, 0.02]),
            shaped(
                arm("lab_paper_shaping", "c01", [16.0, 20.0, 18.0], **{"params.shaping.weight": "0.1"}),
                [0.06, 0.07, 0.08],
            ),
            # eval/length: two of the three runs logged it (the third ran before the metric): mean(500, 900) = 700
            shaped(arm("lab_fidelity", "sp", [70.0, 60.0, 80.0]), [0.6, 0.65, 0.7]).assign(
                **{"metrics.eval/length": [500.0, 900.0, np.nan]}
            ),
            arm("lab_paper", "mr", [30.0, 40.0, 50.0], method="mr"),  # MR: neither PT nor SPOT, left out
            arm("lab_paper_random", "rs", [1.0, 2.0, 3.0], **{"params.subgoal.source": "random"}),  # no metrics
            shaped(arm("lab_fidelity", "ss", [1.0, 2.0, 3.0], **{"params.variant": "spot"}), [0.9, 0.9, 0.9]),
        ],
        ignore_index=True,
    )
    (dose,) = doses(frame)
    assert dose.dataset == "hopper-medium-replay"
    arms = {a["label"]: a for a in dose.arms}
    assert list(arms) == ["PT", "SPOT, cosine λ=0.1", "SPOT, cosine λ=1"]
    assert arms["SPOT, cosine λ=0.1"]["added"] == pytest.approx(0.07) and arms["PT"]["runs"] == 3
    assert arms["SPOT, cosine λ=1"]["score"]["mean"] == pytest.approx(70.0)
    assert dose.rho.value == pytest.approx(0.95) and dose.rho.n == 9
    assert dose.notes == ["3 finished runs without the shaping metrics or a final score left out"]
    x = np.array([0.0, 0.01, 0.02, 0.06, 0.07, 0.08, 0.6, 0.65, 0.7])
    y = np.array([12.0, 10.0, 14.0, 16.0, 20.0, 18.0, 70.0, 60.0, 80.0])
    rng = np.random.default_rng(3)

    boot = []
    for _ in range(5000):
        i = rng.integers(0, 9, 9)
        if np.ptp(x[i]) > 0:  # Spearman's rho: Pearson's r of the ranks, ties given their mean rank
            boot.append(np.corrcoef(pd.Series(x[i]).rank(), pd.Series(y[i]).rank())[0, 1])
    lo, hi = np.percentile(boot, [2.5, 97.5])
    assert abs(dose.rho.low - lo) < 0.05 and abs(dose.rho.high - hi) < 0.02, (dose.rho, lo, hi)
    text = "\n".join(format_dose(dose))
    assert "| SPOT, cosine λ=0.1 | 3 | 0.070 | 18.0 ± 2.0 [" in text and "over the 9 runs: 0.95 [" in text
    assert "| SPOT, cosine λ=1 | 3 | 0.650 | 70.0 ± 10.0 [" in text and "| 700 (2 of 3) |" in text
    assert text.count("| – |\n") == 2  # PT's and λ=0.1's runs logged no length
    assert "final score on hopper-medium-replay (variant paper, set P)" in text


def test_a_long_experiment_set_is_named_by_its_key_and_listed_once(runs):
    frame = pd.concat(
        [
            runs,
            _paper_arm(runs, "lab_fidelity", "sp", [70.0, 80.0, 90.0]),
            _paper_arm(runs, "lab_variant_rows", "pt", [20.0, 25.0, 30.0], method="pt"),
        ],
        ignore_index=True,
    )
    text = text_of(build(frame))
    full = SET_P
    assert "| spot vs pt | set P | 55.0 [" in text and "3 vs 3 runs, 1 dataset |" in text
    assert text.count(full) == 1 and f"- set P: {full}" in text
    # two-experiment sets stay spelled out, with the plural
    assert "| spot vs pt | lab_table1+lab_table1_fr | 8.5 [" in text and "runs, 2 datasets |" in text


def test_dose_response_ranks_each_dataset_on_its_own(runs):
    # the same arms on a second dataset: Walker2d's scores sit lower, so pooling the 12 runs would rank them
    # against Hopper's; per dataset each ranking is exact (rho 1: scores rise with the added term on both)
    arm = functools.partial(_paper_arm, runs)

    def shaped(frame, added, dataset):
        cols = {"metrics.shaping/r_model_mean": 0.5, "metrics.shaping/r_final_mean": [0.5 + a for a in added]}
        return frame.assign(dataset=dataset, paper_dataset=dataset, **cols)

    hop, walk = "hopper-medium-replay", "walker2d-medium-replay"
    frame = pd.concat(
        [
            shaped(arm("lab_variant_rows", "pt", [20.0, 21.0, 22.0], method="pt"), [0.0, 0.01, 0.02], hop),
            shaped(arm("lab_fidelity", "sp", [60.0, 70.0, 80.0]), [0.6, 0.65, 0.7], hop),
            shaped(arm("lab_variant_rows", "wpt", [2.0, 3.0, 4.0], method="pt"), [0.0, 0.01, 0.02], walk),
            shaped(arm("lab_fidelity", "wsp", [5.0, 6.0, 7.0]), [0.6, 0.65, 0.7], walk),
        ],
        ignore_index=True,
    )
    found = doses(frame)
    assert [d.dataset for d in found] == [hop, walk]
    for d in found:
        assert d.rho.value == pytest.approx(1.0) and d.rho.n == 6
        assert [a["runs"] for a in d.arms] == [3, 3]
    assert found[1].arms[1]["score"]["mean"] == pytest.approx(6.0)


def test_a_comparison_over_runs_on_different_data_says_so(runs):
    assert not any("data digests" in n for r in build(runs) for n in r.notes)
    mixed = runs.copy()
    pt_hopper = mixed.index[
        (mixed["method"] == "pt") & (mixed["dataset"] == "hopper-medium-replay") & (mixed["status"] == "FINISHED")
    ]
    mixed.loc[pt_hopper[:1], "data_digest"] = "rebuilt-elsewhere-0123"
    r = _row(build(mixed), "1", "spot vs pt")
    assert (
        "hopper-medium-replay: the runs span 2 data digests (spot: 3 on digest-hoppe; "
        "pt: 2 on digest-hoppe, 1 on rebuilt-else); the arms may not share their data"
    ) in r.notes
    assert not any(n.startswith("walker2d-medium-replay: the runs span") for n in r.notes)


def test_oracle_with_minmax_rewards_is_its_own_reference_row_and_stays_out_of_oracle_proper(runs):
    # row OP: Oracle with relabel.normalize=minmax (lab_paper_oracle_minmax) against Oracle proper
    # (lab_variant_rows; a run without the key counts as Oracle proper); mean(60, 70, 80) - mean(20, 22, 24) = 48
    arm = functools.partial(_paper_arm, runs)
    frame = pd.concat(
        [
            runs,
            arm("lab_variant_rows", "or", [20.0, 22.0, 24.0], method="oracle"),  # the key missing: Oracle proper
            arm("lab_paper_oracle_minmax", "om", [60.0, 70.0, 80.0], method="oracle").assign(
                **{"params.relabel.normalize": "minmax"}
            ),
        ],
        ignore_index=True,
    )
    r = _row(build(frame), "OP", "oracle minmax vs oracle")
    assert r.effect.value == pytest.approx(48.0) and r.n_x == 3 and r.n_y == 3 and r.poi.value == 1.0
    # minmax Oracle runs in set P would not count as Oracle in row 1P's reference
    moved = frame.assign(experiment=frame["experiment"].replace("lab_paper_oracle_minmax", "lab_variant_rows"))
    moved = pd.concat([moved, arm("lab_fidelity", "sp", [50.0, 51.0, 52.0])], ignore_index=True)
    ref = _row(build(moved), "1P", "spot vs oracle")
    assert ref.means == pytest.approx((51.0, 22.0)) and ref.n_y == 3


def test_oracle_at_a_longer_discount_is_row_od_and_stays_out_of_every_other_oracle_arm(runs):
    # row OD: Oracle at iql.discount 0.995 (lab_oracle_discount, two seeds) against Oracle proper at 0.99
    # (lab_variant_rows, one run with the key and two without it): mean(40, 50) - mean(20, 22, 24) = 23
    arm = functools.partial(_paper_arm, runs)
    proper = arm("lab_variant_rows", "or", [20.0, 22.0, 24.0], method="oracle")
    proper.loc[proper.index[0], "params.iql.discount"] = "0.99"  # logged as a string; the others never logged it
    long = arm("lab_oracle_discount", "od", [40.0, 50.0, 0.0], method="oracle").iloc[:2]
    frame = pd.concat([runs, proper, long.assign(**{"params.iql.discount": 0.995})], ignore_index=True)
    r = _row(build(frame), "OD", "oracle γ=0.995 vs oracle")
    assert r.effect.value == pytest.approx(23.0) and (r.n_x, r.n_y) == (2, 3)
    assert r.verdict.startswith("too few")  # 2 seeds < MIN_SEEDS: the effect and CI are shown, no verdict
    # the 0.995 runs never count as Oracle proper: not in row OP's reference, nor in 1P's (moved to set P)
    minmax = arm("lab_paper_oracle_minmax", "om", [60.0, 70.0, 80.0], method="oracle")
    frame = pd.concat([frame, minmax.assign(**{"params.relabel.normalize": "minmax"})], ignore_index=True)
    assert _row(build(frame), "OP", "oracle minmax vs oracle").means == pytest.approx((70.0, 22.0))
    moved = frame.assign(experiment=frame["experiment"].replace("lab_oracle_discount", "lab_variant_rows"))
    moved = pd.concat([moved, arm("lab_fidelity", "sp", [50.0, 51.0, 52.0])], ignore_index=True)
    assert _row(build(moved), "1P", "spot vs oracle").means == pytest.approx((51.0, 22.0))


def test_oracle_with_corls_iql_is_row_oc_and_stays_out_of_every_other_oracle_arm(runs):
    # row OC: Oracle with a deterministic actor and iql.tau 0.001 (lab_oracle_corl) against Oracle proper
    # (lab_variant_rows: one run logging the default tau as a string, two without the key):
    # mean(40, 30, 17) - mean(20, 22, 24) = 29 - 22 = 7
    arm = functools.partial(_paper_arm, runs)
    proper = arm("lab_variant_rows", "or", [20.0, 22.0, 24.0], method="oracle")
    proper.loc[proper.index[0], "params.iql.tau"] = "0.005"
    corl = arm("lab_oracle_corl", "oc", [40.0, 30.0, 17.0], method="oracle").assign(
        **{"params.iql.actor_dist": "deterministic", "params.iql.tau": 0.001}
    )
    # an Oracle run with only one of the two settings belongs to neither arm
    tau_only = arm("lab_oracle_corl", "ot", [90.0, 0.0, 0.0], method="oracle").iloc[:1]
    tau_only = tau_only.assign(**{"params.iql.tau": "0.001", "params.iql.actor_dist": "gaussian"})
    frame = pd.concat([runs, proper, corl, tau_only], ignore_index=True)
    assert _row(build(frame), "OC", "oracle corl vs oracle").effect is None  # not in the default set O
    use = {"O": ("lab_variant_rows", "lab_oracle_corl", "lab_paper_oracle_minmax")}
    r = _row(build(frame, use), "OC", "oracle corl vs oracle")
    assert r.effect.value == pytest.approx(7.0) and (r.n_x, r.n_y) == (3, 3)
    assert r.means == pytest.approx((29.0, 22.0))
    # the CORL runs never count as Oracle proper: not in row OP's reference, nor in 1P's (moved to set P)
    minmax = arm("lab_paper_oracle_minmax", "om", [60.0, 70.0, 80.0], method="oracle")
    frame = pd.concat([frame, minmax.assign(**{"params.relabel.normalize": "minmax"})], ignore_index=True)
    assert _row(build(frame, use), "OP", "oracle minmax vs oracle").means == pytest.approx((70.0, 22.0))
    moved = frame.assign(experiment=frame["experiment"].replace("lab_oracle_corl", "lab_variant_rows"))
    moved = pd.concat([moved, arm("lab_fidelity", "sp", [50.0, 51.0, 52.0])], ignore_index=True)
    assert _row(build(moved), "1P", "spot vs oracle").means == pytest.approx((51.0, 22.0))


def test_a_verdict_that_another_bootstrap_seed_changes_is_marked_borderline():
    row = compare.Row("CP", "text", "a vs b", "exp", "last", min_n=3, perm_p=0.01)
    row.effect = stats.Estimate(15.9, 0.3, 31.1, 12, other_verdicts=(stats.INCONCLUSIVE,))
    assert row.verdict == "supported (borderline: inconclusive under another bootstrap seed)"
    row.effect = stats.Estimate(15.9, 0.3, 31.1, 12)
    assert row.verdict == stats.SUPPORTED


def test_a_verdict_without_a_permutation_test_says_it_is_the_cis_alone():
    # claim 4 without seed-matched gains has no permutation test (perm_p nan): its CI decides, and says so
    row = compare.Row("4P", "text", "(spot few − most) − (pt few − most)", "exp", "last", min_n=3)
    row.effect = stats.Estimate(-27.7, -53.3, -2.6, 16)
    assert row.verdict == "not supported (the CI alone: no permutation test for this effect)"
    row.effect = stats.Estimate(-27.7, -53.3, 2.6, 16)
    assert row.verdict == stats.INCONCLUSIVE
    # with the seed-matched gains' test (perm_p set) the verdict needs it too
    row.effect, row.perm_p = stats.Estimate(-27.7, -53.3, -2.6, 16), 12 / 56
    assert row.verdict == "inconclusive (the CI alone: not supported; permutation p = 0.21)"
    row.perm_p = 0.01
    assert row.verdict == stats.NOT_SUPPORTED


def test_seed_matched_differences_against_an_independent_bootstrap(runs):
    r = _row(build(runs), "1", "spot vs pt")
    # SPOT − PT at seeds 0, 1, 2: hopper 61−50, 64−52, 66−57 = 11, 12, 9; walker 65−58, 69−61, 64−60 = 7, 8, 4
    seeds, hopper = r.pairs["hopper-medium-replay"]
    assert list(seeds) == [0, 1, 2] and list(hopper) == [11.0, 12.0, 9.0]
    assert list(r.pairs["walker2d-medium-replay"][1]) == [7.0, 8.0, 4.0]
    assert r.paired.value == pytest.approx((32 / 3 + 19 / 3) / 2)
    d = [np.array([11.0, 12, 9]), np.array([7.0, 8, 4])]
    rng = np.random.default_rng(3)
    boot = [np.mean([rng.choice(a, 3).mean() for a in d]) for _ in range(20000)]
    lo, hi = np.percentile(boot, [2.5, 97.5])
    assert abs(r.paired.low - lo) < 0.15 and abs(r.paired.high - hi) < 0.15
    # narrower than the unpaired CI: the seed's shifts cancel in the differences
    assert r.paired.high - r.paired.low < r.effect.high - r.effect.low
    # the reading is the exact sign-flip test's: all 6 differences positive, and of the 2^6 sign patterns
    # only all-plus and all-minus reach |mean of means| >= 8.5: p = 2/64
    assert r.paired_p == pytest.approx(2 / 64)
    assert r.paired_verdict == stats.SUPPORTED
    text = text_of(build(runs))
    assert "### Seed-matched differences" in text
    assert "hopper-medium-replay: s0 +11.0, s1 +12.0, s2 +9.0; walker2d-medium-replay: s0 +7.0" in text


def test_seed_matched_differences_leave_out_unmatched_seeds_and_need_one_run_per_seed(runs):
    hopper_spot = (runs["method"] == "spot") & (runs["dataset"] == "hopper-medium-replay")
    without_s1 = runs[~(hopper_spot & (runs["seed"] == 1))]
    r = _row(build(without_s1), "1", "spot vs pt")
    seeds, diffs = r.pairs["hopper-medium-replay"]
    assert list(seeds) == [0, 2] and list(diffs) == [11.0, 9.0]  # PT's seed 1 has no SPOT run to pair with
    assert r.paired_verdict == stats.TOO_FEW and r.verdict == stats.TOO_FEW
    # a second SPOT config in the arm (another run at seed 0): no single pair per seed, no paired reading
    extra = runs[hopper_spot & (runs["seed"] == 0)].assign(run_id="run999", config_hash="ffffffffffffffff")
    r = _row(build(pd.concat([runs, extra], ignore_index=True)), "1", "spot vs pt")
    assert r.paired is None and r.paired_verdict == "no pairs" and r.effect is not None


def test_sign_flip_p_counts_sign_patterns_by_hand():
    # 3 differences all positive: 2 of the 8 patterns (all +, all −) are as extreme
    assert stats.sign_flip_p([[27.5, 7.7, 36.1]]) == pytest.approx(2 / 8)
    # 1, −2, 3 (mean 2/3): the signed sums are ±6, ±4, ±2, 0, 0; six of eight reach |sum| >= 2
    assert stats.sign_flip_p([[1.0, -2.0, 3.0]]) == pytest.approx(6 / 8)
    # two datasets weigh the same: the mean of means of (1, 1) and (10,) is 5.5, reached only by
    # the all-plus and all-minus patterns of the 2^3 = 8: flipping 10 alone gives -4.5, flipping
    # one 1 gives 5.0
    assert stats.sign_flip_p([[1.0, 1.0], [10.0]]) == pytest.approx(2 / 8)
    assert np.isnan(stats.sign_flip_p([]))
    # one difference: +d and -d are equally extreme, p = 2/2 (a one-seed smoke report must not crash)
    assert stats.sign_flip_p([[4.2]]) == 1.0 and stats.sign_flip_p([[-3.0]]) == 1.0


def test_a_failing_permutation_test_drops_the_borderline_note():
    # the CI is inconclusive and another bootstrap seed would say supported, but the permutation test
    # fails: no bootstrap seed can make this row pass, so no borderline note
    row = compare.Row("CP", "t", "c", "e", "last", min_n=3, perm_p=0.1)
    row.effect = stats.Estimate(15.9, -0.3, 31.1, 6, other_verdicts=(stats.SUPPORTED,))
    assert row.verdict == stats.INCONCLUSIVE
    row.perm_p = 0.01
    assert row.verdict.startswith("inconclusive (borderline: supported")


def test_planning_section_sizes_the_next_runs_from_the_pooled_sd(runs):
    from scipy import stats as sps

    rows = build(runs)
    r = _row(rows, "1", "spot vs pt")
    # within-dataset sums of squares: hopper SPOT (61, 64, 66) 38/3, PT (50, 52, 57) 26; walker SPOT
    # (65, 69, 64) 14, PT (58, 61, 60) 14/3; 172/3 over 8 dof
    sd = np.sqrt(172 / 3 / 8)
    assert r.plan.sd == pytest.approx(sd)
    # the smallest effect a t-test finds 80 % of the time: the mean of two datasets' differences of
    # 3 vs 3 runs is as precise as 6 vs 6 runs, with the pooled sd's 8 dof (noncentral t by hand)
    d, crit = r.plan.mde / sd, sps.t.ppf(0.975, 8)
    nc = d / np.sqrt(1 / 6 + 1 / 6)
    assert sps.nct.sf(crit, 8, nc) + sps.nct.cdf(-crit, 8, nc) == pytest.approx(0.8, abs=1e-3)
    # the observed 8.5 is 3.2 sd: the permutation test's floor on two datasets (3 per arm) is enough
    assert r.plan.runs == 3
    text = text_of(rows)
    assert "### Runs for a verdict (planning numbers, not findings)" in text
    assert f"| 1 | spot vs pt | last | 6 vs 6 runs, 2 datasets | {sd:.1f} | {r.plan.mde:.1f} | +8.5 | 3 |" in text


def test_planning_section_counts_the_missing_runs_and_their_logged_time(runs):
    rows = build(runs)  # the fixture logs no run time
    mr = _row(rows, "1", "spot vs mr")  # inconclusive: the runs still to do are listed
    need = int(mr.plan.runs)
    assert mr.sizes == ([3, 3], [3, 3]) and need > 3
    assert report.still_to_do(mr) == f"{2 * (need - 3):,} + {2 * (need - 3):,} (time not logged)"
    timed = runs.copy()
    timed[compare.RUN_TIME] = np.where(timed["method"] == "mr", 1800.0, 900.0)  # MR runs 30 min, SPOT 15
    mr = _row(build(timed), "1", "spot vs mr")
    missing = 2 * (need - 3)  # per arm: two datasets short of `need` by 3 runs each
    hours = missing * (900 + 1800) / 3600
    assert report.still_to_do(mr) == f"{missing:,} + {missing:,} ({hours:,.0f} h)"
    pt = _row(rows, "1", "spot vs pt")  # supported at this n: nothing to do
    assert report.still_to_do(pt) == "none: a verdict at this n"


# --------------------------------------------------------------------------- the studies' reports, rebuilt
def _rebuild_commands() -> list[list[str]]:
    """Every `spot ...` line of every study's rebuild.sh, ``$D`` replaced by the study folder."""
    out = []
    for script in sorted((ROOT / "experiments").glob("*/rebuild.sh")):
        text = script.read_text()
        folder = re.search(r"^D=(\S+)$", text, flags=re.M).group(1)
        for line in text.splitlines():
            if line.startswith("spot "):
                out.append([arg.replace("$D", folder) for arg in shlex.split(line, comments=True)])
    return out


REBUILDS = _rebuild_commands()


def test_every_committed_report_has_its_rebuild_line():
    committed = {
        p.relative_to(ROOT).as_posix() for p in (ROOT / "experiments").glob("*/*.md") if p.name not in ("NOTES.md",)
    }
    written = {argv[argv.index("--out") + 1] for argv in REBUILDS}
    assert written == committed and len(written) == 6, written ^ committed


@pytest.mark.parametrize("argv", REBUILDS, ids=[argv[argv.index("--out") + 1] for argv in REBUILDS])
def test_committed_reports_and_tables_rebuild_byte_identical_from_their_study_folders(argv, tmp_path, monkeypatch):
    """Each rebuild.sh line, with its --out in tmp_path, writes exactly the committed file: the
    reports from the studies' claims files, lab_table1.md from the study's `tables` entry."""
    from spot import cli

    committed = ROOT / argv[argv.index("--out") + 1]
    argv = [tmp_path / committed.name if a == argv[argv.index("--out") + 1] else a for a in argv]
    monkeypatch.chdir(ROOT)
    assert cli.main([str(a) for a in argv[1:]]) == 0
    assert (tmp_path / committed.name).read_bytes() == committed.read_bytes()


# --------------------------------------------------------------------------- a new question, no code
MY_CLAIMS = """\
# a question the lab never asked: does MR beat PT on hopper-full-replay?
results: [results]
sets:
  FR: [lab_hopper_fr_pf, lab_hopper_fr_pf_seeds34, lab_hopper_fr_pf_queries]
claims:
  - id: Q1
    text: MR ≥ PT on hopper-full-replay (variant paper)
    comparison: mr vs pt
    set: FR
    variant: paper
    datasets: [hopper-full-replay]
    x: {method: mr}
    y: {method: pt}
    labels: [mr, pt]
    metrics: [last]
"""


def test_a_new_claims_file_over_committed_runs_prints_its_verdict(tmp_path):
    study = ROOT / "experiments" / "lab-hopper-full-replay" / "results"
    (tmp_path / "results").mkdir()
    for f in study.glob("*.csv"):
        shutil.copy(f, tmp_path / "results" / f.name)
    path = tmp_path / "my_claims.yaml"
    path.write_text(MY_CLAIMS)
    p = run_cli("report", "--claims", str(path), cwd=ROOT / "tests")  # its results: relative to the file
    assert p.returncode == 0, p.stderr
    # the same question by hand: the set's finished runs under variant paper, at the dataset's most queries
    df = pd.concat([pd.read_csv(f) for f in sorted(study.glob("*.csv"))], ignore_index=True)
    df = df[df["experiment"].isin(["lab_hopper_fr_pf", "lab_hopper_fr_pf_seeds34", "lab_hopper_fr_pf_queries"])]
    fewer = int((df["params.labels.num_queries"] < df["params.labels.num_queries"].max()).sum())  # at 50, not 500
    df = df[(df["status"] == "FINISHED") & (df["params.variant"] == "paper")]
    df = df[df["params.labels.num_queries"] == df["params.labels.num_queries"].max()]
    assert not df.duplicated(["config_hash", "seed"]).any()
    mr = df.loc[df["method"] == "mr", "metrics.eval/score_final"].to_numpy()
    pt = df.loc[df["method"] == "pt", "metrics.eval/score_final"].to_numpy()
    assert len(mr) == len(pt) == 5
    effect = mr.mean() - pt.mean()
    pooled = np.concatenate([mr, pt])  # the exact permutation test over the C(10, 5) splits
    diffs = [pooled[list(c)].mean() - np.delete(pooled, list(c)).mean() for c in itertools.combinations(range(10), 5)]
    perm = min(1.0, 2 * min(np.mean(np.array(diffs) >= effect - 1e-9), np.mean(np.array(diffs) <= effect + 1e-9)))
    assert perm == pytest.approx(2 / 252)  # every MR run above every PT run
    head = (
        "| Q1 | MR ≥ PT on hopper-full-replay (variant paper) | mr vs pt "
        f"| lab_hopper_fr_pf+lab_hopper_fr_pf_seeds34+lab_hopper_fr_pf_queries | {effect:.1f} ["
    )
    row = next(line for line in p.stdout.splitlines() if line.startswith("| Q1 |"))
    assert row.startswith(head), (row, head)
    assert row.endswith(f"| {mr.mean():.1f} / {pt.mean():.1f} | 5 vs 5 runs, 1 dataset | {perm:.2g} | supported |")
    assert f"runs at fewer queries than their dataset's most left out ({fewer} at 50;" in p.stdout and fewer == 6
    assert "Best evaluation" not in p.stdout  # metrics: [last] only


def test_the_default_claims_file_is_the_papers_claims_with_generic_names():
    paper = claims.load()
    assert [c.id for c in paper.claims] == ["1", "1", "2", "3", "4", "5", "6", "C", "C", "C"]
    assert paper.sets["table1"].experiments == ("table1",) and not paper.results
    text = claims.default_file().read_text()
    assert "lab_" not in text and paper.claims[6].metrics == ("ood",)


@pytest.mark.parametrize(
    "body, message",
    [
        ("claims: [{id: a}]\nnope: 1\n", "unknown key 'nope'"),
        ("claims: [{id: a, text: t, comparison: c, set: S, x: {method: a}, y: {method: b}}]\n", "set 'S' is not"),
        (
            "sets: {S: [e]}\nclaims: [{id: a, text: t, comparison: c, set: S, x: spot2, y: {method: b}}]\n",
            r"claims\[0\].x: no filter named 'spot2'",
        ),
        (
            "sets: {S: [e]}\nclaims: [{id: a, text: t, comparison: c, set: S, x: {methods: a}, y: {method: b}}]\n",
            r"claims\[0\].x: unknown key 'methods'",
        ),
        (
            "sets: {S: [e]}\nclaims: [{id: a, text: t, comparison: c, set: S, test: t-test, x: {method: a}}]\n",
            "test: 't-test'; expected one of difference, runner-up, queries, dose-response",
        ),
        ("sets: {S: [e]}\nclaims: [{id: a, text: t, comparison: c, set: S, x: {method: a}}]\n", "needs an arm 'y'"),
        (
            "sets: {S: [e]}\nclaims: [{id: a, text: t, comparison: c, set: S, x: {params: {k: {over: 1}}}, y: b}]\n",
            r"x.params.k: expected a value or one of \{not, in, other_than\}",
        ),
        (
            "sets: {S: [e]}\nfilters: {f: {none: [f]}}\n"
            "claims: [{id: a, text: t, comparison: c, set: S, x: f, y: f}]\n",
            "filter 'f' refers to itself",
        ),
        ("extends: me.yaml\n", "extends .*me.yaml, which extends it back"),
        ("sets: {S: [e]}\n", "no claims"),
    ],
)
def test_a_bad_claims_file_is_one_clear_error_naming_the_file_and_key(tmp_path, body, message):
    path = tmp_path / "me.yaml"
    path.write_text(body)
    with pytest.raises(SpotError, match=message) as err:
        claims.load(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_filters_select_by_hand():
    """Each filter condition on a small frame, the runs it keeps counted by hand."""
    frame = pd.DataFrame(
        {
            "method": ["spot", "spot", "spot", "pt", "oracle"],
            "dataset": ["h", "h", "w", "h", "h"],
            "params.variant": [np.nan, "paper", "paper", "paper", "spot"],  # NaN: logged before the key
            "params.shaping.weight": ["1.0", "0.5", np.nan, np.nan, "1"],
            "params.iql.discount": ["0.99", "0.995", np.nan, "0.99", "0.995"],
        }
    )

    def kept(spec, named=None):
        return list(frame.index[claims.select.compile_filter(spec, named or {}, "test")(frame)])

    assert kept({"variant": "spot"}) == [0, 4]  # runs without the key count as the default variant
    assert kept({"method": ["spot", "pt"], "dataset": "h"}) == [0, 1, 3]
    assert kept({"params": {"shaping.weight": 1.0}}) == [0, 4]  # numbers compare as numbers: "1" is 1.0
    assert kept({"params": {"shaping.weight": "1.0"}}) == [0]  # text compares as text
    assert kept({"params": {"shaping.weight": {"other_than": 1.0}}}) == [1]  # unlogged = the default
    assert kept({"params": {"shaping.weight": {"not": 1.0}}}) == [1, 2, 3]
    assert kept({"params": {"iql.discount": {"in": [0.995, 0.9]}}}) == [1, 4]
    named = {"long": {"params": {"iql.discount": {"other_than": 0.99}}}}
    assert kept({"method": "spot", "none": ["long"]}, named) == [0, 2]
    assert kept({"any": ["long", {"method": "pt"}]}, named) == [1, 3, 4]


def test_report_takes_a_study_folder_or_a_claims_file_not_both(tmp_path):
    p = run_cli("report", "experiments/lab-walker2d", "--claims", "x.yaml", cwd=ROOT)
    assert p.returncode == 2 and p.stderr.startswith("error: spot report: give a study folder"), p.stderr
    p = run_cli("report", str(tmp_path))
    assert p.returncode == 2 and "has no claims.yaml" in p.stderr, p.stderr
    p = run_cli("report", "experiments/lab-walker2d", "--use", "Q=lab_walker", cwd=ROOT)
    assert p.returncode == 2 and "has no set 'Q'" in p.stderr, p.stderr
