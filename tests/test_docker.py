"""docker/: no Docker engine here, so check what can be checked without one (see docker/README.md)."""

import contextlib
import fnmatch
import http.client
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent
DOCKER = REPO / "docker"
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
PINS = dict(
    re.match(r"([A-Za-z0-9_.\[\]-]+)==(.+)", d).groups() for d in PYPROJECT["project"]["dependencies"] if "==" in d
)


def _readme_install() -> str:
    block = (REPO / "README.md").read_text().split("```bash", 1)[1].split("```", 1)[0]
    return re.search(r'pip install (-e "\.\[\w+\]")', block.strip().splitlines()[0]).group(1)


def test_images_install_like_the_readme_on_the_required_python():
    install = _readme_install()
    python = PYPROJECT["project"]["requires-python"]
    assert "3.11" in python
    for name in ("Dockerfile.cpu", "Dockerfile.cuda"):
        text = (DOCKER / name).read_text()
        assert text.startswith("#") and re.search(r"^FROM \S+", text, re.M)
        assert f"pip install --no-cache-dir {install}" in text, name
        assert "python:3.11" in text or "python3.11" in text, name
    cuda = (DOCKER / "Dockerfile.cuda").read_text()
    assert '-e ".[cuda]"' in cuda  # jax[cuda12] at jaxlib's pin: tests/test_bench_sweep.py


def test_compose_file_and_mlflow_version():
    compose = yaml.safe_load((DOCKER / "compose.mlflow.yaml").read_text())
    assert {"postgres", "mlflow", "minio"} <= set(compose["services"])
    command = compose["services"]["mlflow"]["command"]
    assert "postgresql://" in command and "--artifacts-destination s3://mlflow/" in command
    assert f'"mlflow=={PINS["mlflow"]}"' in (DOCKER / "mlflow" / "Dockerfile").read_text()
    images = {name: s["image"] for name, s in compose["services"].items() if "image" in s}
    assert set(images) == {"postgres", "minio", "create-bucket"}  # mlflow is built from mlflow/Dockerfile
    for image in images.values():  # pinned: an explicit version tag, never latest or a bare major
        tag = image.rpartition(":")[2]
        assert ":" in image and tag != "latest" and re.fullmatch(r"\d+\.\d+|RELEASE\.\d{4}-\d\d-\d\dT[\d-]+Z", tag), (
            image
        )


def test_ray_configs_parse_and_point_at_real_sweeps():
    cluster = yaml.safe_load((DOCKER / "ray-cluster.yaml").read_text())
    assert cluster["cluster_name"] and cluster["provider"]["type"] == "local"
    rc = yaml.safe_load((DOCKER / "kuberay" / "raycluster.yaml").read_text())
    job = yaml.safe_load((DOCKER / "kuberay" / "rayjob.yaml").read_text())
    for doc, kind in ((rc, "RayCluster"), (job, "RayJob")):
        assert doc["apiVersion"] == "ray.io/v1" and doc["kind"] == kind
    assert rc["spec"]["rayVersion"] == PINS["ray[tune]"] == job["spec"]["rayClusterSpec"]["rayVersion"]
    sweep_file = re.search(r"spot sweep (\S+)", job["spec"]["entrypoint"]).group(1)
    assert (REPO / sweep_file).is_file()


# --------------------------------------------------------------------------- .dockerignore
def _ignored(path: str, patterns: list[str]) -> bool:
    """Docker's rule: the last matching pattern wins; `!` re-includes; a pattern matches from the root."""
    ignored = False
    for pattern in patterns:
        negate = pattern.startswith("!")
        pattern = pattern.lstrip("!").strip("/")
        parts = path.split("/")
        prefixes = ["/".join(parts[:i]) for i in range(1, len(parts) + 1)]  # a folder excludes its files
        if any(
            fnmatch.fnmatchcase(p, pattern)
            or (pattern.startswith("**/") and fnmatch.fnmatchcase(p.split("/")[-1], pattern[3:]))
            for p in prefixes
        ):
            ignored = not negate
    return ignored


def test_dockerignore_keeps_the_source_and_drops_venv_runs_and_data():
    patterns = [
        line.strip()
        for line in (REPO / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    for path in (
        ".venv/bin/python",
        ".git/HEAD",
        "mlruns/mlflow.db",
        "spot_runs/mlflow.db",
        "runs/x",
        "ray_results/x",
        "data/hopper.hdf5",
        "spot_data/x",
        "cache/stages/x.pkl",
        "docker/.env",
        "analysis/out/table1.md",
        "spot/__pycache__/cli.cpython-311.pyc",
        "scratch/d4rl.hdf5",
    ):
        assert _ignored(path, patterns), path
    for path in (
        "pyproject.toml",
        "README.md",
        "spot/cli.py",
        "spot/paper_tables.csv",
        "sweeps/paper/table1.yaml",
        "configs/quickstart.yaml",
        "tests/data/pt-human-labels/Lift_mh/label_human",
        "docker/mlflow/Dockerfile",
    ):
        assert not _ignored(path, patterns), path


# --------------------------------------------------------------------------- MLflow as deployed
def _interpolate(text: str, env: dict[str, str]) -> str:
    """Compose's variable syntax: ${VAR}, ${VAR:-default}, ${VAR-default}, ${VAR:?error} and
    ${VAR?error} (a ValueError with the error when unset or, with ':', empty), $$ for a literal $."""

    def sub(m: re.Match) -> str:
        if m.group(0) == "$$":
            return "$"
        name, op, default = m.groups()
        value = env.get(name)
        if op == ":-":
            return value if value else default
        if op == "-":
            return default if value is None else value
        if op in (":?", "?") and (value is None or (op == ":?" and not value)):
            raise ValueError(f"{name}: {default}")
        return value or ""

    return re.sub(r"\$\$|\$\{(\w+)(?:(:?[-?])([^}]*))?\}", sub, text)


SECRETS = {"POSTGRES_PASSWORD": "pg-secret", "MINIO_ROOT_PASSWORD": "minio-secret"}
"""What docker/.env sets (docker/.env.example): the compose file has no default for them."""


def test_compose_passwords_have_no_defaults():
    """Issue 42: without a .env the stack came up with the passwords mlflow / minio12345."""
    text = (DOCKER / "compose.mlflow.yaml").read_text()
    assert "minio12345" not in text and "PASSWORD:-" not in text
    for name in SECRETS:  # compose stops naming the variable and .env
        with pytest.raises(ValueError, match=rf"{name}: set {name} in docker/.env"):
            _interpolate(text, {k: v for k, v in SECRETS.items() if k != name})
    filled = _interpolate(text, SECRETS)
    service = yaml.safe_load(filled)["services"]
    assert service["postgres"]["environment"]["POSTGRES_PASSWORD"] == "pg-secret"
    assert "mlflow:pg-secret@postgres" in service["mlflow"]["command"]
    assert service["mlflow"]["environment"]["AWS_SECRET_ACCESS_KEY"] == "minio-secret"
    example = dict(ln.split("=", 1) for ln in (DOCKER / ".env.example").read_text().splitlines() if "=" in ln)
    assert set(SECRETS) <= set(example)  # the example .env sets each one


def test_kuberay_worker_ranges_are_autoscaled():
    """minReplicas/maxReplicas act only with KubeRay's in-tree autoscaler on."""
    for doc in _k8s_docs():
        cluster = doc["spec"].get("rayClusterSpec", doc["spec"]) if doc["kind"] in ("RayCluster", "RayJob") else {}
        ranged = [g for g in cluster.get("workerGroupSpecs", []) if "minReplicas" in g or "maxReplicas" in g]
        if ranged:
            assert cluster.get("enableInTreeAutoscaling") is True, doc["metadata"]["name"]
            assert all(g["minReplicas"] <= g["replicas"] <= g["maxReplicas"] for g in ranged)


def _split_options(argv: list[str]) -> list[tuple[str, str | None]]:
    """``--flag value`` / ``--flag=value`` / ``--flag`` -> [(flag, value or None)], in order."""
    out, i = [], 0
    while i < len(argv):
        flag = argv[i]
        assert flag.startswith("--"), argv
        if "=" in flag:
            out.append(tuple(flag.split("=", 1)))
        elif i + 1 < len(argv) and not argv[i + 1].startswith("--"):
            out.append((flag, argv[i + 1]))
            i += 1
        else:
            out.append((flag, None))
        i += 1
    return out


def _request(
    port: int,
    host: str,
    method: str = "GET",
    path: str = "/api/2.0/mlflow/experiments/search?max_results=1",
    body: dict | None = None,
) -> tuple[int, str]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        data = json.dumps(body).encode() if body is not None else None
        conn.request(method, path, body=data, headers={"Host": host, "Content-Type": "application/json"})
        resp = conn.getresponse()
        return resp.status, resp.read().decode(errors="replace")
    finally:
        conn.close()


@contextlib.contextmanager
def _serve(argv: list[str], env: dict[str, str], tmp_path: Path, replace: dict[str, str]):
    """Start ``argv`` (an ``mlflow server ...`` command line) with only the ``replace`` options' values changed."""
    from spot.sweep.mlflow_server import free_port

    assert argv[:2] == ["mlflow", "server"], argv
    options = _split_options(argv[2:])
    port = free_port()
    replace = {**replace, "--host": "127.0.0.1", "--port": str(port)}
    assert {f for f, _ in options} >= set(replace), (options, replace)
    cmd = [sys.executable, "-m", "mlflow", "server"]
    for flag, value in options:
        cmd += [flag] if value is None else [flag, replace.get(flag, value)]
    log = (tmp_path / "server.log").open("wb")
    proc = subprocess.Popen(
        cmd, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, **env}, start_new_session=True
    )
    try:
        deadline = time.monotonic() + 180
        while True:
            assert proc.poll() is None, (tmp_path / "server.log").read_text()[-3000:]
            with contextlib.suppress(OSError):
                if _request(port, "localhost", path="/health")[0] == 200:
                    break
            assert time.monotonic() < deadline, (tmp_path / "server.log").read_text()[-3000:]
            time.sleep(0.5)
        yield port
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        log.close()


@pytest.mark.slow
def test_compose_mlflow_command_answers_its_service_name(tmp_path):
    """The compose file's mlflow command line, run on loopback with SQLite/file stores for Postgres/S3.

    Everything else (workers, --allowed-hosts, --cors-allowed-origins, --serve-artifacts, the
    service's environment) is taken from the compose file as it is.
    """
    import mlflow

    assert mlflow.__version__ == PINS["mlflow"]  # the version docker/mlflow/Dockerfile installs
    compose = yaml.safe_load((DOCKER / "compose.mlflow.yaml").read_text())
    service = compose["services"]["mlflow"]
    argv = shlex.split(_interpolate(service["command"], SECRETS))
    env = {k: _interpolate(str(v), SECRETS) for k, v in service["environment"].items()}
    options = dict(_split_options(argv[2:]))
    assert (
        options["--backend-store-uri"].startswith("postgresql://")
        and options["--artifacts-destination"] == "s3://mlflow/"
    )
    container_port = options["--port"]
    assert f"{container_port}:{container_port}" in service["ports"]
    replace = {
        "--backend-store-uri": f"sqlite:///{tmp_path / 'mlflow.db'}",
        "--artifacts-destination": str(tmp_path / "artifacts"),
    }
    with _serve(argv, env, tmp_path, replace) as port:
        # what `--tracking-uri http://mlflow:5000` sends from a container on the compose network
        status, text = _request(port, f"mlflow:{container_port}")
        assert status == 200, text
        status, text = _request(
            port, f"mlflow:{container_port}", "POST", "/api/2.0/mlflow/experiments/create", {"name": "from-a-container"}
        )
        assert status == 200 and "experiment_id" in text, text
        assert _request(port, f"localhost:{container_port}")[0] == 200  # the published port, on this machine
        assert _request(port, f"192.168.1.20:{container_port}")[0] == 200  # a LAN address
        status, text = _request(port, f"mlflow.attacker.example:{container_port}")
        assert status == 403 and "Invalid Host header" in text


def _k8s_docs() -> list[dict]:
    return [d for f in sorted((DOCKER / "kuberay").glob("*.yaml")) for d in yaml.safe_load_all(f.read_text()) if d]


def _pod_specs(doc: dict) -> list[dict]:
    """The pod specs a manifest creates (Deployments, and the head/worker groups of Ray resources)."""
    if doc["kind"] == "Deployment":
        return [doc["spec"]["template"]["spec"]]
    cluster = doc["spec"].get("rayClusterSpec", doc["spec"]) if doc["kind"] in ("RayCluster", "RayJob") else None
    if cluster is None:
        return []
    return [cluster["headGroupSpec"]["template"]["spec"], *(g["template"]["spec"] for g in cluster["workerGroupSpecs"])]


@pytest.mark.slow
def test_k8s_mlflow_command_answers_its_service_name(tmp_path):
    """mlflow.yaml's container command on loopback (its SQLite/artifact paths moved into tmp)."""
    docs = {(d["kind"], d["metadata"]["name"]): d for d in _k8s_docs()}
    deployment, service = docs[("Deployment", "mlflow")], docs[("Service", "mlflow")]
    (container,) = deployment["spec"]["template"]["spec"]["containers"]
    options = dict(_split_options(container["command"][2:]))
    (port_spec,) = service["spec"]["ports"]
    assert port_spec["targetPort"] == container["ports"][0]["name"]
    assert str(container["ports"][0]["containerPort"]) == options["--port"] == str(port_spec["port"])
    replace = {
        "--backend-store-uri": f"sqlite:///{tmp_path / 'mlflow.db'}",
        "--artifacts-destination": str(tmp_path / "artifacts"),
    }
    env = {e["name"]: e["value"] for e in container.get("env", [])}
    with _serve(container["command"], env, tmp_path, replace) as port:
        for host in (
            f"mlflow:{port_spec['port']}",
            f"mlflow.spot.svc.cluster.local:{port_spec['port']}",
            f"localhost:{port_spec['port']}",
        ):
            status, text = _request(port, host)
            assert status == 200, (host, text)
        status, text = _request(port, f"evil.example:{port_spec['port']}")
        assert status == 403 and "Invalid Host header" in text


def test_k8s_manifests_validate_and_reference_only_what_they_define():
    """Kubernetes schemas (kubernetes-validate, strict) for the core objects and the Ray pod templates;
    the RayCluster/RayJob CRDs themselves have no schema there, so their references are checked here."""
    import kubernetes_validate

    docs = _k8s_docs()
    kinds = {d["kind"] for d in docs}
    assert {"PersistentVolumeClaim", "Deployment", "Service", "RayCluster", "RayJob"} <= kinds
    for doc in docs:
        if doc["kind"] in ("RayCluster", "RayJob"):
            for spec in _pod_specs(doc):
                kubernetes_validate.validate(
                    {"apiVersion": "v1", "kind": "PodTemplate", "metadata": {"name": "t"}, "template": {"spec": spec}},
                    "1.37",
                    strict=True,
                )
        else:
            kubernetes_validate.validate(doc, "1.37", strict=True)
    pvcs = {d["metadata"]["name"]: d for d in docs if d["kind"] == "PersistentVolumeClaim"}
    assert pvcs["spot-shared"]["spec"]["accessModes"] == ["ReadWriteMany"]
    services = {d["metadata"]["name"]: d for d in docs if d["kind"] == "Service"}
    deployments = [d for d in docs if d["kind"] == "Deployment"]
    for svc in services.values():  # each Service selects the pods of a Deployment
        assert any(
            svc["spec"]["selector"].items() <= d["spec"]["template"]["metadata"]["labels"].items() for d in deployments
        ), svc["metadata"]["name"]
    for doc in docs:
        for spec in _pod_specs(doc):
            volumes = {v["name"]: v for v in spec.get("volumes", [])}
            for v in volumes.values():
                if "persistentVolumeClaim" in v:
                    assert v["persistentVolumeClaim"]["claimName"] in pvcs, v
            for c in spec["containers"]:
                mounts = {m["name"] for m in c.get("volumeMounts", [])}
                assert mounts == set(volumes), (doc["metadata"]["name"], c["name"])  # every volume is mounted
                # not a bare local tag: an image pushed to a registry (the placeholder says so)
                assert c["image"].startswith("<registry>/"), c["image"]
                if doc["kind"] in ("RayCluster", "RayJob"):
                    assert "spot-shared" in {volumes[m]["persistentVolumeClaim"]["claimName"] for m in mounts}
                    assert c["image"].split("/", 1)[1] in ("spot:cpu", "spot:cuda")
                    assert c["workingDir"] == "/opt/spot"  # the images' WORKDIR: relative sweep paths resolve
    (mlflow_deploy,) = deployments
    assert mlflow_deploy["spec"]["template"]["spec"]["containers"][0]["image"].endswith(f":{PINS['mlflow']}")
    # every http://NAME:PORT the manifests log to is a Service of this setup on that port
    text = "\n".join(f.read_text() for f in (DOCKER / "kuberay").glob("*.yaml"))
    for name, port in set(re.findall(r"--tracking-uri http://([a-z0-9-]+):(\d+)", text)):
        assert name in services and int(port) in [p["port"] for p in services[name]["spec"]["ports"]]
    for f in (DOCKER / "kuberay").glob("*.yaml"):
        if "<registry>" in f.read_text().split("apiVersion", 1)[1]:
            assert "push" in f.read_text().split("apiVersion", 1)[0], f.name  # the header says to push
