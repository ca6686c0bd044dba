"""Issue 43, finding 6: poisoned cache entries and models, bad directories, a full disk.

* A stage-cache entry whose digest is valid but which cannot be rebuilt, for any reason (a type in a
  module that is gone, 5,000 levels of nesting, a stored type that refuses its fields, a member
  that declares more than it holds, a truncated file), is evicted and recomputed once: the compute
  function runs exactly once and the next read is a hit.
* ``spot eval`` reads ``models/policy`` through the same reader, and checks the networks against
  those the run's config builds: a poisoned or wrong-shaped policy is one error naming the artifact.
* A cache, data or store folder that is a file, or read-only, is one error naming its variable.
* A full disk (ENOSPC) while writing a cache entry, a dataset, its card or the SAC cache is one
  error naming the file; no temporary file is left and the old file is untouched; an HDF5 write
  that fails in the kernel no longer crashes the process.
"""

import errno
import io
import json
import os
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import jax
import numpy as np
import pytest

from spot import SpotError, cache, config, store, tracking
from spot.data import formats, registry
from spot.data.dataset import RawDataset

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stages"))
    monkeypatch.delenv("SPOT_STORE", raising=False)
    return tmp_path / "stages"


class _Counter:
    def __init__(self, value):
        self.value, self.calls = value, 0

    def __call__(self):
        self.calls += 1
        return self.value


def _entry(tree_json: bytes, arrays: dict[str, np.ndarray] | None = None) -> bytes:
    """An entry's bytes holding the tree ``tree_json`` (raw JSON text) with a valid digest."""
    arrays = arrays or {}
    meta = {
        "__tree__": np.frombuffer(tree_json, np.uint8),
        "__digest__": np.frombuffer(cache._digest(tree_json, arrays).encode(), np.uint8),
    }
    buf = io.BytesIO()
    np.savez(buf, **meta, **arrays)
    return buf.getvalue()


def _nested(depth: int) -> bytes:
    """A list inside a list ... ``depth`` levels, written as text (json.dumps itself would recurse)."""
    return b'{"t": "list", "v": [' * depth + b'{"t": "none"}' + b"]}" * depth


def _oversized_member() -> bytes:
    """A valid entry whose array member is replaced by one whose .npy header declares 10**12
    float64s (8 TB) over 32 bytes of data."""
    good = cache.entry_bytes({"x": np.arange(4.0)})
    npy = io.BytesIO()
    np.lib.format.write_array_header_1_0(npy, {"descr": "<f8", "fortran_order": False, "shape": (10**12,)})
    npy.write(np.arange(4.0).tobytes())
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(good)) as src, zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as dst:
        for info in src.infolist():
            dst.writestr(info.filename, npy.getvalue() if info.filename == "a0.npy" else src.read(info))
    return out.getvalue()


POISONED = {
    # a type in a spot module that does not exist (renamed or removed since)
    "missing module": lambda: _entry(
        json.dumps({"t": "namedtuple", "type": "spot.no_such_module:Thing", "v": []}).encode()
    ),
    # a class that its module does not define
    "missing class": lambda: _entry(
        json.dumps({"t": "namedtuple", "type": "spot.batches:NoSuchClass", "v": []}).encode()
    ),
    # 5,000 levels of nesting: refused by counting, never parsed or rebuilt recursively
    "nested 5000 deep": lambda: _entry(_nested(5000)),
    "nested one past the limit": lambda: _entry(_nested(cache.MAX_DEPTH + 1)),
    # a spot dataclass whose constructor refuses the stored fields (RawDataset validates its arrays)
    "constructor refuses": lambda: _entry(
        json.dumps(
            {
                "t": "dataclass",
                "type": "spot.data.dataset:RawDataset",
                "k": ["observations", "actions", "rewards", "terminals", "timeouts"]
                + ["next_observations", "name", "metadata", "infos"],
                "v": [{"t": "str", "v": "x"}] * 5
                + [{"t": "none"}, {"t": "str", "v": "n"}]
                + [{"t": "dict", "k": [], "v": []}] * 2,
            }
        ).encode()
    ),
    # a dict whose keys cannot be keys (a list: TypeError unhashable)
    "unhashable dict key": lambda: _entry(json.dumps({"t": "dict", "k": [[1]], "v": [{"t": "none"}]}).encode()),
    # a NamedTuple with the wrong number of fields
    "wrong field count": lambda: _entry(
        json.dumps({"t": "namedtuple", "type": "spot.batches:Transitions", "v": [{"t": "none"}]}).encode()
    ),
    # a tree that is not UTF-8 JSON
    "tree not JSON": lambda: _entry(b"\xff\xfe not json"),
    # an array member whose header declares far more than the member holds
    "member declares 8 TB": _oversized_member,
    # a compressed npz (entries are never compressed: a deflate bomb could not be bounded)
    "compressed": lambda: _compressed(cache.entry_bytes({"x": np.zeros(1000)})),
    "truncated": lambda: cache.entry_bytes({"x": np.arange(50.0)})[:300],
    "empty": lambda: b"",
}


def _compressed(entry: bytes) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(entry)) as src, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            dst.writestr(info.filename, src.read(info))
    return out.getvalue()


@pytest.mark.parametrize("case", list(POISONED))
def test_a_poisoned_entry_is_evicted_and_recomputed_once(cache_dir, case):
    k = cache.key("reward", {"a": 1}, "v")
    cache_dir.mkdir(parents=True)
    (cache_dir / f"{k}.npz").write_bytes(POISONED[case]())
    compute = _Counter({"x": np.arange(3.0)})
    with pytest.warns(UserWarning, match="unusable"):
        value, hit, _ = cache.cached("reward", {"a": 1}, compute, code="v")
    assert not hit and compute.calls == 1 and value["x"].tolist() == [0.0, 1.0, 2.0]
    value, hit, _ = cache.cached("reward", {"a": 1}, compute, code="v")  # the recomputed entry is read back
    assert hit and compute.calls == 1 and value["x"].tolist() == [0.0, 1.0, 2.0]


def test_the_depth_limit_is_where_it_says(cache_dir):
    """A tree nested exactly MAX_DEPTH levels is stored and read back; one more is refused."""
    value: object = None
    for _ in range(cache.MAX_DEPTH):
        value = [value]
    cache.store("deep", value)
    found, back = cache.load("deep")
    depth = 0
    while isinstance(back, list):
        back, depth = back[0], depth + 1
    assert found and depth == cache.MAX_DEPTH and back is None
    with pytest.raises(cache.EntryError, match="nested deeper"):
        cache.read_entry_bytes(_entry(_nested(cache.MAX_DEPTH + 1)))


def test_a_poisoned_entry_imports_nothing_outside_spot(cache_dir):
    for ref in ("spot.__main__:X", "spot..x:Y", "spot.cli:main.__globals__"):
        data = _entry(json.dumps({"t": "namedtuple", "type": ref, "v": []}).encode())
        with pytest.raises(cache.EntryError):
            cache.read_entry_bytes(data)
    assert "spot.__main__" not in sys.modules


# --------------------------------------------------------------------------- spot eval's models/policy
def _uri(tmp_path):
    return f"sqlite:///{tmp_path / 'mlflow.db'}"


HOPPER = ("hopper-medium-replay", 11, 3)  # gymnasium Hopper-v5: 11 observations, 3 actions


def _policy(cfg, obs_dim, act_dim):
    from spot.policy import iql

    st = iql.init_state(jax.random.key(0), obs_dim, act_dim, cfg.iql)
    return {"actor": st.actor.params, "critic": st.critic.params, "value": st.value.params,
            "target_critic": st.target_critic_params}  # fmt: skip


def _saved_run(tmp_path, value, **head):
    cfg = config.load(None, ["budget=tiny", f"tracking.uri={_uri(tmp_path)}", "tracking.experiment=h43"])
    with tracking.start_run(cfg, {"name": HOPPER[0]}, system_metrics=False) as tr:
        tracking.save_model(
            tr, tmp_path / "out", "policy", "p", value, {}, **{"env": HOPPER[0], "eval_seed": 10000, **head}
        )
    return tr.run_id, cfg


def test_a_policy_of_the_runs_networks_loads(tmp_path):
    cfg = config.load(None, ["budget=tiny"])
    run_id, _ = _saved_run(tmp_path, _policy(cfg, HOPPER[1], HOPPER[2]))
    params, head = tracking.load_model(run_id, "policy", _uri(tmp_path))
    w = params["actor"]["params"]["Dense_0"]["kernel"]
    assert w.shape == (cfg.iql.hidden[-1], 3) and head["env"] == HOPPER[0]


def test_a_policy_with_wrong_shapes_is_one_error_naming_the_artifact(tmp_path, capsys):
    from spot import cli

    cfg = config.load(None, ["budget=tiny"])
    run_id, _ = _saved_run(tmp_path, _policy(cfg, HOPPER[1], 2))  # 2 actions: Hopper has 3
    with pytest.raises(SpotError, match=r"models/policy\.npz: .*is float32\[2\]; expected float32\[3\]"):
        tracking.load_model(run_id, "policy", _uri(tmp_path))
    capsys.readouterr()
    assert cli.main(["eval", run_id, "--tracking-uri", _uri(tmp_path)]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "models/policy.npz" in errors[0] and "expected float32[3]" in errors[0]
    assert "Traceback" not in err


@pytest.mark.parametrize(
    "value, head, match",
    [
        ({"w": np.ones(3, np.float32)}, {}, r"policy\.npz: not the expected networks: \d+ arrays missing"),
        ("nan", {}, r"policy\.npz: .* holds non-finite values"),
        ("float64", {}, r"policy\.npz: .* is float64\[.*\]; expected float32\["),
        ("ok", {"eval_seed": "x"}, r"policy\.json: 'eval_seed' is 'x'; expected an integer"),
        ("ok", {"env": "no-such-env"}, r"policy\.json: 'env': "),
        ("ok", {"env": ["hopper"]}, r"policy\.json: 'env' is \['hopper'\]"),
    ],
)
def test_a_poisoned_policy_is_one_error(tmp_path, value, head, match):
    cfg = config.load(None, ["budget=tiny"])
    if isinstance(value, str):
        good = _policy(cfg, HOPPER[1], HOPPER[2])
        if value == "nan":
            layer = good["value"]["params"]["MLP_0"]["Dense_0"]
            layer["bias"] = np.full_like(layer["bias"], np.nan)
        elif value == "float64":
            good = jax.tree.map(lambda a: np.asarray(a, np.float64), good)
        value = good
    run_id, _ = _saved_run(tmp_path, value, **head)
    with pytest.raises(SpotError, match=match):
        tracking.load_model(run_id, "policy", _uri(tmp_path))


def test_a_saved_model_nested_5000_deep_is_one_error(tmp_path):
    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "policy.npz").write_bytes(_entry(_nested(5000)))
    (folder / "policy.json").write_text("{}")
    with pytest.raises(SpotError, match="not a readable saved model .*nested deeper"):
        tracking.models.read_model(folder, "policy")
    (folder / "policy.json").write_text("[" * 5000 + "]" * 5000)  # a header nested as deep
    (folder / "policy.npz").write_bytes(cache.entry_bytes({"w": np.ones(2)}))
    with pytest.raises(SpotError, match="not a readable saved model"):
        tracking.models.read_model(folder, "policy")


# --------------------------------------------------------------------------- bad directories
def test_a_cache_dir_that_is_a_file_is_one_error(tmp_path, monkeypatch):
    monkeypatch.delenv("SPOT_STORE", raising=False)
    file = tmp_path / "not-a-dir"
    file.write_text("x")
    for where in (file, file / "sub"):
        monkeypatch.setenv("SPOT_CACHE_DIR", str(where))
        with pytest.raises(SpotError, match=rf"^\$SPOT_CACHE_DIR: '{where}' ") as got:
            cache.cached("reward", {}, _Counter(1), code="v")
        assert f"'{file}' is a file" in str(got.value) or f"'{where}' is a file" in str(got.value)
    assert file.read_text() == "x"


def test_a_store_that_is_a_file_is_one_error(tmp_path, monkeypatch):
    file = tmp_path / "store-file"
    file.write_text("x")
    monkeypatch.setenv("SPOT_STORE", str(file))
    with pytest.raises(SpotError, match=rf"\$SPOT_STORE \({file}\): '{file}/stages' .*'{file}' is a file"):
        cache.cached("reward", {}, _Counter(1), code="v")
    with pytest.raises(SpotError, match=r"\$SPOT_STORE"):
        store.datasets()


def test_a_data_dir_that_is_a_file_is_one_error_in_the_cli(tmp_path, monkeypatch, capsys):
    from spot import cli

    file = tmp_path / "data-file"
    file.write_text("x")
    monkeypatch.setenv("SPOT_DATA_DIR", str(file))
    monkeypatch.delenv("SPOT_STORE", raising=False)
    assert cli.main(["data", "build", "drawer-open", "--size", "tiny", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: $SPOT_DATA_DIR: '{file}' is a file, not a folder; expected a folder spot can write to"]


@pytest.fixture
def read_only(tmp_path):
    """A read-only folder: mode 0555, or where that does not restrict (root) a read-only 16 KB
    tmpfs mounted there (unmounted after the test); skipped where neither is possible."""
    path = tmp_path / "ro"
    path.mkdir()
    path.chmod(0o555)
    mounted = False
    if os.access(path, os.W_OK):  # root ignores the mode bits
        path.chmod(0o755)
        got = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=16k", "tmpfs", str(path)], capture_output=True)
        if got.returncode != 0 or os.access(path, os.W_OK):
            pytest.skip("no way to make a read-only folder here (root, and no tmpfs mount)")
        mounted = True
    yield path
    if mounted:
        subprocess.run(["umount", str(path)], check=True)
    else:
        path.chmod(0o755)


@pytest.mark.parametrize("var", ["SPOT_CACHE_DIR", "SPOT_DATA_DIR", "SPOT_STORE"])
def test_a_read_only_dir_is_one_error(tmp_path, monkeypatch, read_only, var):
    for v in ("SPOT_CACHE_DIR", "SPOT_DATA_DIR"):
        monkeypatch.setenv(v, str(tmp_path / v))
    monkeypatch.delenv("SPOT_STORE", raising=False)
    monkeypatch.setenv(var, str(read_only))
    where = read_only / "stages" if var == "SPOT_STORE" else read_only
    reason = r"\((Permission denied|Read-only file system)\)"
    with pytest.raises(SpotError, match=rf"^\${var}.*'{where}' is not a writable folder {reason}"):
        if var == "SPOT_DATA_DIR":
            registry.build("drawer-open", "tiny", 0, progress=False)
        else:
            cache.cached("reward", {}, _Counter(1), code="v")
    assert list(read_only.iterdir()) == []


# --------------------------------------------------------------------------- a full disk
@pytest.fixture
def full_disk(monkeypatch):
    """Every write through spot.store.write_atomic writes its first 100 bytes, then ENOSPC."""
    seen = []

    def write(fd, data):
        os.write(fd, bytes(data[:100]))
        seen.append(len(data))
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(store, "_write_all", write)
    return seen


def _no_temp(folder: Path) -> None:
    assert not [p for p in folder.rglob("*") if ".tmp-" in p.name]


def test_a_full_disk_writing_a_cache_entry(cache_dir, full_disk, monkeypatch):
    compute = _Counter({"x": np.arange(3.0)})
    with pytest.raises(SpotError, match=r"^no space left on device writing .*/reward-\w+\.npz$"):
        cache.cached("reward", {"a": 1}, compute, code="v")
    assert full_disk and compute.calls == 1
    _no_temp(cache_dir)
    k = cache.key("reward", {"a": 2}, "v")
    monkeypatch.undo()
    monkeypatch.setenv("SPOT_CACHE_DIR", str(cache_dir))
    cache.store(k, {"old": np.ones(2)})
    old = (cache_dir / f"{k}.npz").read_bytes()
    monkeypatch.setattr(store, "_write_all", lambda fd, data: (_ for _ in ()).throw(OSError(errno.ENOSPC, "full")))
    with pytest.raises(SpotError, match="no space left on device"):
        cache.store(k, {"new": np.zeros(2)})
    assert (cache_dir / f"{k}.npz").read_bytes() == old
    _no_temp(cache_dir)


def _raw(n=400, seed=0):
    rng = np.random.default_rng(seed)
    done = np.zeros(n, bool)
    done[-1] = True
    return RawDataset(
        rng.normal(size=(n, 4)).astype(np.float32),
        rng.uniform(-1, 1, (n, 2)).astype(np.float32),
        rng.normal(size=n).astype(np.float32),
        np.zeros(n, bool),
        done,
    )


def test_a_full_disk_writing_a_dataset_and_its_card(tmp_path, full_disk):
    path = tmp_path / "data" / "x__tiny__seed0.hdf5"
    path.parent.mkdir()
    path.write_bytes(b"old dataset")
    registry.card_path(path).write_text('{"old": true}')
    with pytest.raises(SpotError, match=rf"^no space left on device writing {path}$"):
        formats.write_d4rl_hdf5(_raw(), path, {"name": "x"})
    with pytest.raises(SpotError, match=rf"^no space left on device writing {registry.card_path(path)}$"):
        registry._write_card(path, {"name": "x"})
    assert path.read_bytes() == b"old dataset" and registry.card_path(path).read_text() == '{"old": true}'
    assert len(full_disk) == 2
    _no_temp(tmp_path)


def test_a_full_disk_writing_the_sac_cache(tmp_path, full_disk):
    from spot.recipes import locomotion_sac, sac, sac_train

    path = tmp_path / "sac" / "Hopper-v5__tiny__seed0__abc.msgpack"
    path.parent.mkdir()
    path.write_bytes(b"old cache")
    locomotion_sac.checksum_path(path).write_text("old  sum\n")
    snap = sac_train.Snapshot(0, 1.0, 0.0, {"w": np.ones(2, np.float32)})
    result = sac_train.SACResult("Hopper-v5", 0, sac.SACConfig(), [snap], {"rewards": np.zeros(3)}, {"total": 1.0})
    with pytest.raises(SpotError, match=rf"^no space left on device writing {path}$"):
        locomotion_sac._save(result, path)
    with pytest.raises(SpotError, match="no space left on device writing .*msgpack.sha256"):
        locomotion_sac._write_checksum(path)
    run = object.__new__(sac_train._Run)  # the training checkpoint: only its payload and timing are used
    run.payload, run.timing = (lambda: {"t": 1}), {"checkpoint": 0.0}
    ckpt = tmp_path / "sac" / "ckpt.msgpack"
    with pytest.raises(SpotError, match=rf"^no space left on device writing {ckpt}$"):
        run.save(ckpt)
    assert path.read_bytes() == b"old cache" and locomotion_sac.checksum_path(path).read_text() == "old  sum\n"
    assert not ckpt.exists()
    _no_temp(tmp_path)


def test_a_full_disk_writing_a_saved_model(tmp_path, full_disk):
    with pytest.raises(SpotError, match=r"no space left on device writing .*policy\.npz"):
        cache.write_entry(tmp_path / "m" / "policy.npz", {"w": np.ones(2)})
    _no_temp(tmp_path)


def test_errors_other_than_a_full_disk_name_the_file(tmp_path):
    parent = tmp_path / "a-file"
    parent.write_text("x")
    with pytest.raises(SpotError, match=rf"^cannot write {parent}/y\.npz \(.+\)$"):
        store.write_atomic(parent / "y.npz", b"data")
    assert str(store.write_error("f", OSError("HDF5: errno = 28, error message = 'No space left on device'"))) == (
        "no space left on device writing f"
    )


def test_a_dataset_write_the_kernel_refuses_does_not_crash(tmp_path):
    """A real failed write (the file-size limit, as a full disk would): HDF5 writing to disk itself
    crashes the process (SIGSEGV at the failed close); spot's write is one error, no temp file."""
    script = textwrap.dedent(
        f"""
        import resource, signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (256 * 1024, 256 * 1024))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the kernel then fails the write (EFBIG)
        import numpy as np
        from spot import SpotError
        from spot.data import formats
        from spot.data.dataset import RawDataset
        n = 50_000
        rng = np.random.default_rng(0)
        raw = RawDataset(rng.normal(size=(n, 11)).astype(np.float32), rng.uniform(-1, 1, (n, 3)).astype(np.float32),
                         rng.normal(size=n).astype(np.float32), np.zeros(n, bool), np.r_[np.zeros(n - 1, bool), True])
        try:
            formats.write_d4rl_hdf5(raw, {str(tmp_path / "d.hdf5")!r}, {{"name": "x"}})
        except SpotError as e:
            print("error:", e)
            raise SystemExit(2)
        """
    )
    got = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
        timeout=300,
    )
    assert got.returncode == 2, (got.returncode, got.stderr[-2000:])
    assert got.stdout.strip() == f"error: cannot write {tmp_path / 'd.hdf5'} (File too large)"
    assert list(tmp_path.iterdir()) == []
