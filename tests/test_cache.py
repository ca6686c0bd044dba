"""The stage cache on its own: data-only entries, eviction of unusable ones, complete keys, code versions."""

import io
import json
import pickle
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from spot import cache, codeversion, stages
from spot.batches import Transitions
from tests.conftest import make_dataset


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stages"))
    return tmp_path / "stages"


class _Counter:
    def __init__(self, value):
        self.value, self.calls = value, 0

    def __call__(self):
        self.calls += 1
        return self.value


# --------------------------------------------------------------------------- the entry format
def _cvae_params():
    from spot.subgoal.cvae import CVAEParams

    net = {"params": {"enc": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3), "bias": np.zeros(3, np.float32)}}}
    return CVAEParams(
        net=net, obs_mean=np.ones(3, np.float32), obs_std=np.full(3, 2.0, np.float32), hidden=(32, 64), latent_dim=4
    )


def test_round_trip_keeps_values_and_types(cache_dir):
    value = {
        "params": _cvae_params(),
        "history": [{"step": 1, "loss": 0.5, "nan": float("nan")}, {"step": 2, "loss": 0.25, "nan": None}],
        "data": Transitions(np.eye(2, dtype=np.float32), np.zeros((2, 1)), np.arange(2), np.eye(2), np.ones(2, bool)),
        "scalars": (np.float32(1.5), np.int64(7), True, "pt", 3),
        7: [np.array([], np.int32), np.zeros((0, 4))],
    }
    cache.store("k", value)
    found, got = cache.load("k")
    assert found
    p = got["params"]
    assert type(p).__name__ == "CVAEParams" and p.hidden == (32, 64) and p.latent_dim == 4
    np.testing.assert_array_equal(p.net["params"]["enc"]["kernel"], np.arange(6).reshape(2, 3))
    assert p.net["params"]["enc"]["kernel"].dtype == np.float32
    assert got["history"][0]["step"] == 1 and np.isnan(got["history"][0]["nan"]) and got["history"][1]["nan"] is None
    assert isinstance(got["data"], Transitions) and got["data"].mask.dtype == bool
    s = got["scalars"]
    assert isinstance(s, tuple) and s[0] == np.float32(1.5) and s[0].dtype == np.float32
    assert s[1].dtype == np.int64 and s[1] == 7 and s[2:] == (True, "pt", 3) and type(s[4]) is int
    assert got[7][0].dtype == np.int32 and got[7][1].shape == (0, 4)
    assert list(cache_dir.iterdir()) == [cache_dir / "k.npz"]  # no temporary file left behind


def test_the_file_is_a_plain_npz_without_pickles(cache_dir):
    cache.store("k", {"w": np.arange(3.0), "name": "pt"})
    with np.load(cache_dir / "k.npz", allow_pickle=False) as z:
        tree = json.loads(z["__tree__"].tobytes())
    assert tree == {"t": "dict", "k": ["w", "name"], "v": [{"t": "array", "ref": "a0"}, {"t": "str", "v": "pt"}]}


def test_values_that_are_not_data_are_refused():
    class Local:
        pass

    with pytest.raises(TypeError, match="cannot store"):
        cache.encode({"f": print})
    with pytest.raises(TypeError, match="dtype object"):
        cache.encode(np.array([object()]))
    with pytest.raises(TypeError, match="local class"):
        from typing import NamedTuple

        class LocalTuple(NamedTuple):
            x: int

        cache.encode(LocalTuple(1))
    with pytest.raises(TypeError, match="cannot store"):
        cache.encode(Local())


# --------------------------------------------------------------------------- cached, hits, eviction
def test_a_miss_computes_and_a_hit_does_not(cache_dir):
    compute = _Counter({"x": np.arange(3)})
    value, hit, key = cache.cached("cvae", {"a": 1}, compute, code="v1")
    assert not hit and compute.calls == 1 and key.startswith("cvae-")
    value, hit, again = cache.cached("cvae", {"a": 1}, compute, code="v1")
    assert hit and again == key and compute.calls == 1 and value["x"].tolist() == [0, 1, 2]
    assert cache.key("cvae", {"a": 2}, "v1") != key  # another dependency
    assert cache.key("cvae", {"a": 1}, "v2") != key  # another code version
    assert cache.key("reward", {"a": 1}, "v1") != key  # another stage


def test_default_code_version_is_the_compute_functions_source(cache_dir):
    compute = _Counter(1)
    _, _, key = cache.cached("s", {}, compute)
    assert key == cache.key("s", {}, cache.code_version(_Counter))  # a callable instance: its class's source
    assert cache.code_version(compute.__call__) == cache.code_version(_Counter)
    assert f"{_Counter.__module__}:_Counter" in cache.code_parts(compute, package=_Counter.__module__)


def test_a_corrupt_entry_is_evicted_and_recomputed(cache_dir):
    compute = _Counter({"x": np.arange(3)})
    _, _, key = cache.cached("cvae", {"a": 1}, compute, code="v")
    path = cache_dir / f"{key}.npz"
    payload = bytearray(path.read_bytes())
    i = payload.index(np.arange(3).tobytes())  # flip a byte of the stored array
    payload[i] ^= 0xFF
    path.write_bytes(bytes(payload))
    with pytest.warns(UserWarning, match="unusable"):
        value, hit, _ = cache.cached("cvae", {"a": 1}, compute, code="v")
    assert not hit and compute.calls == 2 and value["x"].tolist() == [0, 1, 2]
    assert cache.cached("cvae", {"a": 1}, compute, code="v")[1]  # the recomputed entry is used again
    path.write_bytes(path.read_bytes()[:100])  # truncated
    with pytest.warns(UserWarning, match="unusable"):
        assert not cache.cached("cvae", {"a": 1}, compute, code="v")[1]


class _Exploit:
    """Unpickling this runs ``Path(marker).write_text('ran')``."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (self.marker, "ran"))


def _npz(path: Path, tree, arrays: dict, *, digest: bool = True, allow_pickle: bool = False) -> None:
    tree_bytes = json.dumps(tree).encode()
    meta = {"__tree__": np.frombuffer(tree_bytes, np.uint8)}
    if digest:
        meta["__digest__"] = np.frombuffer(cache._digest(tree_bytes, arrays).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **meta, **arrays, allow_pickle=allow_pickle)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(buf.getvalue())


def test_an_entry_crafted_to_run_code_is_never_executed(cache_dir, tmp_path):
    marker = tmp_path / "marker"
    exploit = pickle.dumps({"params": _Exploit(marker)})
    pickle.loads(pickle.dumps(_Exploit(tmp_path / "control")))
    assert (tmp_path / "control").read_text() == "ran"  # the exploit works on anything that unpickles

    compute = _Counter({"x": np.arange(2)})
    k = cache.key("reward", {"a": 1}, "v")
    # 1. an old-format pickle entry under the same key: ignored (never opened), left alone
    (cache_dir / f"{k}.pkl").parent.mkdir(parents=True)
    (cache_dir / f"{k}.pkl").write_bytes(exploit)
    (cache_dir / f"{k}.sha256").write_text("whatever")
    value, hit, _ = cache.cached("reward", {"a": 1}, compute, code="v")
    assert not hit and compute.calls == 1 and value["x"].tolist() == [0, 1]
    assert (cache_dir / f"{k}.pkl").exists()
    # 2. the pickle under the new entry's name
    (cache_dir / f"{k}.npz").write_bytes(exploit)
    with pytest.warns(UserWarning, match="unusable"):
        assert not cache.cached("reward", {"a": 1}, compute, code="v")[1]
    # 3. an npz whose array is a pickled object array (numpy pickles object dtype)
    _npz(
        cache_dir / f"{k}.npz",
        {"t": "array", "ref": "a0"},
        {"a0": np.array([_Exploit(marker)], object)},
        digest=False,
        allow_pickle=True,
    )
    with pytest.warns(UserWarning, match="unusable"):
        assert not cache.cached("reward", {"a": 1}, compute, code="v")[1]
    # 4. a well-formed entry that names a callable outside spot, or a spot function, as its "type"
    for ref in ("builtins:eval", "os:system", "pathlib:Path", "spot.runtime:configure"):
        _npz(cache_dir / f"{k}.npz", {"t": "namedtuple", "type": ref, "v": [{"t": "str", "v": str(marker)}]}, {})
        with pytest.warns(UserWarning, match="unusable"):
            assert not cache.cached("reward", {"a": 1}, compute, code="v")[1]
    assert not marker.exists()
    assert compute.calls == 1 + 1 + 1 + 4


@pytest.mark.parametrize(
    "tree",
    [
        {"t": "array", "ref": "a9"},  # a missing array
        {"t": "dict", "k": ["a", "b"], "v": [{"t": "none"}]},  # keys and values differ
        {"t": "dataclass", "type": "spot.subgoal.cvae:CVAEParams", "k": ["net"], "v": [{"t": "none"}]},  # fields
        {"t": "int", "v": "1"},
        {"t": "lambda"},
        [1, 2],
    ],
)
def test_an_entry_of_the_wrong_structure_is_evicted_and_recomputed(cache_dir, tree):
    k = cache.key("cvae", {}, "v")
    _npz(cache_dir / f"{k}.npz", tree, {})
    compute = _Counter({"ok": np.ones(1)})
    with pytest.warns(UserWarning, match="unusable"):
        value, hit, _ = cache.cached("cvae", {}, compute, code="v")
    assert not hit and compute.calls == 1 and value["ok"].tolist() == [1.0]
    with np.load(cache_dir / f"{k}.npz", allow_pickle=False) as z:  # replaced by the recomputed entry
        assert json.loads(z["__tree__"].tobytes())["t"] == "dict"


# --------------------------------------------------------------------------- complete keys
def _reward_key(ds) -> str:
    return cache.key("reward", {"data": stages.dataset_deps(ds)}, "v")


def test_the_dataset_in_keys_covers_episode_ends_next_observations_and_infos():
    ds = make_dataset([5, 7])
    base = _reward_key(ds)
    assert _reward_key(make_dataset([5, 7])) == base  # same content, same key
    terminals = ds.terminals.copy()
    terminals[4] = True
    assert _reward_key(ds.replace(terminals=terminals)) != base
    next_obs = ds.next_observations.copy()
    next_obs[3, 0] += 1.0
    assert _reward_key(ds.replace(next_observations=next_obs)) != base
    ids = ds.episode_ids.copy()
    ids[5:] += 1  # an episode boundary moved (a timeout in the raw data)
    ids[4] = 1
    assert _reward_key(ds.replace(episode_ids=ids)) != base
    assert _reward_key(ds.replace(infos={"dense_reward": np.zeros(len(ds), np.float32)})) != base
    assert _reward_key(ds.replace(name="renamed", metadata={"x": 1})) == base  # names are not data


# --------------------------------------------------------------------------- code versions
@pytest.fixture
def toy_package(tmp_path, monkeypatch):
    """A package ``toystages`` on sys.path: ``stage.py`` (a stage and an unrelated function) and
    ``helper.py`` (which the stage imports inside its body)."""
    root = tmp_path / "pkgs"
    pkg = root / "toystages"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "helper.py").write_text("def scale(x):\n    return 2 * x\n")
    (pkg / "other.py").write_text("def unused():\n    return 0\n")
    (pkg / "stage.py").write_text(
        textwrap.dedent("""
        from toystages import other

        def _prepare(x):
            return x + 1

        def stage(x):
            from toystages import helper

            def compute():
                return helper.scale(_prepare(x))

            return compute

        def unrelated():
            return other.unused()
    """)
    )
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)  # reloads compile the edited source, never a stale .pyc
    yield pkg
    for name in [m for m in sys.modules if m.startswith("toystages")]:
        del sys.modules[name]


def test_code_version_follows_the_stage_and_what_it_runs(toy_package):
    import importlib

    stage = importlib.import_module("toystages.stage")
    compute = stage.stage(1)  # a closure: its version is the enclosing stage's
    parts = cache.code_parts(compute, package="toystages")
    assert set(parts) == {"toystages.stage:stage", "toystages.stage:_prepare", "toystages.helper", "toystages"}
    v0 = cache.code_version(compute, package="toystages")
    assert cache.code_version(stage.stage, package="toystages") == v0

    def edit(name: str, old: str, new: str) -> str:
        path = toy_package / name
        path.write_text(path.read_text().replace(old, new))
        assert cache.code_version(stage.stage, package="toystages") == current  # the loaded code ran, not the file
        for module in ("toystages.helper", "toystages.other", "toystages.stage"):
            importlib.reload(sys.modules[module])  # reloading picks the edit up
        return cache.code_version(sys.modules["toystages.stage"].stage, package="toystages")

    current = v0
    current = edit("stage.py", "def unrelated():\n    return other.unused()", "def unrelated():\n    return 1")
    assert current == v0
    current = edit("other.py", "return 0", "return 1")  # not run by the stage
    assert current == v0
    current = edit("stage.py", "def _prepare(x):\n", "def _prepare(x):\n    # a comment\n")  # no code change
    assert current == v0
    v1 = current = edit("helper.py", "2 * x", "3 * x")  # a module the stage imports
    assert v1 != v0
    v2 = current = edit("stage.py", "return x + 1", "return x + 2")  # a helper the stage calls
    assert v2 not in (v0, v1)
    v3 = edit("stage.py", "return helper.scale(", "return -helper.scale(")  # the stage itself
    assert v3 not in (v0, v1, v2)


def test_code_versions_do_not_depend_on_where_the_code_is_installed(tmp_path, monkeypatch):
    """Two copies of one package at different paths (two checkouts, two nodes sharing a store) give
    their stages the same code version, also when the code reads ``__file__``."""
    import importlib

    source = "from pathlib import Path\n\ndef stage(x):\n    return Path(__file__).parent, x + 1\n"
    versions = []
    for where in ("a", "b"):
        root = tmp_path / where / "pkgs"
        (root / "wherepkg").mkdir(parents=True)
        (root / "wherepkg" / "__init__.py").write_text("")
        (root / "wherepkg" / "stage.py").write_text(source)
        monkeypatch.syspath_prepend(str(root))
        for name in [m for m in sys.modules if m.startswith("wherepkg")]:
            del sys.modules[name]
        importlib.invalidate_caches()
        module = importlib.import_module("wherepkg.stage")
        assert module.stage(1)[0] == root / "wherepkg"  # this copy is the one loaded
        versions.append(cache.code_version(module.stage, package="wherepkg"))
    for name in [m for m in sys.modules if m.startswith("wherepkg")]:
        del sys.modules[name]
    assert versions[0] == versions[1]


def test_the_real_stages_versions_cover_their_modules():
    from spot.run import reward_stages, subgoal_stages

    reward = cache.code_parts(reward_stages.learned_reward)
    assert {
        "spot.run.reward_stages:learned_reward",
        "spot.run.reward_stages:_reward_deps",  # a helper of the stage's own module
        "spot.run.context",  # Context, the slot types, save_model, dataset_deps: a module the stage uses
        "spot.reward.train",
        "spot.reward.pt",
        "spot.reward.mr",
        "spot.nets",
    } <= set(reward)
    assert "spot.run.subgoal_stages:cvae_stage" not in reward and "spot.subgoal.cvae" not in reward
    assert not {p for p in reward if p.startswith(("spot.run.policy_stages", "spot.run.methods"))}
    assert not [m for m in reward if m.split(":")[0].startswith("spot.config")]  # config values are in the deps
    cvae = cache.code_parts(subgoal_stages.cvae_stage)
    assert {"spot.run.subgoal_stages:cvae_stage", "spot.run.context", "spot.subgoal.cvae"} <= set(cvae)
    assert "spot.reward.pt" not in cvae and "spot.run.reward_stages:learned_reward" not in cvae
    assert cache.code_version(reward_stages.learned_reward) != cache.code_version(subgoal_stages.cvae_stage)
    assert stages.learned_reward is reward_stages.learned_reward  # the plugin API's name, the same stage


def test_figures_read_a_cvae_entry_and_refuse_a_pickle(cache_dir, tmp_path):
    from spot import SpotError, figures

    params = _cvae_params()
    cache.store("cvae-test", {"params": params, "history": []})
    got = figures.load_cvae(cache_dir / "cvae-test.npz")
    assert got.latent_dim == 4 and got.hidden == (32, 64)
    np.testing.assert_array_equal(got.obs_std, params.obs_std)
    marker = tmp_path / "marker"
    (tmp_path / "cvae-old.pkl").write_bytes(pickle.dumps({"params": _Exploit(marker)}))
    with pytest.raises(SpotError, match="is not a stage-cache entry"):
        figures.load_cvae(tmp_path / "cvae-old.pkl")
    assert not marker.exists()


def test_process_state_in_module_globals_is_not_code(monkeypatch):
    """Module globals a process fills as it runs (a private set of servers that answered, of files
    verified) are state, not code: a reused Ray actor's second trial gets the same keys as its first."""
    from spot.data import registry
    from spot.tracking import store as tracking_store

    before = cache.code_version(stages.learned_reward)
    monkeypatch.setattr(tracking_store, "_ANSWERED", {"http://127.0.0.1:5000"})
    monkeypatch.setattr(registry, "_VERIFIED", {("/data/x.hdf5", 1, 2)})
    codeversion._STATE_CACHE.clear()
    assert cache.code_version(stages.learned_reward) == before
    state = codeversion._state_names(vars(tracking_store)) | codeversion._state_names(vars(registry))
    assert {"_ANSWERED", "_VERIFIED"} <= state


def test_fast_compiled_entries_have_their_own_keys(monkeypatch):
    """Under SPOT_FAST_COMPILE the programs round differently: their entries must never be a normal
    run's (and the normal keys stay what they were)."""
    deps = {"a": 1, "b": np.arange(3)}
    monkeypatch.delenv("SPOT_FAST_COMPILE", raising=False)
    plain = cache.key("reward", deps, "c0")
    monkeypatch.setenv("SPOT_FAST_COMPILE", "0")
    assert cache.key("reward", deps, "c0") == plain
    monkeypatch.setenv("SPOT_FAST_COMPILE", "1")
    fast = cache.key("reward", deps, "c0")
    assert fast != plain and fast.startswith("reward-")
