"""deploy/: every file parses and contains what its use needs."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"


def load(name: str):
    return yaml.safe_load((DEPLOY / name).read_text())


def test_image_recipe_installs_icemlab_with_cpu_torch():
    text = (DEPLOY / "Dockerfile").read_text()
    assert [line for line in text.splitlines() if line.startswith("FROM")] == ["FROM python:3.11-slim"]
    assert re.search(r"pip install --index-url https://download.pytorch.org/whl/cpu torch==2\.13\.0", text)
    assert re.search(r"COPY (orchestrator|workers)", text) and "pip install ." in text
    assert "RAY_USAGE_STATS_ENABLED=0" in text


def test_cluster_launcher_config():
    config = load("cluster.yaml")
    assert config["cluster_name"] and config["max_workers"] >= 1
    types = config["available_node_types"]
    assert config["head_node_type"] in types and len(types) >= 2
    assert config["docker"]["image"].endswith(":0.1.0")
    assert any("ray start --head" in c for c in config["head_start_ray_commands"])
    assert any("ray start --address" in c for c in config["worker_start_ray_commands"])
    assert any("icemlab" in c for c in config["setup_commands"])


def test_kuberay_rayjob_runs_icemlab():
    job = load("rayjob.yaml")
    assert job["apiVersion"] == "ray.io/v1" and job["kind"] == "RayJob"
    spec = job["spec"]
    assert spec["entrypoint"].startswith("icemlab run ") and "--tracking-uri http" in spec["entrypoint"]
    assert spec["shutdownAfterJobFinishes"] is True
    cluster = spec["rayClusterSpec"]
    head_image = cluster["headGroupSpec"]["template"]["spec"]["containers"][0]["image"]
    worker_images = [g["template"]["spec"]["containers"][0]["image"] for g in cluster["workerGroupSpecs"]]
    assert worker_images and all(image == head_image for image in worker_images)
    sweep = spec["entrypoint"].split()[2].removeprefix("/opt/icemlab/")
    assert (DEPLOY.parent / sweep).exists()  # the job runs a sweep that ships with the image


def test_mlflow_stack_uses_postgres_s3_and_proxied_artifacts():
    compose = load("mlflow/compose.yaml")
    services = compose["services"]
    assert {"postgres", "minio", "mlflow"} <= set(services)
    start = (DEPLOY / "mlflow" / "start.sh").read_text()
    assert services["mlflow"]["command"] == ["/opt/mlflow/start.sh"]
    assert '--backend-store-uri "postgresql://' in start and "--app-name basic-auth" in start
    assert "--artifacts-destination s3://" in start and "--serve-artifacts" in start
    assert services["mlflow"]["environment"]["MLFLOW_S3_ENDPOINT_URL"].startswith("http://minio:")
    assert services["mlflow"]["depends_on"]["postgres"]["condition"] == "service_healthy"
    assert "psycopg2" in (DEPLOY / "mlflow" / "Dockerfile").read_text()
    secrets = (DEPLOY / "mlflow" / ".env.example").read_text()
    names = ("POSTGRES_PASSWORD", "MINIO_ROOT_USER", "MINIO_ROOT_PASSWORD", "MLFLOW_ADMIN_PASSWORD")
    assert all(name in secrets for name in names)


def test_secrets_stay_out_of_images_and_git_and_authentication_is_on():
    """Ray's token and MLflow's passwords come from the environment; nothing in git or an image holds one."""
    ignored = (DEPLOY.parent / ".gitignore").read_text()
    assert "deploy/mlflow/.env" in ignored.splitlines()
    for image in ("Dockerfile", "mlflow/Dockerfile"):
        text = (DEPLOY / image).read_text()
        assert "PASSWORD" not in text and "RAY_AUTH_TOKEN=" not in text and "COPY .env" not in text
    cluster = load("cluster.yaml")
    assert "--env RAY_AUTH_MODE=token" in cluster["docker"]["run_options"]
    assert "--env RAY_AUTH_TOKEN" in [o.split("#")[0].strip() for o in cluster["docker"]["run_options"]]
    assert all("--dashboard-host=127.0.0.1" in c for c in cluster["head_start_ray_commands"] if "--head" in c)
    assert load("rayjob.yaml")["spec"]["rayClusterSpec"]["authOptions"] == {"mode": "token"}
    compose = load("mlflow/compose.yaml")["services"]["mlflow"]["environment"]
    assert compose["MLFLOW_ADMIN_PASSWORD"].startswith("${MLFLOW_ADMIN_PASSWORD:?")


def test_deploy_readme_covers_every_file():
    readme = (DEPLOY / "README.md").read_text()
    for name in ("Dockerfile", "cluster.yaml", "rayjob.yaml", "mlflow/compose.yaml", "mlflow/.env.example"):
        assert f"`{name}`" in readme
