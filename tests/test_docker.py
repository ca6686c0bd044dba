"""docker/: no Docker engine here, so check what can be checked without one (see docker/README.md)."""

import re
import tomllib
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
DOCKER = REPO / "docker"
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
PINS = dict(re.match(r"([A-Za-z0-9_.\[\]-]+)==(.+)", d).groups() for d in PYPROJECT["project"]["dependencies"] if "==" in d)


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
    assert f'"jax[cuda12]=={PINS["jaxlib"]}"' in cuda


def test_compose_file_and_mlflow_version():
    compose = yaml.safe_load((DOCKER / "compose.mlflow.yaml").read_text())
    assert {"postgres", "mlflow", "minio"} <= set(compose["services"])
    command = compose["services"]["mlflow"]["command"]
    assert "postgresql://" in command and "--artifacts-destination s3://mlflow/" in command
    assert f'"mlflow=={PINS["mlflow"]}"' in (DOCKER / "mlflow" / "Dockerfile").read_text()


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
