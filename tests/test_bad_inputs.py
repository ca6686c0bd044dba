"""Bad inputs through the CLI (issue 15): each ends in exit code 2 and one ``error:`` line that
names the key or file and what was expected, with no traceback and nothing written (no store, no
sweep record) in the working folder.

Most cases call :func:`spot.cli.main` in-process (fast); a few run the real ``python -m spot.cli``
to show the process's own stderr.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from spot import cli

NOT_UTF8 = b"method: oracle\niql:\n  lr: \xff\xfe\n"
ALIAS_BOMB = "a: &a [x, x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]\nc: [*b, *b, *b]\n"
SWEEP = "name: bad\nbase: {method: oracle, budget: tiny}\n"

# (id, argv, files {name: text or bytes}, what the error line must contain)
CASES = [
    ("nan-lr", ["run", "iql.lr=nan"], {}, "config key 'iql.lr': value 'nan' is not a finite number"),
    ("inf-weight", ["run", "shaping.weight=inf"], {}, "config key 'shaping.weight': value 'inf' is not a finite"),
    ("nan-weight", ["run", "shaping.weight=nan"], {}, "config key 'shaping.weight'"),
    ("minus-inf", ["run", "pt.lr=-inf"], {}, "config key 'pt.lr': value '-inf' is not a finite number"),
    ("zero-width", ["run", "iql.hidden=[0]"], {}, "config key 'iql.hidden': value [0]: expected one or more layer"),
    ("no-layers", ["run", "iql.hidden=[]"], {}, "config key 'iql.hidden': value []: expected one or more layer"),
    ("negative-width", ["run", "mr.hidden=[256, -3]"], {}, "config key 'mr.hidden'"),
    (
        "fractional-width",
        ["run", "cvae.hidden=[1.5]"],
        {},
        "config key 'cvae.hidden': value [1.5] is not a tuple of int",
    ),
    ("huge-steps", ["run", "iql.steps=1e400"], {}, "config key 'iql.steps': value '1e400' is not int"),
    (
        "huge-seed",
        ["run", "seed=1e30"],
        {},
        "config key 'seed': value '1e30' is too large; expected at most 2147483647",
    ),
    ("big-int", ["run", "iql.steps=99999999999"], {}, "config key 'iql.steps': value 99999999999 is too large"),
    ("empty-experiment", ["run", "tracking.experiment="], {}, "tracking.experiment is empty"),
    ("not-int", ["run", "iql.steps=abc"], {}, "config key 'iql.steps': value 'abc' is not int"),
    ("unknown-key", ["run", "methd=pt"], {}, "unknown config key 'methd'; did you mean 'method'"),
    ("shaping-needs-pt", ["run", "method=mr", "shaping.kind=cosine"], {}, "shaping.kind='cosine' needs reward.kind=pt"),
    ("missing-config", ["run", "nope.yaml"], {}, "config file 'nope.yaml' does not exist"),
    ("alias-bomb", ["run", "c.yaml"], {"c.yaml": ALIAS_BOMB}, "config file 'c.yaml': not valid YAML: alias '*a' found"),
    (
        "duplicate-key",
        ["run", "c.yaml"],
        {"c.yaml": "iql:\n  lr: 0.1\n  lr: 0.2\n"},
        "config file 'c.yaml': not valid YAML: duplicate key 'lr' at line 3",
    ),
    (
        "duplicate-top-key",
        ["run", "c.yaml"],
        {"c.yaml": "method: pt\nbudget: tiny\nmethod: mr\n"},
        "duplicate key 'method'",
    ),
    ("not-utf8", ["run", "c.yaml"], {"c.yaml": NOT_UTF8}, "config file 'c.yaml': not UTF-8 text"),
    (
        "too-big",
        ["run", "c.yaml"],
        {"c.yaml": "method: oracle\n" + "#" * (1 << 20)},
        "config file 'c.yaml': 1048591 bytes; expected a YAML file of at most 1048576 bytes",
    ),
    ("not-a-mapping", ["run", "c.yaml"], {"c.yaml": "- method\n- pt\n"}, "config file 'c.yaml': expected a mapping"),
    ("bad-syntax", ["run", "c.yaml"], {"c.yaml": "iql: [1,\n"}, "config file 'c.yaml': not valid YAML: "),
    ("yaml-nan", ["run", "c.yaml"], {"c.yaml": "iql:\n  lr: .nan\n"}, "config key 'iql.lr': value nan is not a finite"),
    ("yaml-empty-layers", ["run", "c.yaml"], {"c.yaml": "iql:\n  hidden: []\n"}, "config key 'iql.hidden'"),
    (
        "sweep-alias",
        ["sweep", "s.yaml"],
        {"s.yaml": SWEEP + "grid: &g {seed: [1]}\nzip: *g\n"},
        "sweep file 's.yaml': not valid YAML: alias '*g' found",
    ),
    (
        "sweep-duplicate",
        ["sweep", "s.yaml"],
        {"s.yaml": SWEEP + "grid:\n  iql.lr: [0.1]\n  iql.lr: [0.2]\n"},
        "sweep file 's.yaml': not valid YAML: duplicate key 'iql.lr'",
    ),
    (
        "sweep-not-utf8",
        ["sweep", "s.yaml"],
        {"s.yaml": SWEEP.encode() + b"grid: {iql.lr: [\xff]}\n"},
        "sweep file 's.yaml': not UTF-8 text",
    ),
    (
        "sweep-nan-axis",
        ["sweep", "s.yaml"],
        {"s.yaml": SWEEP + "grid: {iql.lr: [.nan, 0.1]}\n"},
        "config key 'iql.lr': value nan is not a finite number",
    ),
    (
        "sweep-empty-layers",
        ["sweep", "s.yaml"],
        {"s.yaml": SWEEP + "grid: {iql.hidden: [[], [64]]}\n"},
        "config key 'iql.hidden': value []: expected one or more layer sizes",
    ),
    (
        "sweep-ftp-store",
        ["sweep", "s.yaml", "--tracking-uri", "ftp://host/x"],
        {"s.yaml": SWEEP + "grid: {iql.lr: [0.1]}\n"},
        "tracking URI 'ftp://host/x': a sweep logs to sqlite:///path.db",
    ),
    (
        "sweep-sqlite-two-slashes",
        ["sweep", "s.yaml", "--tracking-uri", "sqlite://x.db"],
        {"s.yaml": SWEEP + "grid: {iql.lr: [0.1]}\n"},
        "tracking URI 'sqlite://x.db': a sweep logs to",
    ),
    (
        "sweep-huge-seed",
        ["sweep", "s.yaml"],
        {"s.yaml": SWEEP + "grid: {iql.lr: [0.1]}\nseeds: [1.0e+30]\n"},
        "sweep file 's.yaml'",
    ),
]


def _write(folder: Path, files: dict[str, str | bytes]) -> None:
    for name, content in files.items():
        data = content if isinstance(content, bytes) else content.encode()
        (folder / name).write_bytes(data)


@pytest.mark.parametrize(("argv", "files", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_clear_error(tmp_path, monkeypatch, capsys, argv, files, expected):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    _write(tmp_path, files)
    before = sorted(p.name for p in tmp_path.iterdir())
    rc = cli.main(argv)
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert expected in lines[0], lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no store, no sweep record


@pytest.mark.parametrize("case", ["nan-lr", "alias-bomb", "sweep-not-utf8"])
def test_bad_input_in_a_real_process(tmp_path, case):
    from conftest import run_cli

    (_, argv, files, expected) = next(c for c in CASES if c[0] == case)
    _write(tmp_path, files)
    out = run_cli(*argv, cwd=tmp_path, env={"MLFLOW_TRACKING_URI": ""}, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert out.stderr.strip().splitlines() == [out.stderr.strip()] and expected in out.stderr
