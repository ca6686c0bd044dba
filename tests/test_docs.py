"""The habits that keep the framework and the lab apart (docs/design.md, "Framework and lab"):
the README's budget, no dates in docs/ outside the benchmarks table, no `lab_` names under
spot/, links that resolve, every command in docs/cli.md, and the guide (docs/guide.md) followed
end to end at the tiny budget with the commands it shows."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pandas as pd
import pytest
import yaml

from tests.conftest import run_cli

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
README_BUDGET = 120  # lines
README_COMMANDS = (
    'python3 -m venv .venv && .venv/bin/pip install -e ".[dev]" && .venv/bin/spot sweep sweeps/quickstart.yaml',
    'python3 -m venv .venv && .venv/bin/pip install -e ".[dev]" && .venv/bin/python -m pytest -q',
)
BENCHMARKS_TABLE = "## The figures"  # the one section of docs/ whose table rows may carry dates

_MONTH = (
    r"(?:Jan(?:uary)?|Feb(?:ruary)?|Mar(?:ch)?|Apr(?:il)?|May|June?|July?|Aug(?:ust)?"
    r"|Sep(?:t(?:ember)?)?|Oct(?:ober)?|Nov(?:ember)?|Dec(?:ember)?)\.?"
)
DATE = re.compile(
    rf"\b\d{{4}}-\d{{2}}-\d{{2}}\b"  # 2026-11-28
    rf"|\b{_MONTH} \d{{1,2}}(?:st|nd|rd|th)?,? \d{{4}}\b"  # November 28, 2026
    rf"|\b\d{{1,2}}(?:st|nd|rd|th)? {_MONTH},? \d{{4}}\b"  # 28 November 2026
)


# --------------------------------------------------------------------------- the README
def test_readme_stays_within_its_budget():
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= README_BUDGET, f"README.md has {len(lines)} lines; its budget is {README_BUDGET}"


def test_readme_keeps_its_two_commands():
    text = (REPO / "README.md").read_text()
    for command in README_COMMANDS:
        assert command in text.splitlines(), f"README.md lost the line: {command}"
    assert (REPO / "sweeps" / "quickstart.yaml").is_file()


# --------------------------------------------------------------------------- no dates in docs/
def dated_lines(page: Path, root: Path = REPO) -> list[str]:
    """``page:line: text`` (the page relative to ``root``) for each line naming a date; in
    docs/benchmarks.md the table rows of its figures section are exempt (each figure's date is part
    of its record there)."""
    out, exempt = [], False
    for number, line in enumerate(page.read_text().splitlines(), 1):
        if line.startswith("#"):
            exempt = page.name == "benchmarks.md" and line.strip() == BENCHMARKS_TABLE
        if exempt and line.startswith("|"):
            continue
        if DATE.search(line):
            out.append(f"{page.relative_to(root)}:{number}: {line.strip()[:120]}")
    return out


def test_the_date_rule_catches_each_form_and_exempts_only_the_figures_table(tmp_path):
    docs = tmp_path / "docs"
    docs.mkdir()
    page = docs / "page.md"
    page.write_text(
        "run on 2026-11-28\nNovember 28, 2026\nDec 7 2026\n28 November 2026\n"
        "commit 0aaf8b1, 15:04 UTC, 1,000 steps, version 3.17.2, seeds 0-2\n| 2026-11-28 | in a table |\n"
    )
    assert [x.split(":")[1] for x in dated_lines(page, tmp_path)] == ["1", "2", "3", "4", "6"]
    bench = docs / "benchmarks.md"
    bench.write_text(
        "# B\n\n## The figures\n\n| what | when |\n|---|---|\n| a | 2026-11-28 |\n\n"
        "measured 2026-11-28\n\n## Other\n\n| b | 2026-11-28 |\n"
    )
    assert [x.split(":")[1] for x in dated_lines(bench, tmp_path)] == ["9", "13"]


@pytest.mark.parametrize("page", sorted(DOCS.glob("*.md")), ids=lambda p: p.name)
def test_docs_name_no_dates(page):
    """docs/ states what stays true; what ran when goes into experiments/<study>/NOTES.md."""
    found = dated_lines(page)
    assert not found, "dates in docs/ (move them to a study's NOTES.md):\n" + "\n".join(found)


# --------------------------------------------------------------------------- spot/ names no study
def test_no_lab_names_under_spot():
    """The framework never names one of the lab's experiments (experiments/README.md, "The rule")."""
    found = []
    for path in sorted((REPO / "spot").rglob("*")):
        if not path.is_file() or "__pycache__" in path.parts or path.suffix in (".pyc", ".so"):
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if re.search(r"\blab_[A-Za-z0-9]", line):
                found.append(f"{path.relative_to(REPO)}:{number}: {line.strip()[:100]}")
    assert not found, f"{len(found)} `lab_` names under spot/:\n" + "\n".join(found[:40])


# --------------------------------------------------------------------------- links
def _pages() -> list[Path]:
    return [
        REPO / "README.md",
        *sorted(DOCS.glob("*.md")),
        REPO / "experiments" / "README.md",
        *sorted((REPO / "experiments").glob("*/NOTES.md")),
    ]


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation but - and _ dropped, spaces -> -."""
    text = re.sub(r"[`*]", "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    for heading in re.findall(r"^#+ (.+)$", text, flags=re.M):
        slug = _slug(heading)
        out.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
        seen[slug] = seen.get(slug, 0) + 1
    return out


def broken_links(page: Path, root: Path = REPO) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    text = re.sub(r"`[^`\n]*`", "", text)  # code spans hold no links
    out = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path) if path else page
        if not resolved.exists():
            out.append(f"{page.relative_to(root)}: {target} (no such file)")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            out.append(f"{page.relative_to(root)}: {target} (no such heading)")
    return out


def test_the_link_check_finds_a_missing_file_and_heading(tmp_path):
    (tmp_path / "b.md").write_text("# Title\n\n## Framework and lab\n")
    page = tmp_path / "a.md"
    page.write_text(
        "[ok](b.md) [ok](b.md#framework-and-lab) [gone](c.md) [bad](b.md#nope) [web](https://x.org/y)\n"
        "`[code](d.md)`\n```\n[block](e.md)\n```\n"
    )
    assert broken_links(page, tmp_path) == ["a.md: c.md (no such file)", "a.md: b.md#nope (no such heading)"]


@pytest.mark.parametrize("page", _pages(), ids=lambda p: p.relative_to(REPO).as_posix())
def test_relative_links_resolve(page):
    assert not broken_links(page), "\n".join(broken_links(page))


# --------------------------------------------------------------------------- docs/cli.md
def _subcommands(help_text: str) -> list[str]:
    """The subcommands a ``spot [COMMAND] --help`` lists: its usage ends in ``...`` (argparse's
    subparsers) and its positional section names them, one per line, indented by four spaces."""
    usage = " ".join(help_text.split("\n\n")[0].split())
    if not usage.endswith(" ..."):
        return []
    section = help_text.split("positional arguments:", 1)[-1].split("\n\n")[0]
    return [m.group(1) for line in section.splitlines() if (m := re.match(r"^ {4}([a-z][\w-]*)(?:\s{2,}|$)", line))]


def _help(capsys, *args: str) -> str:
    """``spot ARGS --help`` through the console script's entry point (``spot.cli:main``)."""
    from spot import cli

    with pytest.raises(SystemExit) as e:
        cli.main([*args, "--help"])
    assert e.value.code == 0
    return capsys.readouterr().out


def test_every_command_is_in_the_command_reference(capsys):
    commands = _subcommands(_help(capsys))
    assert len(commands) >= 10
    rows = [ln.split("|")[1].strip() for ln in (DOCS / "cli.md").read_text().splitlines() if ln.startswith("| `spot")]
    missing = []
    for command in commands:
        for sub in _subcommands(_help(capsys, command)) or [""]:
            if not any(r.startswith(f"`spot {command}") and (not sub or re.search(rf"\b{sub}\b", r)) for r in rows):
                missing.append(f"spot {command} {sub}".strip())
    assert not missing, "commands missing from docs/cli.md: " + ", ".join(missing)


# --------------------------------------------------------------------------- the guide, end to end
def guide_blocks() -> dict[str, tuple[str, str]]:
    """docs/guide.md's tested blocks: ``<!-- guide-test: KIND [PATH] -->`` then a fenced block;
    returns ``{KIND: (PATH, body)}``."""
    text = (DOCS / "guide.md").read_text()
    found = re.findall(r"<!-- guide-test: (\w+) ?(\S*) -->\n```\w*\n(.*?)```", text, flags=re.S)
    return {kind: (path, body) for kind, path, body in found}


def test_the_guide_marks_its_sweep_commands_and_claims():
    blocks = guide_blocks()
    assert set(blocks) == {"sweep", "commands", "claims"}
    sweep = yaml.safe_load(blocks["sweep"][1])
    assert sweep["smoke"]["base"]["budget"] == "tiny" and len(sweep["smoke"]["seeds"]) == 1
    lines = [ln for ln in blocks["commands"][1].splitlines() if ln.strip()]
    assert all(ln.startswith("spot ") for ln in lines)
    assert any(" --smoke" in ln and "--dry-run" not in ln and "--status" not in ln for ln in lines)
    assert any(ln.startswith("spot tables") for ln in lines) and any(ln.startswith("spot report") for ln in lines)


@pytest.mark.slow
def test_the_guide_runs_end_to_end(tmp_path, spot_dirs):
    """Write the guide's sweep file and claims file where it says, run its commands in order, and
    check what they leave: two finished tiny runs (λ 0.5 and 1.0) in the results file, Table 3 with
    both λ columns, and the claims report with the guide's claim (one seed an arm: too few seeds)."""
    blocks = guide_blocks()
    for kind in ("sweep", "claims"):
        path, body = blocks[kind]
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text(body)
    (tmp_path / "experiments/my-study/results").mkdir(parents=True, exist_ok=True)
    env = {
        "MLFLOW_TRACKING_URI": "",
        "SPOT_CPU_SLOTS_DIR": str(tmp_path / "slots"),
        "PYTHONUNBUFFERED": "1",
    }
    outputs = {}
    for line in blocks["commands"][1].splitlines():
        argv = shlex.split(line.split("#")[0])
        if not argv:
            continue
        out = run_cli(*argv[1:], cwd=tmp_path, env=env, timeout=1500)
        assert out.returncode == 0, f"{line}\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
        outputs[argv[1]] = outputs.get(argv[1], "") + out.stdout

    results = pd.read_csv(tmp_path / "experiments/my-study/results/weights-smoke.csv")
    assert sorted(results["status"]) == ["FINISHED", "FINISHED"]
    assert sorted(results["params.shaping.weight"].astype(float)) == [0.5, 1.0]
    assert set(results["params.budget"]) == {"tiny"} and set(results["seed"]) == {0}

    table = outputs["tables"]
    assert "hopper-medium-replay" in table and "cosine" in table
    assert re.search(r"\b0\.5\b", table) and re.search(r"\b1(\.0)?\b", table)

    report = (tmp_path / "experiments/my-study/report.md").read_text()
    row = next(ln for ln in report.splitlines() if ln.startswith("| L1 |"))
    assert "cosine shaping at λ = 1 beats λ = 0.5" in row and "too few seeds" in row
