"""The shared store (spot.store): a folder or an S3 bucket (a real moto S3 server on loopback).

Atomic, verified entries; a tampered entry deleted; the lock (flock / S3 lease with a conditional
PUT) making concurrent processes compute a stage-cache entry once; a dataset built on one "node"
fetched, not rebuilt, by another.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from spot import SpotError, cache, store

REPO = Path(__file__).resolve().parents[1]
BUCKET = "spot-test"


# --------------------------------------------------------------------------- a real S3 server
@contextlib.contextmanager
def moto_server(log: Path):
    """A moto S3 server (server mode, a subprocess) on 127.0.0.1; yields its endpoint URL and the
    environment a client needs (dummy credentials, the endpoint). Versioning is on for ``BUCKET``,
    so every PUT of a key is counted."""
    import boto3

    from spot.sweep.mlflow_server import free_port

    port = free_port()
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    url = f"http://127.0.0.1:{port}"
    env = {
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_DEFAULT_REGION": "us-east-1",
        "AWS_ENDPOINT_URL": url,
    }
    try:
        s3 = boto3.client("s3", endpoint_url=url, **_creds(env))
        deadline = time.monotonic() + 60
        while True:
            try:
                s3.create_bucket(Bucket=BUCKET)
                break
            except Exception:  # noqa: BLE001 - not up yet
                assert proc.poll() is None and time.monotonic() < deadline, log.read_text()[-2000:]
                time.sleep(0.3)
        s3.put_bucket_versioning(Bucket=BUCKET, VersioningConfiguration={"Status": "Enabled"})
        yield url, env, s3
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _creds(env: dict[str, str]) -> dict[str, str]:
    return {
        "aws_access_key_id": env["AWS_ACCESS_KEY_ID"],
        "aws_secret_access_key": env["AWS_SECRET_ACCESS_KEY"],
        "region_name": env["AWS_DEFAULT_REGION"],
    }


def versions(s3, prefix: str) -> dict[str, int]:
    """``{key: number of PUTs}`` under ``prefix`` (the bucket is versioned), leases left out."""
    out: dict[str, int] = {}
    for page in s3.get_paginator("list_object_versions").paginate(Bucket=BUCKET, Prefix=prefix):
        for v in page.get("Versions", []):
            if "/locks/" not in v["Key"]:
                out[v["Key"]] = out.get(v["Key"], 0) + 1
    return out


@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    with moto_server(tmp_path_factory.mktemp("moto") / "moto.log") as server:
        yield server


@pytest.fixture
def s3_env(s3, monkeypatch, request):
    """``$SPOT_STORE`` naming a fresh prefix of the moto bucket."""
    url, env, client = s3
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    prefix = f"{request.node.name}-{os.getpid()}"
    monkeypatch.setenv(store.ENV_URI, f"s3://{BUCKET}/{prefix}")
    monkeypatch.delenv(store.ENV_OPTIONS, raising=False)
    return client, prefix


# --------------------------------------------------------------------------- naming
@pytest.mark.parametrize(
    "uri, match",
    [
        ("", "expected a folder path or s3://bucket/prefix"),
        ("gs://b/p", "expected a folder path, file:///path or s3://bucket/prefix"),
        ("s3:///p", "no bucket"),
    ],
)
def test_bad_store_uris_are_refused(uri, match):
    with pytest.raises(SpotError, match=match):
        store.check_uri(uri)


def test_store_names_normalise_and_options_are_checked(tmp_path):
    assert store.check_uri(f"file://{tmp_path}/x") == str(tmp_path / "x")
    assert store.check_uri("s3://b/p/") == "s3://b/p"
    env = store.environment("s3://b/p", {"endpoint_url": "http://h:9000"})
    assert env == {"SPOT_STORE": "s3://b/p", "SPOT_STORE_OPTIONS": '{"endpoint_url": "http://h:9000"}'}
    assert store.environment(None) == {}
    with pytest.raises(SpotError, match="'region': unknown store option"):
        store.check_options({"region": "x"})


# --------------------------------------------------------------------------- entries
def _roundtrip(st: store.Store, tmp_path: Path) -> None:
    st.put_bytes("a/b.bin", b"hello")
    assert st.get_bytes("a/b.bin") == b"hello" and st.get_bytes("a/none.bin") is None
    src = tmp_path / "src.hdf5"
    src.write_bytes(os.urandom(5000))
    rec = st.put_file("d.hdf5", src)
    assert rec["size"] == 5000 and st.record("d.hdf5")["sha256"] == rec["sha256"]
    dst = tmp_path / "got" / "d.hdf5"
    assert st.get_file("d.hdf5", dst) and dst.read_bytes() == src.read_bytes()
    assert not [p for p in dst.parent.iterdir() if ".tmp-" in p.name]  # no temporary file left
    assert not st.get_file("missing.hdf5", tmp_path / "m.hdf5") and not (tmp_path / "m.hdf5").exists()
    # tampered after upload: fails its record, is deleted (so it is rebuilt), and is not used
    st.put_bytes("d.hdf5", b"tampered")
    dst2 = tmp_path / "got2" / "d.hdf5"
    assert not st.get_file("d.hdf5", dst2) and not dst2.exists()
    assert not st.exists("d.hdf5") and st.record("d.hdf5") is None


def test_a_folder_store_writes_atomically_and_verifies(tmp_path):
    st = store.Store(str(tmp_path / "store"))
    _roundtrip(st, tmp_path)
    assert not list((tmp_path / "store").rglob("*.tmp-*"))


def test_an_s3_store_writes_and_verifies(s3_env, tmp_path):
    client, prefix = s3_env
    _roundtrip(store.shared(), tmp_path)
    keys = versions(client, prefix)
    assert keys[f"{prefix}/a/b.bin"] == 1  # one PUT, no temporary objects
    assert not [k for k in keys if ".tmp-" in k]


def test_stage_entries_go_to_the_store_and_a_bad_one_is_recomputed(s3_env, tmp_path, monkeypatch):
    client, prefix = s3_env
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "local"))
    calls = []

    def compute():
        calls.append(1)
        return {"x": np.arange(4)}

    value, hit, k = cache.cached("cvae", {"a": 1}, compute, code="v")
    assert not hit and versions(client, f"{prefix}/stages/{k}") == {f"{prefix}/stages/{k}.npz": 1}
    assert not (tmp_path / "local").exists()  # nothing written locally
    value, hit, _ = cache.cached("cvae", {"a": 1}, compute, code="v")
    assert hit and len(calls) == 1 and value["x"].tolist() == [0, 1, 2, 3]
    st = store.stages(tmp_path / "local")
    st.put_bytes(f"{k}.npz", st.get_bytes(f"{k}.npz")[:-40])  # truncated
    with pytest.warns(UserWarning, match=f"s3://{BUCKET}/{prefix}/stages/{k}.npz is unusable"):
        value, hit, _ = cache.cached("cvae", {"a": 1}, compute, code="v")
    assert not hit and len(calls) == 2 and value["x"].tolist() == [0, 1, 2, 3]


# --------------------------------------------------------------------------- locks
def _hold_and_contend(st: store.Store) -> None:
    """A second holder of one lock gets it only after the first releases it."""
    first_in, release, second_in = threading.Event(), threading.Event(), threading.Event()

    def first():
        with st.lock("k"):
            first_in.set()
            release.wait(30)

    def second():
        first_in.wait(30)
        with st.lock("k"):
            second_in.set()

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    assert first_in.wait(30)
    assert not second_in.wait(2.0)  # blocked while the first holds it
    release.set()
    assert second_in.wait(30)
    for t in threads:
        t.join(30)


def test_a_folder_lock_excludes(tmp_path):
    _hold_and_contend(store.Store(str(tmp_path)))


def test_an_s3_lease_excludes_and_an_expired_one_is_taken_over(s3_env):
    client, prefix = s3_env
    st = store.shared()
    _hold_and_contend(st)
    assert not st.exists("locks/k.lease")  # released
    # a lease whose holder died (never renewed, expired): taken over
    st.put_bytes("locks/dead.lease", json.dumps({"owner": "gone", "expires": time.time() - 1}).encode())
    with st.lock("dead", poll=0.1):
        assert json.loads(st.get_bytes("locks/dead.lease"))["owner"] != "gone"
    assert not st.exists("locks/dead.lease")


COMPUTE_ONCE = """
import json, os, sys, time
import numpy as np
from spot import cache
k = sys.argv[1]
def compute():
    with open(os.environ["COUNTER"], "a") as f:
        f.write(k + "\\n")
    time.sleep(1.0)
    return {"k": np.array([int(k)])}
value, hit, key = cache.cached("reward", {"k": int(k)}, compute, code="v")
assert value["k"].tolist() == [int(k)]
print(json.dumps({"k": k, "hit": hit}))
"""


@pytest.mark.parametrize("where", ["folder", "s3"])
def test_concurrent_processes_compute_each_entry_once(where, tmp_path, request):
    """6 processes at once, 2 per key: each key computed by one, reused by the others."""
    counter = tmp_path / "computed.txt"
    if where == "s3":
        client, prefix = request.getfixturevalue("s3_env")  # sets $SPOT_STORE and the AWS variables
    env = {**os.environ, "COUNTER": str(counter), "SPOT_CACHE_DIR": str(tmp_path / "cache")}
    if where == "folder":
        env.pop(store.ENV_URI, None)
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", COMPUTE_ONCE, str(k)], env=env, cwd=REPO, stdout=subprocess.PIPE, text=True
        )
        for k in (0, 1, 2) * 2
    ]
    outs = [json.loads(p.communicate(timeout=300)[0]) for p in procs]
    assert all(p.returncode == 0 for p in procs)
    assert sorted(counter.read_text().split()) == ["0", "1", "2"]  # each key computed once
    assert sorted(o["k"] for o in outs if o["hit"]) == ["0", "1", "2"]  # and reused once
    if where == "s3":
        stage_puts = {k: n for k, n in versions(client, prefix).items() if k.endswith(".npz")}
        assert sorted(stage_puts.values()) == [1, 1, 1]


# --------------------------------------------------------------------------- datasets
def test_a_dataset_built_on_one_node_is_fetched_not_rebuilt_on_another(s3_env, tmp_path, monkeypatch):
    from spot.data import registry
    from spot.recipes import metaworld

    client, prefix = s3_env
    monkeypatch.setenv("SPOT_DATA_DIR", str(tmp_path / "node1"))
    built = registry.build("drawer-open", "tiny", 0, progress=False)
    assert versions(client, f"{prefix}/data/") == {
        f"{prefix}/data/{built.name}": 1,
        f"{prefix}/data/{built.name}.sha256": 1,
        f"{prefix}/data/{registry.card_path(built).name}": 1,
        f"{prefix}/data/{registry.card_path(built).name}.sha256": 1,
    }

    def no_build(*args, **kwargs):
        raise AssertionError("the dataset was rebuilt")

    monkeypatch.setattr(metaworld, "build", no_build)
    monkeypatch.setenv("SPOT_DATA_DIR", str(tmp_path / "node2"))
    fetched = registry.build("drawer-open", "tiny", 0, progress=False)
    assert fetched == tmp_path / "node2" / built.name
    assert fetched.read_bytes() == built.read_bytes()
    assert registry.read_card(fetched) == registry.read_card(built)
    # a dataset built before the store was named is uploaded when next asked for
    monkeypatch.setenv(store.ENV_URI, f"s3://{BUCKET}/{prefix}-later")
    monkeypatch.setenv("SPOT_DATA_DIR", str(tmp_path / "node1"))
    registry.build("drawer-open", "tiny", 0, progress=False)
    assert versions(client, f"{prefix}-later/data/{built.name}")[f"{prefix}-later/data/{built.name}"] == 1


# --------------------------------------------------------------------------- the sweep file's key
def test_the_sweep_files_store_key(tmp_path):
    from spot import sweep

    path = tmp_path / "s.yaml"
    path.write_text("base: {method: oracle}\nstore: {uri: s3://b/p/, endpoint_url: http://h:9000}\n")
    s = sweep.load(path)
    assert (s.store, dict(s.store_options)) == ("s3://b/p", {"endpoint_url": "http://h:9000"})
    path.write_text("base: {method: oracle}\nstore: shared/store\n")
    assert sweep.load(path).store == str(Path.cwd() / "shared" / "store")
    for text, match in [
        ("store: {uri: s3://b, region: x}\n", r"'store': 'region': unknown store option"),
        ("store: {endpoint_url: http://h}\n", r"'store.uri': missing"),
        ("store: gs://b/p\n", r"'store': 'gs://b/p': expected a folder path"),
    ]:
        path.write_text("base: {method: oracle}\n" + text)
        with pytest.raises(SpotError, match=match) as info:
            sweep.load(path)
        assert str(path) in str(info.value)
