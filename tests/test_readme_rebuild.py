"""The README's rebuild commands rebuild what the README shows (issue 42, item 6).

README.md's numbers ("What we found") come from the lab's committed reports, which
experiments/README.md (the page README links for them) says to check with
``bash experiments/<study>/rebuild.sh``, then ``git diff``. Here every such command is run as a
user runs it: the scripts under bash, with the installed ``spot`` console script on PATH, from the
root of a copy of ``experiments/`` in tmp_path (the scripts write in place), together with every
rebuild command README.md itself shows (``spot tables|report ... --out FILE``,
``bash experiments/<study>/rebuild.sh``; none at present). Then:

- every file a command writes is byte-identical to the committed one (each is deleted from the copy
  first, so a command that writes nothing fails);
- the numbers README.md quotes are those of the rebuilt report and table.

tests/test_report.py runs the same ``spot`` lines in process with ``--out`` redirected; this file
runs the scripts and README's commands as written. Slow: six ``spot`` processes (about a minute).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
STUDIES = sorted(p.parent.name for p in (ROOT / "experiments").glob("*/rebuild.sh"))

# a command with its arguments (prose names the commands bare: `spot tables` / `spot report`)
REBUILD = re.compile(r"(?:spot (?:tables|report) [^`\n]+|(?:bash )?experiments/[\w.-]+/rebuild\.sh)")


def readme_commands(text: str) -> list[str]:
    """The rebuild commands a Markdown page shows, in code spans and code blocks, in order:
    ``spot tables ...``, ``spot report ...`` and ``experiments/<study>/rebuild.sh``."""
    code = re.findall(r"```[^\n]*\n(.*?)```", text, flags=re.S) + re.findall(r"`([^`\n]+)`", text)
    found = []
    for chunk in code:
        for line in chunk.splitlines():
            line = line.split(" #", 1)[0].strip()
            found.extend(m.group(0).strip() for m in REBUILD.finditer(line) if m.group(0).strip() not in found)
    return found


def outputs(command: str, root: Path) -> list[str]:
    """The committed files ``command`` (run from ``root``) rewrites: each ``--out`` of a ``spot``
    line, a script's lines with its ``D=`` folder put in."""
    if command.endswith("rebuild.sh"):
        script = (root / command.split()[-1]).read_text()
        folder = re.search(r"^D=(\S+)$", script, flags=re.M).group(1)
        lines = [ln.replace("$D", folder) for ln in script.splitlines() if ln.startswith("spot ")]
    else:
        lines = [command]
    outs = []
    for line in lines:
        argv = shlex.split(line, comments=True)
        assert "--out" in argv, f"{line!r}: prints instead of writing a committed file; this test cannot compare it"
        outs.append(argv[argv.index("--out") + 1].strip('"'))
    return outs


def test_readme_commands_are_found_in_code():
    """The extraction itself, on a page written for it."""
    page = (
        "Rebuild with `spot tables --table 1 experiments/x --out experiments/x/t.md` or\n"
        "```bash\nbash experiments/lab-walker2d/rebuild.sh   # then git diff\n"
        "spot report experiments/y --out r.md\n```\n"
        "and prose that names `spot report` and `spot tables` bare.\n"
    )
    assert readme_commands(page) == [
        "bash experiments/lab-walker2d/rebuild.sh",
        "spot report experiments/y --out r.md",
        "spot tables --table 1 experiments/x --out experiments/x/t.md",
    ]


def _commands() -> list[str]:
    from_readme = readme_commands(README.read_text())
    # experiments/README.md's `bash experiments/<study>/rebuild.sh`, for each study that has one
    studies = [f"bash experiments/{s}/rebuild.sh" for s in STUDIES]
    return studies + [c for c in from_readme if c not in studies and f"bash {c}" not in studies]


COMMANDS = _commands()


@pytest.fixture(scope="module")
def rebuilt(tmp_path_factory) -> dict[str, Path]:
    """Run every command from the root of a copy of experiments/: ``{committed path: rebuilt file}``."""
    root = tmp_path_factory.mktemp("rebuild")
    shutil.copytree(ROOT / "experiments", root / "experiments", ignore=shutil.ignore_patterns("*.png", "*.lock"))
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    written: dict[str, Path] = {}
    for command in COMMANDS:
        outs = outputs(command.removeprefix("bash "), root)
        for out in outs:
            (root / out).unlink(missing_ok=True)
        argv = ["bash", command.split()[-1]] if command.endswith("rebuild.sh") else ["bash", "-c", command]
        done = subprocess.run(argv, cwd=root, env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, f"{command}: exit {done.returncode}\n{done.stderr[-3000:]}"
        written.update({out: root / out for out in outs})
    return written


@pytest.mark.slow
def test_every_rebuild_command_rewrites_its_committed_file_byte_for_byte(rebuilt):
    assert len(COMMANDS) >= len(STUDIES) == 4
    committed = {p.relative_to(ROOT).as_posix() for p in (ROOT / "experiments").glob("*/*.md") if p.name != "NOTES.md"}
    committed -= {"experiments/README.md"}
    assert set(rebuilt) == committed, set(rebuilt) ^ committed  # every committed report has a command
    differ = [out for out, path in rebuilt.items() if path.read_bytes() != (ROOT / out).read_bytes()]
    assert not differ, f"rebuilt differently from the committed file: {differ}"


def _verdict_row(report: str, claim: str, comparison: str) -> dict[str, str]:
    """The row of claim ``claim`` (its ``#``) and ``comparison`` in a report's first table (the last
    evaluation's verdicts)."""
    table = report.split("\n### ", 1)[0]
    rows = [ln for ln in table.splitlines() if ln.startswith("|")]
    head = [c.strip() for c in rows[0].strip("|").split("|")]
    for ln in rows[2:]:
        cells = dict(zip(head, (c.strip() for c in ln.strip("|").split("|")), strict=True))
        if cells["#"] == claim and cells["comparison"] == comparison:
            return cells
    raise AssertionError(f"no verdict row for claim {claim} ({comparison})")


@pytest.mark.slow
def test_the_numbers_the_readme_quotes_are_the_rebuilt_reports(rebuilt):
    readme = " ".join(README.read_text().split())  # sentences across line breaks
    # "What we found": SPOT over PT on the full replay buffer, from lab-hopper-full-replay's report
    found = re.search(
        r"SPOT's gains over PT on Hopper\s+\(\+(?P<effect>[\d.]+) points, p = (?P<p>[\d.]+), "
        r"on the full replay buffer\)",
        readme,
    )
    assert found, "README.md's 'What we found' no longer quotes SPOT over PT on hopper-full-replay: update this test"
    report = rebuilt["experiments/lab-hopper-full-replay/report_hopper_fr_pf.md"].read_text()
    row = _verdict_row(report, "1P", "spot vs pt")  # claim 1 on the study's own runs (variant paper)
    effect = row["effect [95% CI]"].split(" [")[0]
    assert effect == found["effect"], (row, found.group(0))
    decimals = len(found["p"].split(".")[1])
    assert f"{float(row['perm. p']):.{decimals}f}" == found["p"], (row, found.group(0))
    assert row["verdict"] == "supported"
    # "Oracle capped near 20–30 by the local medium-replay files": Table 1's Oracle cell
    span = re.search(r"Oracle capped near (\d+)[–-](\d+) by the local medium-replay files", readme)
    assert span, "README.md no longer gives Oracle's range on the medium-replay files: update this test"
    table = rebuilt["experiments/lab-hopper-medium-replay/lab_table1.md"].read_text()
    (line,) = [ln for ln in table.splitlines() if ln.startswith("| hopper-medium-replay |")]
    head = [ln for ln in table.splitlines() if ln.startswith("| dataset |")][0]
    oracle = dict(zip(head.split("|"), line.split("|"), strict=True))[" Oracle "].split()[0]
    assert int(span[1]) <= round(float(oracle)) <= int(span[2]), (oracle, span.group(0))
