"""A sweep on a real two-node Ray cluster, with datasets and stage entries in a real S3 store.

On this machine, all on loopback: a moto S3 server (server mode, a subprocess) with a versioned
bucket (so every PUT of a key is counted), a Ray head (``ray start --head``) and a second node
(``ray start --address``), each with its own Ray temp dir, HOME, ``SPOT_DATA_DIR`` and
``SPOT_CACHE_DIR`` and one CPU (and a custom resource naming it). ``spot sweep --smoke --address``
runs four SPOT trials (2 seeds x 2 lambdas), one CPU each, at most two at a time: with one CPU per
node the two running trials are on different nodes. The driver (its own HOME and dirs too) starts
its MLflow server (``--tracking-host 127.0.0.1``); the trials log runs and artifacts through it.

Checked: every run FINISHED with its artifacts served by the MLflow server; the dataset PUT once
(built once, by the driver) and fetched by both nodes; each reward model, relabelling and CVAE
PUT once (2 of each: one per seed; the lambdas share them) with ``stage.<name>.source`` tags of 2
computed and 2 reused; nothing in the nodes' local stage caches; the paper table printed.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from tests.test_store import moto_server, versions

REPO = Path(__file__).resolve().parents[1]
RAY = str(Path(sys.executable).parent / "ray")
DATASET = "drawer-open__tiny__seed0.hdf5"

SWEEP = """
name: multinode
base: {method: spot, budget: small, data.name: drawer-open, labels.source: script}
grid:
  shaping.weight: [0.5, 1.0]
seeds: [0, 1]
resources: {cpu: 1, gpu: 0}
max_concurrent: 2
table: 3
store: s3://spot-test/sweep
smoke:
  base: {budget: tiny, data.size: tiny, iql.steps: 100, eval.every: 100, eval.episodes: 2}
  fast_compile: true
"""


def _env(root: Path, name: str, common: dict[str, str]) -> dict[str, str]:
    """A node's (or the driver's) own HOME, data dir and stage cache."""
    home = root / name
    for sub in ("home", "data", "cache"):
        (home / sub).mkdir(parents=True, exist_ok=True)
    return {
        **common,
        "HOME": str(home / "home"),
        "SPOT_DATA_DIR": str(home / "data"),
        "SPOT_CACHE_DIR": str(home / "cache"),
    }


def _start_node(args: list[str], env: dict[str, str], log: Path, stack: contextlib.ExitStack) -> None:
    """``ray start ... --block`` in its own session; the finalizer ends the session's processes."""
    out = open(log, "wb")
    proc = subprocess.Popen(
        [RAY, "start", *args, "--block"], env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True
    )

    def stop() -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:  # a worker node's `ray start --block` ends within ~1 s; the head's never did in 30 s
            proc.wait(5)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        out.close()

    stack.callback(stop)


def _alive_nodes(address: str, env: dict[str, str]) -> int:
    code = (
        f"import ray, logging; ray.init(address={address!r}, logging_level=logging.ERROR); "
        "print(sum(n['Alive'] for n in ray.nodes()))"
    )
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    try:
        return int(out.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return 0


def _ray_processes_of(root: Path) -> list[str]:
    """Command lines of live processes that name a folder under ``root`` (Ray's temp dirs)."""
    found = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            with contextlib.suppress(OSError):
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                if str(root) in cmd:
                    found.append(f"{pid}: {cmd[:200]}")
    return found


@pytest.fixture(scope="module")
def launched(tmp_path_factory):
    from spot.sweep.mlflow_server import free_port

    root = tmp_path_factory.mktemp("multinode")
    # Ray's temp dirs: short paths (its unix sockets live there; a socket path is at most 107 bytes)
    ray_tmp = Path(tempfile.mkdtemp(prefix="spot-mn-", dir="/tmp"))
    with contextlib.ExitStack() as stack:
        stack.callback(shutil.rmtree, ray_tmp, ignore_errors=True)
        url, aws, s3 = stack.enter_context(moto_server(root / "moto.log"))
        common = {k: v for k, v in os.environ.items() if not k.startswith(("SPOT_", "RAY_", "MLFLOW_"))}
        common.update(aws)
        common.update(
            {
                "RAY_AUTH_MODE": "token",  # as a real cluster should be: nodes and driver share a token
                "RAY_AUTH_TOKEN": secrets.token_hex(32),
                "RAY_USAGE_STATS_ENABLED": "0",
                "PYTHONUNBUFFERED": "1",
            }
        )
        port = free_port()
        address = f"127.0.0.1:{port}"
        node = ["--node-ip-address=127.0.0.1", "--num-cpus=1"]
        env_a, env_b = _env(root, "node_a", common), _env(root, "node_b", common)
        _start_node(
            [
                "--head",
                f"--port={port}",
                "--include-dashboard=false",
                *node,
                '--resources={"node_a": 1}',
                f"--temp-dir={ray_tmp / 'a'}",
            ],
            env_a,
            root / "node_a.log",
            stack,
        )
        deadline = time.monotonic() + 120
        while not _try_connect(port):  # the head's GCS answers
            assert time.monotonic() < deadline, (root / "node_a.log").read_text()[-3000:]
            time.sleep(1)
        _start_node(
            [f"--address={address}", *node, '--resources={"node_b": 1}', f"--temp-dir={ray_tmp / 'b'}"],
            env_b,
            root / "node_b.log",
            stack,
        )
        driver = _env(root, "driver", common)
        while _alive_nodes(address, driver) < 2:
            assert time.monotonic() < deadline + 120, (root / "node_b.log").read_text()[-3000:]
            time.sleep(2)
        sweep_file = root / "multinode.yaml"
        sweep_file.write_text(SWEEP)
        cmd = [
            sys.executable,
            "-m",
            "spot.cli",
            "sweep",
            str(sweep_file),
            "--smoke",
            "--address",
            address,
            "--tracking-host",
            "127.0.0.1",
        ]
        out = subprocess.run(cmd, cwd=root / "driver", env=driver, capture_output=True, text=True, timeout=900)
        yield {"root": root, "out": out, "s3": s3, "driver": driver}
    leftover = _ray_processes_of(ray_tmp)
    assert not leftover, "processes left behind:\n" + "\n".join(leftover)


def _try_connect(port: int) -> bool:
    import socket

    with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=1):
        return True
    return False


@pytest.fixture(scope="module")
def runs(launched):
    """A client on the sweep's store, served again (runs' artifacts are ``mlflow-artifacts:`` URIs,
    which only a server resolves), and the sweep's child runs."""
    from mlflow.tracking import MlflowClient

    from spot.sweep.mlflow_server import MlflowServer, sqlite_uri

    out = launched["out"]
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-4000:]
    runs_dir = launched["root"] / "driver" / "spot_runs"
    with MlflowServer(
        sqlite_uri(runs_dir / "mlflow.db"), runs_dir / "artifacts", log_path=runs_dir / "again.log"
    ) as srv:
        client = MlflowClient(srv.uri)
        exp = client.get_experiment_by_name("multinode-smoke")
        children = [
            r for r in client.search_runs([exp.experiment_id], max_results=100) if "spot.trial_key" in r.data.tags
        ]
        yield client, children


@pytest.mark.slow
def test_every_trial_finished_with_its_artifacts_on_the_server(launched, runs):
    client, children = runs
    assert "4/4 runs finished" in launched["out"].stdout
    assert len(children) == 4 and all(r.info.status == "FINISHED" for r in children)
    for run in children:
        assert run.info.artifact_uri.startswith("mlflow-artifacts:")  # uploaded through the server
        names = {a.path for a in client.list_artifacts(run.info.run_id)}
        assert "models" in names, names
        models = {a.path for a in client.list_artifacts(run.info.run_id, "models")}
        assert any("reward_model" in m for m in models) and any("cvae" in m for m in models), models
    artifacts = launched["root"] / "driver" / "spot_runs" / "artifacts"
    assert len(list(artifacts.rglob("*reward_model*"))) >= 4  # on the server's disk


@pytest.mark.slow
def test_trials_ran_on_both_nodes_and_the_dataset_was_built_once(launched, runs):
    root, s3 = launched["root"], launched["s3"]
    puts = versions(s3, "sweep/data/")
    assert puts[f"sweep/data/{DATASET}"] == 1  # built once (by the driver), uploaded once
    built = (root / "driver" / "data" / DATASET).read_bytes()
    for node in ("node_a", "node_b"):  # each node ran a trial: it fetched the dataset, the same bytes
        assert (root / node / "data" / DATASET).read_bytes() == built
    assert "uploaded to s3://spot-test/sweep/data/" in launched["out"].stderr + launched["out"].stdout


@pytest.mark.slow
def test_each_shared_stage_was_trained_once(launched, runs):
    _, children = runs
    puts = versions(launched["s3"], "sweep/stages/")
    for stage in ("reward", "relabel", "cvae"):
        entries = {k: n for k, n in puts.items() if k.startswith(f"sweep/stages/{stage}-")}
        assert len(entries) == 2 and set(entries.values()) == {1}, puts  # one per seed, written once
        sources = sorted(r.data.tags.get(f"spot.stage.{stage}.source") for r in children)
        assert sources == ["computed", "computed", "reused", "reused"], stage
        keys = {r.data.tags[f"spot.stage.{stage}.key"] for r in children}
        assert {f"sweep/stages/{k}.npz" for k in keys} == set(entries)
    for node in ("node_a", "node_b", "driver"):  # nothing in the local stage caches
        assert not list((launched["root"] / node / "cache").glob("*.npz"))


@pytest.mark.slow
def test_the_paper_table_prints(launched, runs):
    out = launched["out"].stdout
    assert "Table 3" in out and "full table with CIs and notes:" in out, out[-3000:]


# --------------------------------------------------------------------------- --tracking-host
@pytest.mark.parametrize(
    "host, address, uri, match",
    [
        ("0.0.0.0", None, None, "only for a cluster sweep"),
        ("0.0.0.0", "h:6379", "http://m:5000", "spot starts no server for --tracking-uri http://m:5000"),
        ("http://x", "h:6379", None, "expected an IPv4 address or host name"),
    ],
)
def test_tracking_host_is_only_for_the_server_of_a_cluster_sweep(host, address, uri, match, monkeypatch):
    from spot import SpotError
    from spot.sweep import uris

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    with pytest.raises(SpotError, match=match):
        uris.check_tracking_host(host, address, uri)
    uris.check_tracking_host("0.0.0.0", "h:6379", "sqlite:///x.db")  # a SQLite store spot serves: fine


def test_a_server_on_all_interfaces_advertises_the_address_on_the_route_to_the_head():
    from spot.sweep import uris

    assert uris.advertised_host("0.0.0.0", "127.0.0.1:6379") == "127.0.0.1"
    assert uris.advertised_host("10.1.2.3", "127.0.0.1:6379") == "10.1.2.3"  # a given address as it is


# --------------------------------------------------------------------------- a lambda sweep, one machine
LAMBDA_SWEEP = """
name: lambdas
base: {method: spot, budget: small, data.name: drawer-open, labels.source: script}
grid:
  shaping.weight: [0.5, 1.0]
seeds: [0, 1]
resources: {cpu: 1, gpu: 0}
max_concurrent: 2
smoke:
  base: {budget: tiny, data.size: tiny, iql.steps: 100, eval.every: 100, eval.episodes: 1}
  fast_compile: true
"""


@pytest.mark.slow
def test_a_lambda_sweep_trains_one_reward_model_and_one_cvae_per_seed(tmp_path):
    """2 seeds x 2 lambdas = 4 SPOT runs, two at a time, on a local Ray and the default store (the
    local stage cache): the lambdas of a seed share its reward model, relabelling and CVAE, so 2 of
    each are trained (tagged ``computed``), not 4; the other 2 runs reuse them. (The 3 x 6 grid,
    18 runs and 3 of each, was measured once; this smaller grid keeps the suite's time.)"""
    from mlflow.tracking import MlflowClient

    (tmp_path / "lambdas.yaml").write_text(LAMBDA_SWEEP)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SPOT_STORE", "RAY_ADDRESS", "MLFLOW_"))}
    env.update({"SPOT_CACHE_DIR": str(tmp_path / "cache"), "PYTHONUNBUFFERED": "1"})
    env.setdefault("SPOT_DATA_DIR", str(tmp_path / "data"))
    out = subprocess.run(
        [sys.executable, "-m", "spot.cli", "sweep", "lambdas.yaml", "--smoke"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=1500,
    )
    assert out.returncode == 0 and "4/4 runs finished" in out.stdout, out.stdout[-3000:] + out.stderr[-3000:]
    for stage in ("reward", "relabel", "cvae"):
        assert len(list((tmp_path / "cache").glob(f"{stage}-*.npz"))) == 2, stage
    client = MlflowClient(f"sqlite:///{tmp_path / 'spot_runs' / 'mlflow.db'}")
    exp = client.get_experiment_by_name("lambdas-smoke")
    children = [r for r in client.search_runs([exp.experiment_id], max_results=100) if "spot.trial_key" in r.data.tags]
    assert len(children) == 4
    for stage in ("reward", "relabel", "cvae"):
        computed = [r for r in children if r.data.tags[f"spot.stage.{stage}.source"] == "computed"]
        assert len(computed) == 2 and sorted(int(r.data.tags["seed"]) for r in computed) == [0, 1], stage
        assert sum(r.data.tags[f"spot.stage.{stage}.source"] == "reused" for r in children) == 2
