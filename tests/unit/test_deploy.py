"""The deployment files: docker-compose.yml (v1 and v2 syntax, Flower's login, Prometheus and
Grafana wired to the API's metrics), the scrape configuration, the Grafana dashboard's queries
against the series the service exports, the image's Dockerfile and lock, and the build context."""

from __future__ import annotations

import json
import os
import re
import subprocess
import tomllib
from pathlib import Path

import pytest
import yaml
from docker.utils.build import exclude_paths
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from sqlalchemy.orm import sessionmaker

from services.api.metrics import Metrics

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[2]
COMPOSE = REPO / "docker-compose.yml"
PROMETHEUS = REPO / "deploy" / "prometheus" / "prometheus.yml"
GRAFANA = REPO / "deploy" / "grafana"
SECRET_PATH = "/run/secrets/csr_metrics_key"
MAX_CONTEXT_BYTES = 50 * 1024 * 1024
# what a compose run needs in the environment (docker-compose.yml's ${VAR:?...})
COMPOSE_ENV = {"CSR_ADMIN_KEY": "a" * 24, "CSR_FLOWER_BASIC_AUTH": "ops:pw", "CSR_GRAFANA_PASSWORD": "pw"}
# PromQL's words that are not metric names
PROMQL_WORDS = {
    "sum",
    "max",
    "min",
    "avg",
    "by",
    "without",
    "rate",
    "delta",
    "increase",
    "histogram_quantile",
}


def _compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def _panels() -> list[dict]:
    panels = []
    for path in sorted((GRAFANA / "dashboards").glob("*.json")):
        panels += json.loads(path.read_text())["panels"]
    return panels


def _metric_names(expr: str) -> set[str]:
    without_strings = re.sub(r'"(?:[^"\\]|\\.)*"', " ", expr)
    without_labels = re.sub(r"\{[^}]*\}|\[[^\]]*\]|\bby \([^)]*\)", " ", without_strings)
    words = set(re.findall(r"[a-zA-Z_:][a-zA-Z0-9_:]*", without_labels))
    return words - PROMQL_WORDS


def test_compose_parses_with_docker_compose_v1_and_has_no_top_level_name():
    compose = _compose()
    assert "name" not in compose and "version" not in compose
    env = {**os.environ, **COMPOSE_ENV}
    result = subprocess.run(
        ["docker-compose", "-f", str(COMPOSE), "config", "--quiet"], capture_output=True, text=True, env=env
    )
    assert result.returncode == 0, result.stderr


def test_compose_requires_the_secrets_it_uses():
    env = {k: v for k, v in {**os.environ, **COMPOSE_ENV}.items() if k != "CSR_FLOWER_BASIC_AUTH"}
    result = subprocess.run(
        ["docker-compose", "-f", str(COMPOSE), "config", "--quiet"], capture_output=True, text=True, env=env
    )
    assert result.returncode != 0 and "CSR_FLOWER_BASIC_AUTH" in result.stderr


def test_flower_needs_a_login_and_listens_on_this_host_only():
    services = _compose()["services"]
    flower = services["flower"]
    assert flower["environment"]["FLOWER_BASIC_AUTH"].startswith("${CSR_FLOWER_BASIC_AUTH:?")
    for name in ("flower", "prometheus", "grafana"):
        assert all(str(p).startswith("127.0.0.1:") for p in services[name]["ports"]), name


def test_prometheus_scrapes_the_api_with_the_key_the_api_accepts():
    compose = _compose()
    services = compose["services"]
    assert services["api"]["environment"]["CSR_METRICS_KEY_FILE"] == SECRET_PATH
    for name in ("api", "prometheus"):
        assert services[name]["secrets"] == ["csr_metrics_key"], name
    assert "csr_metrics_key" in compose["secrets"]
    mounts = dict(v.split(":")[:2] for v in services["prometheus"]["volumes"] if v.startswith("./"))
    assert (REPO / mounts["./deploy/prometheus/prometheus.yml"].removeprefix("/")).name == "prometheus.yml"
    (job,) = yaml.safe_load(PROMETHEUS.read_text())["scrape_configs"]
    assert job["metrics_path"] == "/metrics"
    assert job["authorization"] == {"type": "Bearer", "credentials_file": SECRET_PATH}
    assert job["dns_sd_configs"][0]["names"] == ["api"] and job["dns_sd_configs"][0]["port"] == 8000


def test_prometheus_config_passes_promtool(tmp_path):
    key = tmp_path / "metrics.key"
    key.write_text("k" * 24)
    config = tmp_path / "prometheus.yml"
    config.write_text(PROMETHEUS.read_text().replace(SECRET_PATH, str(key)))
    result = subprocess.run(["promtool", "check", "config", str(config)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_grafana_is_provisioned_with_the_datasource_and_dashboards_compose_mounts():
    grafana = _compose()["services"]["grafana"]
    mounted = {v.split(":")[0] for v in grafana["volumes"] if v.startswith("./")}
    assert mounted == {"./deploy/grafana/provisioning", "./deploy/grafana/dashboards"}
    (datasource,) = yaml.safe_load((GRAFANA / "provisioning/datasources/prometheus.yml").read_text())[
        "datasources"
    ]
    assert datasource["url"] == "http://prometheus:9090"
    (provider,) = yaml.safe_load((GRAFANA / "provisioning/dashboards/csr.yml").read_text())["providers"]
    assert provider["options"]["path"] == "/var/lib/grafana/dashboards"
    for panel in _panels():
        uids = {panel["datasource"]["uid"]} | {t["datasource"]["uid"] for t in panel["targets"]}
        assert uids == {datasource["uid"]}, panel["title"]


def test_every_dashboard_query_names_series_the_service_exports():
    exported = Metrics(sessionmaker()).series_names()
    panels = _panels()
    titles = " ".join(p["title"].lower() for p in panels)
    for wanted in ("upload", "reject", "queue", "duration", "fail", "dirty", "tile latency", "published"):
        assert wanted in titles, wanted
    for panel in panels:
        for target in panel["targets"]:
            names = _metric_names(target["expr"])
            assert names and names <= exported, (panel["title"], names - exported)


def test_dashboard_queries_are_valid_promql(tmp_path):
    rules = {
        "groups": [
            {
                "name": "dashboard",
                "rules": [
                    {"record": f"csr:dashboard_query_{i}", "expr": t["expr"]}
                    for i, t in enumerate(t for p in _panels() for t in p["targets"])
                ],
            }
        ]
    }
    path = tmp_path / "rules.yml"
    path.write_text(yaml.safe_dump(rules))
    result = subprocess.run(["promtool", "check", "rules", str(path)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_image_is_multi_stage_non_root_and_installs_the_lock_before_the_code():
    lines = [ln.strip() for ln in (REPO / "Dockerfile").read_text().splitlines()]
    froms = [i for i, ln in enumerate(lines) if ln.startswith("FROM ")]
    assert len(froms) == 2 and " AS build" in lines[froms[0]]
    users = [ln for ln in lines[froms[1] :] if ln.startswith("USER ")]
    assert users and users[-1] not in ("USER root", "USER 0")
    lock = next(i for i, ln in enumerate(lines) if ln.startswith("RUN") and "--require-hashes" in ln)
    first_code = next(i for i, ln in enumerate(lines) if ln.startswith("COPY services"))
    assert lock < first_code
    assert not any(re.search(r"pip install[^\n]* -e\b", ln) for ln in lines)


def test_the_lock_pins_every_dependency_with_hashes():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    wanted = [Requirement(r) for r in project["dependencies"] + project["optional-dependencies"]["ops"]]
    text = (REPO / "requirements.lock").read_text()
    pinned = {canonicalize_name(m[1]): m[2] for m in re.finditer(r"(?m)^([A-Za-z0-9._-]+)==(\S+) \\$", text)}
    for requirement in wanted:
        version = pinned.get(canonicalize_name(requirement.name))
        assert version is not None, f"{requirement.name} is not in requirements.lock"
        assert requirement.specifier.contains(version, prereleases=True), (requirement, version)
    entries = re.split(r"(?m)^(?=[A-Za-z0-9])", text.split("\n\n", 1)[-1])
    assert all("--hash=sha256:" in e for e in entries if "==" in e)


def test_the_build_context_is_small_and_holds_what_the_dockerfile_copies():
    patterns = [
        ln.strip()
        for ln in (REPO / ".dockerignore").read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    ]
    context = exclude_paths(str(REPO), patterns)  # Docker's own matching of .dockerignore
    files = [REPO / p for p in context if (REPO / p).is_file() and not (REPO / p).is_symlink()]
    size = sum(f.stat().st_size for f in files)
    assert size < MAX_CONTEXT_BYTES, f"build context {size / 1e6:.1f} MB"
    copied = re.findall(r"(?m)^COPY (?!--from)(.+) \S+$", (REPO / "Dockerfile").read_text())
    for source in (s for line in copied for s in line.split()):
        assert source in context or any(p.startswith(source + "/") for p in context), source
    assert not any(p.startswith((".venv/", "data/", ".git/")) or "node_modules" in p for p in context)


def test_an_installed_package_finds_alembic_scripts_through_csr_migrations_dir(monkeypatch, tmp_path):
    from services.db.engine import SOURCE_MIGRATIONS_DIR, migrations_dir

    monkeypatch.delenv("CSR_MIGRATIONS_DIR", raising=False)
    assert migrations_dir() == SOURCE_MIGRATIONS_DIR == REPO / "migrations"
    monkeypatch.setenv("CSR_MIGRATIONS_DIR", str(tmp_path))
    assert migrations_dir() == tmp_path
    dockerfile = (REPO / "Dockerfile").read_text()
    assert "CSR_MIGRATIONS_DIR=/app/migrations" in dockerfile and "COPY migrations ./migrations" in dockerfile
