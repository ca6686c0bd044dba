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


def _d4rl(obs_dim: int = 11, act_dim: int = 3, **change):
    """A writer of a 40-row D4RL hdf5 file (Hopper's sizes by default), ``change`` replacing arrays."""

    def write(path: Path) -> None:
        import h5py
        import numpy as np

        rng = np.random.default_rng(0)
        n = 40
        arrays = {
            "observations": rng.normal(size=(n, obs_dim)).astype(np.float32),
            "actions": rng.uniform(-1, 1, size=(n, act_dim)).astype(np.float32),
            "rewards": rng.normal(size=n).astype(np.float32),
            "terminals": np.zeros(n, np.float32),
            "timeouts": (np.arange(n) % 20 == 19).astype(np.float32),
            **change,
        }
        with h5py.File(path, "w") as f:
            for key, arr in arrays.items():
                f.create_dataset(key, data=arr)

    return write


def _labels(**change):
    """A writer of a ``spot labels make`` .npz file of 2 queries of length 5, ``change`` replacing arrays."""

    def write(path: Path) -> None:
        import numpy as np

        fields = {
            "starts_1": np.array([0, 3]),
            "starts_2": np.array([10, 20]),
            "labels": np.array([0.0, 1.0], np.float32),
            "segment_length": np.int64(5),
            "source": np.str_("script"),
            **change,
        }
        with open(path, "wb") as fh:
            np.savez(fh, **fields)

    return write


def _terminals_3_5():
    import numpy as np

    t = np.zeros(40, np.float32)
    t[7] = 3.5
    return t


HOPPER = "hopper-medium.hdf5"  # the file's stem names the evaluation env (Hopper-v5: 11-D observations, 3-D actions)
RUN_FILE = ["run", "method=oracle", "budget=tiny", f"data.name={HOPPER}"]
LABELS_INFO = ["labels", "info", "q.npz", "--dataset", HOPPER]

# (id, argv, files {name: text, bytes or a writer of the file}, what the error line must contain)
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
    # datasets (issue 15, items 6 and 7): checked when the run loads them, before any training
    (
        "terminals-3.5",
        RUN_FILE,
        {HOPPER: _d4rl(terminals=_terminals_3_5())},
        f"dataset file '{HOPPER}': 'terminals' has the value 3.5 at row 7 (1 rows not 0/1); expected flags 0 or 1",
    ),
    (
        "timeouts-2",
        RUN_FILE,
        {HOPPER: _d4rl(timeouts=__import__("numpy").full(40, 2.0))},
        "'timeouts' has the value 2.0 at row 0 (40 rows not 0/1)",
    ),
    (
        "every-step-a-timeout",
        RUN_FILE,
        {HOPPER: _d4rl(timeouts=__import__("numpy").ones(40, bool))},
        "every one of its 39 rows before the last is a timeout, so it has no transitions",
    ),
    (
        "observation-size",
        RUN_FILE,
        {HOPPER: _d4rl(obs_dim=5)},
        "observations have 5 dimensions, but the evaluation env of 'hopper-medium' (Hopper-v5) has 11",
    ),
    (
        "action-size",
        RUN_FILE,
        {HOPPER: _d4rl(act_dim=4)},
        "actions have 4 dimensions, but the evaluation env of 'hopper-medium' (Hopper-v5) has 3",
    ),
    (
        "unreachable-tracking-server",
        [*RUN_FILE, "tracking.uri=http://127.0.0.1:9"],
        {HOPPER: _d4rl()},
        "tracking server http://127.0.0.1:9 does not answer",
    ),
    (
        "run-unsupported-tracking-uri",
        [*RUN_FILE, "tracking.uri=ftp://host/x"],
        {HOPPER: _d4rl()},
        "tracking URI 'ftp://host/x': scheme 'ftp' is not one MLflow stores runs in",
    ),
    (
        "run-file-store-tracking-uri",
        [*RUN_FILE, "tracking.uri=file:///tmp/spot-file-store"],
        {HOPPER: _d4rl()},
        "tracking URI 'file:///tmp/spot-file-store': a folder (MLflow's file store) is refused by this MLflow",
    ),
    (
        "tables-sqlite-two-slashes",
        ["tables", "--table", "1", "--tracking-uri", "sqlite://x.db"],
        {},
        "tracking URI 'sqlite://x.db': expected sqlite:///relative/path.db or sqlite:////absolute/path.db",
    ),
    # label files
    (
        "label-start-near-2^63",
        LABELS_INFO,
        {HOPPER: _d4rl(), "q.npz": _labels(starts_1=__import__("numpy").array([2**63 - 3, 0]))},
        "segment 1 of query 0 starts at index 9223372036854775805 with length 5, past the end of dataset",
    ),
    (
        "label-start-uint64",
        LABELS_INFO,
        {HOPPER: _d4rl(), "q.npz": _labels(starts_2=__import__("numpy").array([2**64 - 1, 0], "uint64"))},
        "'starts_2' has start index 18446744073709551615; expected at most 9223372036854775807",
    ),
    (
        "label-array-segment-length",
        LABELS_INFO,
        {HOPPER: _d4rl(), "q.npz": _labels(segment_length=__import__("numpy").array([5, 5]))},
        "preference file 'q.npz': 'segment_length' is an array of shape (2,) and dtype int64; expected one integer",
    ),
    (
        "label-object-array",
        LABELS_INFO,
        {HOPPER: _d4rl(), "q.npz": _labels(starts_2=__import__("numpy").array([1, "a", None], object))},
        "preference file 'q.npz': array 'starts_2' cannot be read without pickles",
    ),
    ("label-zero-bytes", LABELS_INFO, {HOPPER: _d4rl(), "q.npz": b""}, "preference file 'q.npz' is not a readable npz"),
    # tables
    (
        "tables-out-missing-folder",
        ["tables", "--table", "1", "--results", "r.csv", "--out", "nope/t.md"],
        {},
        "--out nope/t.md: folder 'nope' does not exist; expected a file in an existing folder",
    ),
    (
        "tables-out-a-folder",
        ["tables", "--table", "1", "--results", "r.csv", "--out", "."],
        {},
        "--out .: is a folder; expected a file name",
    ),
    (
        "tables-unreachable-tracking-server",
        ["tables", "--table", "1", "--tracking-uri", "http://127.0.0.1:9"],
        {},
        "tracking server http://127.0.0.1:9 does not answer",
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
        if callable(content):
            content(folder / name)
            continue
        data = content if isinstance(content, bytes) else content.encode()
        (folder / name).write_bytes(data)


@pytest.mark.parametrize(("argv", "files", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_clear_error(tmp_path, monkeypatch, capsys, argv, files, expected):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    _write(tmp_path, files)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    rc = cli.main(argv)
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert expected in lines[0], lines[0]
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # no store or record; inputs unchanged


@pytest.mark.parametrize(
    "case", ["nan-lr", "alias-bomb", "sweep-not-utf8", "every-step-a-timeout", "unreachable-tracking-server"]
)
def test_bad_input_in_a_real_process(tmp_path, case):
    from conftest import run_cli

    (_, argv, files, expected) = next(c for c in CASES if c[0] == case)
    _write(tmp_path, files)
    out = run_cli(*argv, cwd=tmp_path, env={"MLFLOW_TRACKING_URI": ""}, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert out.stderr.strip().splitlines() == [out.stderr.strip()] and expected in out.stderr
