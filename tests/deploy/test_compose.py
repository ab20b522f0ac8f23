"""deploy/compose: two replicas on one PostgreSQL, started in a health-checked order.

No container engine runs here; the file is checked for what the README promises of it.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from service.infra.settings import PACKAGE_ROOT, Settings

COMPOSE = PACKAGE_ROOT / "deploy" / "compose"


def compose() -> dict:
    return yaml.safe_load((COMPOSE / "compose.yaml").read_text(encoding="utf-8"))


def test_two_replicas_on_one_postgresql_in_a_health_checked_order() -> None:
    services = compose()["services"]
    db, service, proxy = services["db"], services["keypoints"], services["proxy"]
    assert "pg_isready" in " ".join(db["healthcheck"]["test"])
    assert service["deploy"]["replicas"] == 2
    assert int(service["stop_grace_period"].removesuffix("s")) > Settings().server.shutdown_grace_seconds
    assert service["depends_on"]["db"]["condition"] == "service_healthy"
    assert proxy["depends_on"]["keypoints"]["condition"] == "service_healthy"  # the image's HEALTHCHECK
    assert service["environment"]["CKS_STORE_URL"].startswith("postgresql://")
    assert "@db:5432/" in service["environment"]["CKS_STORE_URL"]


def test_the_build_context_holds_the_dockerfile_and_secrets_are_files() -> None:
    config = compose()
    service = config["services"]["keypoints"]
    assert (COMPOSE / service["build"] / "Dockerfile").resolve() == PACKAGE_ROOT / "Dockerfile"
    assert service["environment"]["CKS_ADMIN_TOKENS_FILE"] == "/run/secrets/admin_tokens"
    assert config["secrets"]["admin_tokens"]["file"] == "./admin_tokens"
    assert any(volume.endswith(":/data") for volume in service["volumes"])  # one shared data volume


def test_the_proxy_runs_the_shipped_edge_configuration() -> None:
    config = compose()
    proxy, service = config["services"]["proxy"], config["services"]["keypoints"]
    mounted = proxy["volumes"][0].split(":")[0]
    assert (COMPOSE / mounted).resolve() == PACKAGE_ROOT / "deploy" / "haproxy" / "haproxy.cfg"
    shipped = (PACKAGE_ROOT / "deploy" / "haproxy" / "haproxy.cfg").read_text(encoding="utf-8")
    for variable in proxy["environment"]:
        assert f"${{{variable}-" in shipped, variable  # each one the configuration reads
    assert proxy["environment"]["CKS_PROXY_REPLICAS"] == str(service["deploy"]["replicas"])
    address = proxy["networks"]["edge"]["ipv4_address"]
    assert service["environment"]["CKS_TRUSTED_PROXIES"] == address  # X-Forwarded-For from it alone
    assert "client_max_body_size" not in shipped and "http-request deny" not in shipped  # uploads pass


def test_the_readme_points_at_it() -> None:
    readme = Path(PACKAGE_ROOT / "README.md").read_text(encoding="utf-8")
    assert "deploy/compose/compose.yaml" in readme
