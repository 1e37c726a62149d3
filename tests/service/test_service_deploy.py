"""deploy/ agrees with the code (no Docker engine needed): compose variables are real settings, ports and
health checks match the app's routes, nginx pins sessions by the id the app generates and upgrades
WebSockets, and the image installs no torch."""

from __future__ import annotations

import re
import secrets
from pathlib import Path

import pytest

from service.app import create_app, route_paths
from service.settings import ENV_PREFIX, Settings

yaml = pytest.importorskip("yaml", reason="PyYAML is not installed (dev extra)")

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())


@pytest.fixture(scope="module")
def nginx() -> str:
    return (DEPLOY / "nginx.conf").read_text()


def _replicas(compose: dict) -> dict[str, dict]:
    return {name: svc for name, svc in compose["services"].items() if "build" in svc}


def _routes() -> set[str]:
    return route_paths(create_app(Settings()))


def test_two_replicas_redis_and_a_load_balancer(compose):
    services = compose["services"]
    replicas = _replicas(compose)
    assert len(replicas) == 2 and "redis" in services
    assert any("nginx" in svc.get("image", "") for svc in services.values())
    for svc in replicas.values():
        assert svc["environment"]["HAPTICLINK_BROKER"] == "redis"
        assert svc["environment"]["HAPTICLINK_REDIS_URL"].startswith("redis://redis:")
    ids = [svc["environment"]["HAPTICLINK_INSTANCE_ID"] for svc in replicas.values()]
    assert len(set(ids)) == 2


def test_every_variable_compose_sets_is_a_setting_with_a_valid_value(compose, monkeypatch):
    fields = set(Settings.model_fields)
    for name, svc in _replicas(compose).items():
        env = svc["environment"]
        for key in env:
            assert key.startswith(ENV_PREFIX), f"{name}: {key} is not a HAPTICLINK_ setting"
            assert key[len(ENV_PREFIX) :].lower() in fields, f"{name}: {key} is no field of Settings"
        for key, value in env.items():
            monkeypatch.setenv(key, str(value))
        settings = Settings()  # parses every value the way the container will
        assert settings.broker == "redis" and settings.host == "0.0.0.0"


def test_ports_and_healthchecks_match_the_app(compose, nginx):
    routes = _routes()
    for svc in _replicas(compose).values():
        port = int(svc["environment"]["HAPTICLINK_PORT"])
        check = " ".join(svc["healthcheck"]["test"])
        url = re.search(r"http://127\.0\.0\.1:(\d+)(/\w+)", check)
        assert url and int(url.group(1)) == port and url.group(2) in routes
        upstreams = re.findall(r"server\s+([\w-]+):(\d+)", nginx)
        assert upstreams and all(int(p) == port for _, p in upstreams)
    lb = next(svc for svc in compose["services"].values() if "nginx" in svc.get("image", ""))
    assert "/health" in " ".join(lb["healthcheck"]["test"])
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    assert "EXPOSE 8000" in dockerfile and "http://127.0.0.1:8000/health" in dockerfile
    for path in ("/sessions/{session_id}/ingest", "/sessions/{session_id}/events", "/health", "/console"):
        assert path in routes


def test_nginx_pins_each_session_to_the_replica_that_made_its_id(compose, nginx):
    path_rule = re.search(r"map \$uri \$path_instance \{\s*~(\S+)\s+\$inst;", nginx)
    assert path_rule, "nginx.conf has no session-id map"
    pattern = re.compile(path_rule.group(1).replace("(?<", "(?P<"))
    mapping = dict(re.findall(r"^\s+(replica-\w+)\s+(replica_\w+);", nginx, re.M))
    upstream_hosts = dict(re.findall(r"upstream (replica_\w+)\s*\{\s*server ([\w-]+):", nginx))
    for name, svc in _replicas(compose).items():
        instance = svc["environment"]["HAPTICLINK_INSTANCE_ID"]
        session_id = f"{instance}.{secrets.token_urlsafe(9)}"  # the form ServiceState.create_session uses
        for tail in ("/blocks", "/ingest", "/events", ""):
            match = pattern.match(f"/sessions/{session_id}{tail}")
            assert match and match.group("inst") == instance
        assert upstream_hosts[mapping[instance]] == name  # that replica's container


def test_nginx_upgrades_the_websocket_routes(nginx):
    ws_block = re.search(r"location ~ \^/sessions/\[\^/\]\+/\(ingest\|events\)\$ \{(.*?)\}", nginx, re.S)
    assert ws_block, "no location for the WebSocket routes"
    body = ws_block.group(1)
    assert "proxy_http_version 1.1;" in body
    assert "proxy_set_header Upgrade $http_upgrade;" in body
    assert "proxy_set_header Connection $connection_upgrade;" in body
    assert re.search(r"map \$http_upgrade \$connection_upgrade", nginx)
    assert re.search(r"client_max_body_size 8m;", nginx)


def test_the_image_installs_no_torch(compose):
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    instructions = "\n".join(line for line in dockerfile.splitlines() if not line.lstrip().startswith("#"))
    assert "FROM python:3.11-slim" in instructions
    assert "torch" not in instructions.lower()
    assert not re.search(r"\[[^\]]*train", instructions), "the image must not install the train extra"
    assert re.search(r'pip install [^\n]*"\.\[serve\]"', instructions)
    assert 'CMD ["hapticlink", "serve"]' in instructions


def test_nginx_keeps_session_tokens_out_of_its_access_log(nginx):
    """WebSocket URLs and the console link carry ?token=: the access log must not write query strings."""
    fmt = re.search(r"log_format\s+(\w+)\s+(.*?);", nginx, re.S)
    assert fmt, "nginx.conf defines no log_format (the default one logs $request, query string included)"
    assert re.search(rf"access_log\s+\S+\s+{fmt.group(1)};", nginx)
    assert not re.search(r"\$(request|request_uri|args|query_string|arg_\w+)\b", fmt.group(2))
