"""Issue 41, items 3-5 (the reporting side): claims paired by design and their exact sign-flip
verdict, the mean of a run's last K evaluations, claims amended by a file that extends another,
arms that mix configs, the runs a report leaves out, and the hopper-full-replay study's claims
file before and after its paired launch is exported."""

import itertools
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from spot import SpotError
from spot.results import claims, compare, load, report, stats
from spot.results.select import finished

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "experiments" / "lab-hopper-full-replay"


def _brute_sign_flip(diffs) -> float:
    """Two-sided p of the mean over every sign assignment, counted directly (|mean| as extreme)."""
    d = np.asarray(diffs, np.float64)
    observed = abs(d.mean())
    means = [abs(np.mean(np.array(s) * d)) for s in itertools.product((1.0, -1.0), repeat=len(d))]
    return sum(m >= observed - 1e-12 for m in means) / len(means)


# --------------------------------------------------------------------------- the sign-flip test
def test_sign_flip_p_is_exact_over_every_sign_assignment():
    # [1, -2, 3]: sum 2. The 8 assignments' sums: +1-2+3 = 2, -1-2+3 = 0, +1+2+3 = 6, -1+2+3 = 4,
    # +1-2-3 = -4, -1-2-3 = -6, +1+2-3 = 0, -1+2-3 = -2; six of them reach |sum| >= 2: p = 6/8
    assert stats.sign_flip_p([[1.0, -2.0, 3.0]]) == pytest.approx(6 / 8)
    # ten differences of one sign: only the all-plus and all-minus assignments are as extreme: 2/1024
    assert stats.sign_flip_p([[3, 1, 4, 1, 5, 9, 2, 6, 5, 3]]) == pytest.approx(2 / 1024)
    mixed = [4.7, -0.5, 12.2, -11.6, 0.9, 3.0, -1.0, 2.0, 5.0, -7.0]
    assert stats.sign_flip_p([mixed]) == pytest.approx(_brute_sign_flip(mixed))
    assert stats.sign_flip_exact(10) and stats.sign_flip_exact(14)  # 16,384 <= 20,000 resamples
    assert not stats.sign_flip_exact(15) and not stats.sign_flip_exact(0)


# --------------------------------------------------------------------------- the mean of the last K evaluations
def test_mean_last_reads_the_last_k_periodic_evaluations_by_step():
    runs = pd.DataFrame(
        {
            "run_id": ["a", "b", "c", "d"],
            load.CURVE_COLUMN: [
                "0:1;10:2;20:3;30:4;40:5",  # (3 + 4 + 5) / 3 = 4
                "40:8;0:100;20:2;10:1;30:5",  # listed out of order: steps 20, 30, 40 -> (2 + 5 + 8) / 3 = 5
                "0:9;10:1;20:2",  # two periodic evaluations: step 0 does not count
                np.nan,  # no curve
            ],
        }
    )
    values = compare.mean_last(runs, 3)
    assert values.iloc[0] == pytest.approx(4.0) and values.iloc[1] == pytest.approx(5.0)
    assert np.isnan(values.iloc[2]) and np.isnan(values.iloc[3])
    assert compare.mean_last(runs, 2).iloc[2] == pytest.approx(1.5)
    assert compare.mean_last(runs.drop(columns=[load.CURVE_COLUMN]), 3).isna().all()


def test_last_k_metric_names_and_their_validation(tmp_path):
    assert claims.last_k("last3") == 3 and claims.last_k("last") is None and claims.last_k("best") is None
    assert claims.metric_column("last3") == "curve.eval/score.mean_last3"
    assert claims.metric_column("last") == "metrics.eval/score_final"
    assert claims.metric_column("reward/corr_true") == "metrics.reward/corr_true"
    for bad in ("last1", "last0"):
        path = tmp_path / f"{bad}.yaml"
        path.write_text(_claims_yaml(metrics=f"[last, {bad}]"))
        with pytest.raises(SpotError, match=f"metrics: '{bad}'; lastK takes K of 2 or more"):
            claims.load(path)


# --------------------------------------------------------------------------- a synthetic paired design
SEEDS = range(10)
DIFFS = [3.0, 1.0, 4.0, 1.0, 5.0, 9.0, 2.0, 6.0, 5.0, 3.0]  # x − y of each seed's final score


def _claims_yaml(metrics: str = "[last, last3, best]", paired: str = "true", extra: str = "") -> str:
    return f"""\
results: [runs.csv]
sets:
  S: [exp]
claims:
  - id: Q
    text: a beats b
    comparison: a vs b
    set: S
    x: {{params: {{arm: a}}}}
    y: {{params: {{arm: b}}}}
    labels: [a, b]
    metrics: {metrics}
    paired: {paired}
{extra}"""


def _run(run_id, arm, seed, final, curve, status="FINISHED", start="2026-12-01 10:00:00", config=None):
    return {
        "run_id": run_id,
        "experiment": "exp",
        "status": status,
        "method": "spot",
        "dataset": "hopper-medium-replay",
        "seed": seed,
        "config_hash": config or f"cfg-{arm}",
        "start_time": start,
        "end_time": "2026-12-01 10:01:40",
        "params.arm": arm,
        "metrics.eval/score_final": final,
        "metrics.eval/score_best": final + 1.0,
        load.CURVE_COLUMN: curve,
    }


def _paired_frame(tmp_path) -> pd.DataFrame:
    """Per seed an a run and a b run. b: final 50, curve 0:0;100:10;200:20;300:30;400:50 (last three
    20, 30, 50: mean 100/3); a: d higher at steps 200 and 400 (last three: (100 + 2d)/3)."""
    rows = []
    for s, d in zip(SEEDS, DIFFS, strict=True):
        rows.append(_run(f"a{s}", "a", s, 50 + d, f"0:0;100:10;200:{20 + d};300:30;400:{50 + d}"))
        rows.append(_run(f"b{s}", "b", s, 50.0, "0:0;100:10;200:20;300:30;400:50"))
    pd.DataFrame(rows).to_csv(tmp_path / "runs.csv", index=False)
    return load.read(tmp_path / "runs.csv")


def _rows(frame, path):
    return report.build(frame, claims.load(path))


def test_a_claim_paired_by_design_gets_the_exact_sign_flip_verdict(tmp_path):
    frame = _paired_frame(tmp_path)
    (tmp_path / "claims.yaml").write_text(_claims_yaml())
    built = _rows(frame, tmp_path / "claims.yaml")
    last = next(r for r in built.rows if r.stat == "last")
    assert last.by_design and list(last.pairs["hopper-medium-replay"][0]) == list(SEEDS)
    assert last.paired.value == pytest.approx(np.mean(DIFFS))  # 3.9
    assert last.paired_p == pytest.approx(2 / 1024)  # every difference positive: 2 of 2^10 assignments
    assert last.paired_verdict == stats.SUPPORTED
    text = report.format_report(built)
    section = text.split("### Paired verdicts (seed-matched by design)")[1].split("###")[0]
    line = next(x for x in section.splitlines() if x.startswith("| Q |") and "| last |" in x)
    assert "| 10 | s0 +3.0, s1 +1.0, s2 +4.0" in line
    assert "| 3.9 [" in line and "| 0.00195 (exact: all 2^10 = 1,024 assignments) | supported |" in line
    # the main table keeps the unpaired verdict and points at the paired one
    assert "(unpaired; paired by design: supported, below)" in text
    # not repeated in the second-reading section
    assert "Seed-matched differences (a second reading" not in text


def test_the_last3_table_reads_each_runs_last_three_evaluations(tmp_path):
    frame = _paired_frame(tmp_path)
    (tmp_path / "claims.yaml").write_text(_claims_yaml())
    built = _rows(frame, tmp_path / "claims.yaml")
    assert [r.stat for r in built.rows] == ["last", "last3", "best"]  # last3 right after the final score
    r = next(r for r in built.rows if r.stat == "last3")
    # per seed: (100 + 2d)/3 − 100/3 = 2d/3; means: a (100 + 2·3.9)/3, b 100/3
    assert r.means == pytest.approx(((100 + 2 * 3.9) / 3, 100 / 3))
    assert r.effect.value == pytest.approx(2 * 3.9 / 3)
    assert list(r.pairs["hopper-medium-replay"][1]) == pytest.approx([2 * d / 3 for d in DIFFS])
    text = report.format_report(built)
    assert "### Mean of the last 3 evaluations (each run's last 3 points of `curve.eval/score`)" in text
    # planning numbers are for the verdict's statistic, not for the description beside it
    plan = text.split("### Runs for a verdict")[1].split("###")[0]
    assert "| last3 |" not in plan and "| last |" in plan


def test_runs_with_short_curves_are_named_for_last3(tmp_path):
    frame = _paired_frame(tmp_path)
    frame.loc[frame["run_id"] == "a0", load.CURVE_COLUMN] = "0:0;100:10;200:20"
    (tmp_path / "claims.yaml").write_text(_claims_yaml())
    rows = _rows(frame, tmp_path / "claims.yaml").rows
    r = next(r for r in rows if r.stat == "last3")
    assert r.n_x == 9 and r.n_y == 10
    assert any("1 finished run(s) have fewer than 3 evaluations" in n for n in r.notes)
    assert not any("fewer than 3 evaluations" in n for n in next(r for r in rows if r.stat == "last").notes)


def test_a_paired_claim_with_mixed_signs_and_few_pairs(tmp_path):
    frame = _paired_frame(tmp_path)
    keep = frame["seed"].isin([0, 1, 2])
    frame = frame[keep].copy()
    # a − b at seeds 0, 1, 2: 1, −2, 3 (p = 6/8, worked out in the sign-flip test above)
    for s, d in zip((0, 1, 2), (1.0, -2.0, 3.0), strict=True):
        frame.loc[frame["run_id"] == f"a{s}", "metrics.eval/score_final"] = 50 + d
    (tmp_path / "claims.yaml").write_text(_claims_yaml(metrics="[last]"))
    r = _rows(frame, tmp_path / "claims.yaml").rows[0]
    assert r.paired_p == pytest.approx(6 / 8) and r.paired_verdict == stats.INCONCLUSIVE
    frame = frame[frame["seed"].isin([0, 1])]
    r = _rows(frame, tmp_path / "claims.yaml").rows[0]
    assert r.paired_verdict == stats.TOO_FEW


def test_a_paired_claim_without_runs_renders_as_no_runs(tmp_path):
    frame = _paired_frame(tmp_path)
    frame = frame[frame["params.arm"] == "a"]
    (tmp_path / "claims.yaml").write_text(_claims_yaml(metrics="[last, last3]"))
    text = report.format_report(_rows(frame, tmp_path / "claims.yaml"))
    section = text.split("### Paired verdicts (seed-matched by design)")[1]
    assert "| Q | a beats b | a vs b | last | 0 | – | – | – | no runs |" in section


def test_paired_must_be_true_or_false(tmp_path):
    (tmp_path / "claims.yaml").write_text(_claims_yaml(paired="'yes'"))
    with pytest.raises(SpotError, match=r"claims\[0\]: paired: expected true or false"):
        claims.load(tmp_path / "claims.yaml")


# --------------------------------------------------------------------------- amend and note
BASE = """\
sets:
  S: [exp]
  T: [exp, exp2]
claims:
  - id: Q
    text: a beats b
    comparison: a vs b
    set: S
    x: {params: {arm: a}}
    y: {params: {arm: b}}
  - id: R
    text: b beats a
    comparison: b vs a
    set: S
    x: {params: {arm: b}}
    y: {params: {arm: a}}
"""


def test_a_file_amends_the_claims_it_extends(tmp_path):
    (tmp_path / "base.yaml").write_text(BASE)
    (tmp_path / "study.yaml").write_text(
        "extends: base.yaml\n"
        "amend:\n"
        "  - {id: Q, comparison: a vs b, set: T, paired: true, metrics: [last, last3], note: why a}\n"
        "claims:\n"
        "  - {id: Z, text: z, comparison: a vs b again, set: S, x: {params: {arm: a}}, y: {params: {arm: b}}}\n"
    )
    loaded = claims.load(tmp_path / "study.yaml")
    q, r, z = loaded.claims
    assert (q.sets, q.paired, q.metrics, q.note, q.text) == (("T",), True, ("last", "last3"), "why a", "a beats b")
    assert (r.sets, r.paired, r.note) == (("S",), False, "")  # the other claim as it was
    assert z.id == "Z"
    assert claims.load(tmp_path / "base.yaml").claims[0].sets == ("S",)  # the base file unchanged


@pytest.mark.parametrize(
    ("amend", "match"),
    [
        ("[{id: Q, comparison: b vs a, paired: true}]", "amend\\[0\\]: no claim has id 'Q' and comparison 'b vs a'"),
        ("[{id: Q, comparison: a vs b}]", "amend\\[0\\]: expected \\{id, comparison\\} of a claim and the keys"),
        ("[{id: Q, comparison: a vs b, colour: red}]", "amend\\[0\\]: unknown key 'colour'"),
        ("{id: Q}", "amend: expected a list"),
        ("[{id: Q, comparison: a vs b, set: nope}]", "set 'nope' is not in the file's sets"),
    ],
)
def test_a_bad_amendment_is_one_error(tmp_path, amend, match):
    (tmp_path / "base.yaml").write_text(BASE)
    (tmp_path / "study.yaml").write_text(f"extends: base.yaml\namend: {amend}\n")
    with pytest.raises(SpotError, match=match):
        claims.load(tmp_path / "study.yaml")


def test_a_claims_note_goes_to_the_reports_notes(tmp_path):
    frame = _paired_frame(tmp_path)
    (tmp_path / "claims.yaml").write_text(_claims_yaml(metrics="[last]") + "    note: the b arm is the paper's\n")
    text = report.format_report(_rows(frame, tmp_path / "claims.yaml"))
    assert "- claim Q (a vs b, exp): the b arm is the paper's" in text


# --------------------------------------------------------------------------- mixed configs and left-out runs
def test_an_arm_whose_runs_logged_different_values_gets_a_note(tmp_path):
    frame = _paired_frame(tmp_path)
    frame["params.reward.length"] = np.where(frame["seed"] < 5, "epochs", "steps")
    frame["params.cvae.holdout"] = frame["seed"].map(lambda s: None if s < 5 else "0.0")  # logged by some runs only
    (tmp_path / "claims.yaml").write_text(_claims_yaml(metrics="[last]"))
    r = _rows(frame, tmp_path / "claims.yaml").rows[0]
    mixed = [n for n in r.notes if "mixes configs" in n]
    assert mixed == [
        "hopper-medium-replay: the a runs differ in reward.length: 5 at epochs, 5 at steps; the arm mixes configs",
        "hopper-medium-replay: the b runs differ in reward.length: 5 at epochs, 5 at steps; the arm mixes configs",
    ]
    frame["params.reward.length"] = "steps"
    assert not [n for n in _rows(frame, tmp_path / "claims.yaml").rows[0].notes if "mixes configs" in n]


def test_the_report_lists_the_runs_it_left_out_and_why(tmp_path):
    frame = _paired_frame(tmp_path)
    extra = [
        # KILLED after 100 s; a finished run of its config and seed (a0) counts
        _run("k1", "a", 0, np.nan, np.nan, status="KILLED"),
        # FAILED with no finished run of its config (cfg-c) and seed
        _run("f1", "a", 3, np.nan, np.nan, status="FAILED", config="cfg-c"),
        # an earlier finished run of b at seed 4, replaced by b4 (which starts later)
        _run("old", "b", 4, 10.0, "0:0;100:1;200:2;300:3;400:10", start="2026-11-30 10:00:00"),
    ]
    frame = pd.concat([frame, load.read(_csv(tmp_path, extra))], ignore_index=True)
    (tmp_path / "claims.yaml").write_text(_claims_yaml(metrics="[last]"))
    built = _rows(frame, tmp_path / "claims.yaml")
    left = {r["run"]: r for r in built.left_out}
    assert set(left) == {"k1", "f1", "old"}
    killed = "KILLED after 100 s; not finished, never counted; `a0` of the same config and seed counts"
    assert left["k1"]["why"] == killed
    assert left["f1"]["why"].startswith("FAILED")
    assert left["f1"]["why"].endswith("no finished run of its config and seed")
    assert left["old"]["why"] == "replaced by the later re-run `b4` of the same config and seed"
    assert (left["old"]["experiment"], left["old"]["seed"], left["old"]["method"]) == ("exp", "4", "spot")
    text = report.format_report(built)
    assert "### Runs left out" in text
    assert "| `k1` | exp | spot | hopper-medium-replay | 0 | KILLED after 100 s;" in text
    # the replaced run does not count: b at seed 4 is still 50
    r = built.rows[0]
    assert r.n_y == 10 and r.means[1] == pytest.approx(50.0)


def test_a_report_without_left_out_runs_has_no_such_section(tmp_path):
    frame = _paired_frame(tmp_path)
    (tmp_path / "claims.yaml").write_text(_claims_yaml(metrics="[last]"))
    assert "Runs left out" not in report.format_report(_rows(frame, tmp_path / "claims.yaml"))


def _csv(tmp_path, rows) -> Path:
    path = tmp_path / "extra.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


# --------------------------------------------------------------------------- the study, before and after the export
def _study_rows(frame: pd.DataFrame, keep: set[tuple[str, str]]):
    parsed = claims.load(claims.study_file(STUDY))
    parsed.claims = [c for c in parsed.claims if (c.id, c.comparison) in keep]
    return report.build(frame, parsed)


KEEP = {
    ("CP", "spot vs constant bonus"),
    ("CP", "spot vs random subgoals"),
    ("1P", "spot vs oracle"),
    ("1P", "spot vs oracle pt"),
    ("1P", "mr vs oracle pt"),
    ("OL", "oracle pt vs oracle"),
}


def _study_runs() -> pd.DataFrame:
    """The study's committed runs as they were before the paired launch's export (the tests below
    stand in for that export themselves, so they hold however far the launch has got)."""
    runs = load.read(list(claims.load(claims.study_file(STUDY)).results))
    return runs[runs["experiment"] != "lab_hopper_fr_pf_paired"]


def test_the_studys_claims_file_marks_the_controls_paired_and_shows_both_oracle_arms():
    parsed = claims.load(claims.study_file(STUDY))
    by_key = {(c.id, c.comparison): c for c in parsed.claims}
    for comparison in ("spot vs constant bonus", "spot vs random subgoals"):
        c = by_key[("CP", comparison)]
        assert c.paired and c.metrics == ("last", "last3", "best") and c.sets == ("Pplus",)
        assert "lab_hopper_fr_pf_paired" in parsed.sets["Pplus"].experiments
    assert "the paper's Oracle" in by_key[("1P", "spot vs oracle")].text
    assert "relabel.normalize=iql" in by_key[("1P", "spot vs oracle")].text
    assert "relabel.normalize=pt" in by_key[("1P", "spot vs oracle pt")].text
    assert "the paper's Oracle is the relabel.normalize=iql arm" in by_key[("OL", "oracle pt vs oracle")].note


def test_the_studys_report_before_the_export_has_no_oracle_pt_runs_and_five_pairs():
    built = _study_rows(_study_runs(), KEEP)
    rows = {(r.claim, r.comparison, r.stat): r for r in built.rows}
    assert rows[("1P", "spot vs oracle pt", "last")].verdict == "no runs"
    assert rows[("OL", "oracle pt vs oracle", "last")].verdict == "no runs"
    const = rows[("CP", "spot vs constant bonus", "last")]
    assert list(const.pairs["hopper-full-replay"][0]) == [0, 1, 2, 3, 4]
    assert const.paired.value == pytest.approx(1.1, abs=0.05)  # NOTES.md: seed-matched +1.1
    text = report.format_report(built)
    assert "| 1P | reference: SPOT vs Oracle like for like" in text
    left = [r for r in built.left_out if r["experiment"] == "lab_hopper_fr_pf_shaping"]
    assert sorted(r["run"] for r in left) == ["a11f660bfa6e4d9c8e3d22be834a9030", "c3367344bbb346cab00efa4e320dda90"]
    assert all(r["why"].startswith("KILLED") for r in left)


def _exported(runs: pd.DataFrame) -> pd.DataFrame:
    """A stand-in for results/lab_hopper_fr_pf_paired.csv: set P's SPOT, constant and random runs of
    seeds 0-4 again at seeds 5-9 (final score + 2 for SPOT), under the fixed variant (reward.length
    steps), and Oracle's seeds 0-2 with relabel.normalize=pt (final score + 10)."""
    done = finished(runs[runs["experiment"].str.startswith("lab_hopper_fr_pf") & (runs["params.variant"] == "paper")])
    done = done[done["params.labels.num_queries"] == "500"]
    plain = (done["params.shaping.weight"].astype(float) == 1.0) & (done["params.subgoal.group"] == "top")
    plain &= (done["params.cvae.loss"] == "mse_cos") & done["params.shaping.kind"].isin(["cosine", "constant"])
    spot = done[(done["method"] == "spot") & plain & done["seed"].between(0, 4)].copy()
    spot["seed"] = spot["seed"] + 5
    proper = (spot["params.shaping.kind"] == "cosine") & (spot["params.subgoal.source"] != "random")
    spot.loc[proper, "metrics.eval/score_final"] += 2.0
    oracle = done[(done["method"] == "oracle") & done["seed"].between(0, 2)].copy()
    oracle["params.relabel.normalize"] = "pt"
    oracle["metrics.eval/score_final"] += 10.0
    new = pd.concat([spot, oracle])
    new["experiment"] = "lab_hopper_fr_pf_paired"
    new["params.reward.length"] = "steps"
    new["run_id"] = [f"paired{i:03d}" for i in range(len(new))]
    new["config_hash"] = new["config_hash"] + "-fixed"
    assert len(spot) == 15 and len(oracle) == 3
    return pd.concat([runs, new], ignore_index=True)


def test_the_studys_report_after_the_export_pairs_ten_seeds_and_reads_both_oracle_arms():
    runs = _study_runs()
    built = _study_rows(_exported(runs), KEEP)
    rows = {(r.claim, r.comparison, r.stat): r for r in built.rows}
    before = {(r.claim, r.comparison, r.stat): r for r in _study_rows(runs, KEEP).rows}
    const = rows[("CP", "spot vs constant bonus", "last")]
    seeds, diffs = const.pairs["hopper-full-replay"]
    assert list(seeds) == list(range(10))
    # seeds 5-9 repeat seeds 0-4's differences, 2 points higher
    old = before[("CP", "spot vs constant bonus", "last")].pairs["hopper-full-replay"][1]
    assert diffs[5:] == pytest.approx(old + 2.0)
    assert const.paired_p == pytest.approx(_brute_sign_flip(diffs))
    assert const.n_x == 10 and const.n_y == 10
    assert any("reward.length: 5 at epochs, 5 at steps" in n for n in const.notes)  # the version change, named
    assert len(rows[("CP", "spot vs random subgoals", "last3")].pairs["hopper-full-replay"][0]) == 10
    # Oracle like for like: SPOT's seeds 0-4 (the set-P version) against the three pt runs
    pt = rows[("1P", "spot vs oracle pt", "last")]
    assert (pt.n_x, pt.n_y) == (5, 3)
    assert pt.means[0] == pytest.approx(before[("1P", "spot vs oracle", "last")].means[0])
    ol = rows[("OL", "oracle pt vs oracle", "last")]
    assert (ol.n_x, ol.n_y) == (3, 5)
    assert list(ol.pairs["hopper-full-replay"][1]) == pytest.approx([10.0, 10.0, 10.0])
    assert (rows[("1P", "mr vs oracle pt", "last")].n_x, rows[("1P", "mr vs oracle pt", "last")].n_y) == (5, 3)
    # the paper's Oracle row stays on set P: the pt runs never enter its oracle arm
    paper = rows[("1P", "spot vs oracle", "last")]
    assert (paper.n_x, paper.n_y) == (5, 5)
    assert paper.means == pytest.approx(before[("1P", "spot vs oracle", "last")].means)
