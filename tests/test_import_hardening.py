"""`spot results import` of hostile records (issue 43, finding 1): links, FIFOs, sockets and oversized
files among the artifacts, MLflow's reserved tags, non-finite metrics, impossible times and huge
names. Each is one `error:` line naming the file and field, exit 2, and leaves no run and no file."""

import json
import os
import re
import signal
import socket
import stat
import tempfile
import urllib.parse
import urllib.request
from pathlib import Path

import pytest
from mlflow.entities import ViewType
from mlflow.tracking import MlflowClient

from spot import SpotError, cli, config
from spot.tracking import record_checks, recorded

TINY = ["budget=tiny", "data.name=drawer-open", "iql.steps=100", "iql.chunk=50", "eval.every=50", "eval.episodes=1"]
SECRET = "not-for-the-store-7f3a"


@pytest.fixture(autouse=True)
def _contained(tmp_path, monkeypatch):
    """Temp files (the import's staging folder) and the working folder under tmp_path; a blocking
    open of a FIFO fails the test after 60 s instead of hanging it."""
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)

    def hung(*_):
        raise TimeoutError("the import blocked (opened a FIFO?)")

    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(60)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)
    assert not list((tmp_path / "tmp").iterdir()), "the import left temporary files"


def _record(tmp_path: Path) -> Path:
    """A finished record written by spot's own recorder, with a plot artifact in a sub-folder."""
    cfg = config.load(None, [*TINY, "method=oracle", "seed=0", f"tracking.record={tmp_path / 'rec'}"])
    with recorded.start_record(cfg, {"name": "drawer-open", "source": "recipe", "size": "tiny"}) as tr:
        tr.log_metrics({"eval/score": 1.5}, step=0)
        tr.log_series("eval/score", [50, 100], [2.5, 3.5])
        (tmp_path / "curve.txt").write_text("a curve")
        tr.log_artifact(tmp_path / "curve.txt", "plots")
    (tmp_path / "curve.txt").unlink()
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret").write_text(SECRET)
    (outside / "curve.txt").write_text(SECRET)
    return tr.folder


def _edit_head(folder: Path, **change) -> None:
    head = json.loads((folder / "record.json").read_text())
    for key, value in change.items():
        if key in ("tags", "params"):
            head[key].update(value)
        else:
            head[key] = value
    (folder / "record.json").write_text(json.dumps(head))


def _add_point(folder: Path, line: str) -> None:
    with open(folder / "metrics.jsonl", "a") as f:
        f.write(line + "\n")


def _point(**change) -> str:
    base = {"key": "eval/score", "value": 1.0, "step": 1, "timestamp": 1_767_225_600_000}  # 2026-01-01
    return json.dumps({**base, **change})


def _socket(path: Path) -> None:
    os.chdir(path.parent)  # a relative name: tmp_path may be longer than a socket address allows
    s = socket.socket(socket.AF_UNIX)
    s.bind(path.name)
    s.close()


def _runs(db: Path) -> list:
    """Every run in the store, deleted ones included."""
    if not db.exists():
        return []
    client = MlflowClient(f"sqlite:///{db}")
    ids = [e.experiment_id for e in client.search_experiments(view_type=ViewType.ALL)]
    return client.search_runs(ids, run_view_type=ViewType.ALL) if ids else []


def _stored(run) -> Path:
    """The local folder of a run's artifacts (the test stores are SQLite with a local artifact root)."""
    uri = urllib.parse.urlparse(run.info.artifact_uri)
    assert uri.scheme == "file", run.info.artifact_uri
    return Path(urllib.request.url2pathname(uri.path))


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    """Every entry under ``root`` (links not followed): its type and size, and a file's content hash."""
    out = {}
    for top, dirs, files in os.walk(root):
        for name in dirs + files:
            path = Path(top, name)
            st = path.lstat()
            digest = hash(path.read_bytes()) if stat.S_ISREG(st.st_mode) else 0
            out[str(path.relative_to(root))] = (stat.S_IFMT(st.st_mode), st.st_size, digest)
    return out


A = "artifacts"
M = r"line 4: metric 'eval/score'"  # the point _point adds, after the recorder's three


def _pt(**change):
    return lambda f, t: _add_point(f, _point(**change))


def _hd(**change):
    return lambda f, t: _edit_head(f, **change)


def _replace(name, make):
    """Replace the record's file ``name`` by what ``make(path, tmp_path)`` puts there."""
    return lambda f, t: ((f / name).rename(t / "outside" / name), make(f / name, t))


CASES = [
    # artifacts that are not regular files inside the record
    ("symlink-to-file-outside", lambda f, t: (f / A / "secret.txt").symlink_to(t / "outside" / "secret"),
     r"artifact 'secret.txt' is a symbolic link"),
    ("symlink-to-etc-passwd", lambda f, t: (f / A / "passwd").symlink_to("/etc/passwd"),
     r"artifact 'passwd' is a symbolic link"),
    ("symlink-to-dev-zero", lambda f, t: (f / A / "zeros.bin").symlink_to("/dev/zero"),
     r"artifact 'zeros.bin' is a symbolic link"),
    ("symlink-to-folder", lambda f, t: (f / A / "etc").symlink_to(t / "outside"),
     r"artifact 'etc' is a symbolic link"),
    ("symlink-in-sub-folder", lambda f, t: (f / A / "plots" / "x.txt").symlink_to(t / "outside" / "secret"),
     r"artifact 'plots/x.txt' is a symbolic link"),
    ("relative-symlink-escaping", lambda f, t: (f / A / "up").symlink_to("../../../outside/secret"),
     r"artifact 'up' is a symbolic link"),
    ("fifo", lambda f, t: os.mkfifo(f / A / "pipe"), r"artifact 'pipe' is a FIFO"),
    ("socket", lambda f, t: _socket(f / A / "sock"), r"artifact 'sock' is a socket"),
    ("artifacts-folder-is-a-symlink", _replace(A, lambda p, t: p.symlink_to(t / "outside")),
     r"artifacts is a symbolic link, expected a folder"),
    ("metrics-file-is-a-fifo", _replace("metrics.jsonl", lambda p, t: os.mkfifo(p)),
     r"metrics.jsonl: is a FIFO, expected a regular file"),
    ("metrics-file-links-dev-zero", _replace("metrics.jsonl", lambda p, t: p.symlink_to("/dev/zero")),
     r"metrics.jsonl: cannot read it \(a symbolic link; expected a regular file\)"),
    ("record-file-links-outside", _replace("record.json", lambda p, t: p.symlink_to(t / "outside" / "record.json")),
     r"record.json: cannot read it \(a symbolic link; expected a regular file\)"),
    # MLflow's own tags
    ("tag-mlflow.parentRunId", _hd(tags={"mlflow.parentRunId": "0" * 32}),
     r"tag 'mlflow.parentRunId' is MLflow's own field"),
    ("tag-mlflow.user", _hd(tags={"mlflow.user": "admin"}), r"tag 'mlflow.user' is MLflow's own field"),
    ("tag-mlflow.runName", _hd(tags={"mlflow.runName": "other"}), r"tag 'mlflow.runName' is MLflow's own field"),
    ("tag-mlflow.source.docker", _hd(tags={"mlflow.source.docker.image": "x"}),
     r"tag 'mlflow.source.docker.image' is MLflow's own field"),
    # metric values, steps and times
    ("metric-nan", _pt(value=float("nan")), M + r" has value 'nan', expected a finite number"),
    ("metric-infinity", _pt(value=float("inf")), M + r" has value 'inf', expected a finite number"),
    ("metric-minus-infinity", _pt(value=float("-inf")), M + r" has value '-inf', expected a finite number"),
    ("metric-string", _pt(value="1.5"), M + r" has value '1.5', expected a finite number"),
    ("metric-bool", _pt(value=True), M + r" has value 'True', expected a finite number"),
    ("metric-int-overflowing-a-double", _pt(value=10**400), M + r" has value '1000+', expected a finite number"),
    ("metric-negative-step", _pt(step=-1), M + r" has step '-1', expected an integer 0\.\.9223372036854775807"),
    ("metric-fractional-step", _pt(step=1.5), M + r" has step '1.5', expected an integer"),
    ("metric-timestamp-year-33000", _pt(timestamp=10**15), M + r" timestamp is 1000000000000000, expected ms"),
    ("metric-timestamp-in-seconds", _pt(timestamp=1_767_225_600), M + r" timestamp is 1767225600, expected ms"),
    ("start-time-1970", _hd(start_time=5), r"record.json: field 'start_time' is 5, expected ms since the epoch"),
    ("end-time-before-start", _hd(start_time=1_767_225_600_000, end_time=1_767_225_500_000),
     r"record.json: end_time 1767225500000 is before start_time 1767225600000"),
    # names and values past MLflow's limits
    ("metric-name-100k", _pt(key="k" * 100_000),
     r"line 4: metric key 'k{60}'\.\.\. \(100000 characters\) is longer than MLflow's 250 characters"),
    ("tag-name-100k", _hd(tags={"t" * 100_000: "x"}),
     r"tags key 't{60}'\.\.\. \(100000 characters\) is longer than MLflow's 250"),
    ("param-name-100k", _hd(params={"p" * 100_000: "x"}),
     r"params key 'p{60}'\.\.\. \(100000 characters\) is longer than MLflow's 250"),
    ("run-name-100k", _hd(run_name="r" * 100_000),
     r"run_name 'r{60}'\.\.\. \(100000 characters\) is longer than 250"),
    ("tag-value-8001", _hd(tags={"note": "v" * 8001}), r"tags\['note'\] has 8001 characters, MLflow's limit is 8000"),
    ("param-value-6001", _hd(params={"iql.steps": "1" * 6001}),
     r"params\['iql.steps'\] has 6001 characters, MLflow's limit is 6000"),
    ("metric-name-leaving-its-path", _pt(key="eval/../../x"), r"line 4: metric key 'eval/../../x': MLflow's names"),
    ("tag-name-with-a-newline", _hd(tags={"a\nb": "x"}), r"tags key 'a\\nb': MLflow's names"),
]  # fmt: skip


@pytest.mark.parametrize(("damage", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_a_damaged_record_is_one_clear_error_and_imports_nothing(tmp_path, capsys, damage, expected):
    folder = _record(tmp_path)
    damage(folder, tmp_path)
    os.chdir(tmp_path)
    before = _tree(tmp_path)
    db = tmp_path / "store" / "mlflow.db"
    rc = cli.main(["results", "import", str(tmp_path / "rec"), "--tracking-uri", f"sqlite:///{db}"])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert len(lines[0]) < 600, lines[0]  # a 100k-character name is not echoed whole
    assert str(folder) in lines[0]  # names the record (and, per the pattern, the file and field)
    assert re.search(expected, lines[0]), lines[0]
    assert _runs(db) == [] and not db.exists()  # checked before any store is opened
    assert _tree(tmp_path) == before  # nothing written: no store, no staged file, the record untouched


@pytest.mark.parametrize("limit", ["MAX_ARTIFACT_BYTES", "MAX_ARTIFACTS_BYTES", "MAX_ARTIFACT_FILES"])
def test_artifacts_over_the_limits_are_refused(tmp_path, monkeypatch, limit):
    folder = _record(tmp_path)
    (folder / A / "big.bin").write_bytes(b"x" * 3000)
    sizes = sorted(p.stat().st_size for p in (folder / A).rglob("*") if p.is_file())
    small = {
        "MAX_ARTIFACT_BYTES": 2999,  # big.bin alone is over
        "MAX_ARTIFACTS_BYTES": sum(sizes) - 1,  # each file fits, all of them do not
        "MAX_ARTIFACT_FILES": len(sizes) - 1,
    }[limit]
    monkeypatch.setattr(record_checks, limit, small)
    if limit != "MAX_ARTIFACT_BYTES":
        monkeypatch.setattr(record_checks, "MAX_ARTIFACT_BYTES", max(sizes))
    db = tmp_path / "mlflow.db"
    with pytest.raises(
        SpotError, match=rf"record {folder}: artifact '.+' (is 3000 bytes, over 2999 bytes a file|brings)"
    ):
        recorded.import_records(tmp_path / "rec", f"sqlite:///{db}")
    assert not db.exists()


def _after_scan(monkeypatch, change):
    """Run ``change`` right after the import listed the artifacts: a record that changes under it."""
    scan = record_checks.scan_artifacts

    def scan_then_change(folder):
        files = scan(folder)
        change(folder)
        return files

    monkeypatch.setattr(record_checks, "scan_artifacts", scan_then_change)


def _grow(folder):
    # past the cap (the largest artifact + 10 bytes) whatever that artifact's size: environment.json
    # grows with the command line the test process carries
    largest = max(p.stat().st_size for p in (folder / A).rglob("*") if p.is_file())
    with open(folder / A / "plots" / "curve.txt", "ab") as f:
        f.write(b"y" * (largest + 100))


def _swap(folder, make):
    (folder / A / "plots" / "curve.txt").unlink()
    make(folder / A / "plots" / "curve.txt")


RACES = [
    ("file-grows-past-the-cap", _grow, r"artifact 'plots/curve.txt' grew past the limit of \d+ bytes a file"),
    ("file-becomes-a-link-to-dev-zero", lambda f: _swap(f, lambda p: p.symlink_to("/dev/zero")),
     r"artifact 'plots/curve.txt' cannot be opened as a regular file inside the record \(Too many levels"),
    ("file-becomes-a-fifo", lambda f: _swap(f, os.mkfifo), r"artifact 'plots/curve.txt' is a FIFO"),
    ("folder-becomes-a-link-outside",
     lambda f: ((f / A / "plots").rename(f / "old"), (f / A / "plots").symlink_to(f.parents[1] / "outside")),
     r"artifact 'plots/curve.txt' cannot be opened as a regular file inside the record"),
]  # fmt: skip


@pytest.mark.parametrize(("change", "expected"), [r[1:] for r in RACES], ids=[r[0] for r in RACES])
def test_a_record_changed_while_imported_leaves_no_run_and_imports_once_fixed(tmp_path, monkeypatch, change, expected):
    """The artifacts are listed, then change before they are copied: the limits and the no-link rule
    hold while copying, before the run is created; once the record is put right it imports."""
    folder = _record(tmp_path)
    largest = max(p.stat().st_size for p in (folder / A).rglob("*") if p.is_file())
    monkeypatch.setattr(record_checks, "MAX_ARTIFACT_BYTES", largest + 10)  # _grow appends more than that
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    scan = record_checks.scan_artifacts
    _after_scan(monkeypatch, change)
    with pytest.raises(SpotError, match=expected):
        recorded.import_records(tmp_path / "rec", uri)
    assert _runs(tmp_path / "mlflow.db") == []  # copied before the run was created
    assert not (tmp_path / "artifacts").exists() or not any(p.is_file() for p in (tmp_path / "artifacts").rglob("*"))
    monkeypatch.setattr(record_checks, "scan_artifacts", scan)
    if (folder / "old").exists():  # the record put right
        (folder / A / "plots").unlink()
        (folder / "old").rename(folder / A / "plots")
    (folder / A / "plots" / "curve.txt").unlink()
    (folder / A / "plots" / "curve.txt").write_text("a curve")
    (done,) = recorded.import_records(tmp_path / "rec", uri)
    assert done["action"] == "imported"
    client = MlflowClient(uri)
    run = client.get_run(done["run_id"])
    assert run.info.status == "FINISHED"
    stored = _stored(run)
    assert (stored / "plots" / "curve.txt").read_text() == "a curve"


def test_a_run_that_fails_after_it_was_created_is_deleted_and_the_record_imports_later(tmp_path, monkeypatch):
    folder = _record(tmp_path)
    db = tmp_path / "mlflow.db"
    uri = f"sqlite:///{db}"

    def fail(self, run_id, *args, **kwargs):
        raise OSError("the store went away")

    monkeypatch.setattr(MlflowClient, "set_terminated", fail)
    with pytest.raises(OSError, match="the store went away"):
        recorded.import_records(tmp_path / "rec", uri)
    (run,) = _runs(db)
    assert run.info.lifecycle_stage == "deleted"  # not a half-imported run among the results
    monkeypatch.undo()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (done,) = recorded.import_records(tmp_path / "rec", uri)  # not marked imported by the failed try
    assert done["action"] == "imported" and done["run_id"] != run.info.run_id
    live = [r for r in _runs(db) if r.info.lifecycle_stage == "active"]
    assert [r.data.tags["spot.record_id"] for r in live] == [folder.name]


def test_a_valid_record_from_spots_recorder_imports_whole(tmp_path):
    folder = _record(tmp_path)
    (folder / A / "plots" / "deep" / "er").mkdir(parents=True)
    (folder / A / "plots" / "deep" / "er" / "data.bin").write_bytes(bytes(range(256)) * 4)
    head = record_checks.read_record(folder)
    assert {k for k in head["tags"] if k.startswith("mlflow.")} <= set(record_checks.MLFLOW_TAGS)
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    (done,) = recorded.import_records(tmp_path / "rec", uri, "imported")
    assert done["action"] == "imported"
    client = MlflowClient(uri)
    run = client.get_run(done["run_id"])
    assert run.info.status == "FINISHED" and run.data.tags["spot.record_id"] == folder.name
    assert run.data.tags["mlflow.source.type"] == head["tags"]["mlflow.source.type"]
    assert run.data.tags["mlflow.runName"] == head["run_name"] and "mlflow.parentRunId" not in run.data.tags
    history = client.get_metric_history(run.info.run_id, "eval/score")
    assert [(m.step, m.value) for m in history] == [(0, 1.5), (50, 2.5), (100, 3.5)]
    stored = _stored(run)
    mine = sorted(p.relative_to(folder / A) for p in (folder / A).rglob("*") if p.is_file())
    assert sorted(p.relative_to(stored) for p in stored.rglob("*") if p.is_file()) == mine
    for rel in mine:
        assert (stored / rel).read_bytes() == (folder / A / rel).read_bytes(), rel
    # the shipped limits are MLflow's (names and values) and spot's (files)
    assert (
        record_checks.MAX_ARTIFACT_BYTES == 1 << 30
        and record_checks.MAX_ARTIFACTS_BYTES >= record_checks.MAX_ARTIFACT_BYTES
    )


def test_a_record_of_a_very_long_command_line_imports(tmp_path, monkeypatch):
    """spot's own recorder keeps a run's tags within MLflow's 8,000-character limit whatever the
    command line: the command is cut (with a note) in the description and in mlflow.source.name."""
    monkeypatch.setenv("SPOT_COMMAND", "spot run " + "x" * 20_000)
    _record(tmp_path)
    (done,) = recorded.import_records(tmp_path / "rec", f"sqlite:///{tmp_path / 'mlflow.db'}")
    run = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}").get_run(done["run_id"])
    assert len(run.data.tags["mlflow.source.name"]) <= 8000
    assert run.data.tags["mlflow.source.name"].endswith("more characters)")
    assert "more characters)" in run.data.tags["mlflow.note.content"]
