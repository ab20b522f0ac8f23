"""deploy/k8s: every manifest is valid Kubernetes, and agrees with the service it deploys.

The schemas are kept in the repository (tests/deploy/kubernetes_schemas.py: kubernetes-validate's
strict schemas of the kinds used, for a pinned Kubernetes version; an unknown or misspelt field
fails). Beyond the schemas: the probes
ask for routes the app has, the container listens on ``CKS_PORT``, selectors find the pods,
the Secrets the Deployment reads are those ``secrets.example.yaml`` shows, the pod runs as the
image's user on a read-only root with its writable paths mounted, and the resources follow
the layout and the figures of docs/performance.md.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from service import __version__
from service.calibration.archive import MAX_UNCOMPRESSED_BYTES
from service.infra.operators import load_operators
from service.infra.settings import PACKAGE_ROOT, Settings
from service.serving.app import create_app
from tests.deploy import kubernetes_schemas

K8S = PACKAGE_ROOT / "deploy" / "k8s"
KUSTOMIZATION = K8S / "kustomization.yaml"
SECRETS_EXAMPLE = K8S / "secrets.example.yaml"
MANIFESTS = sorted(path for path in K8S.glob("*.yaml") if path != KUSTOMIZATION)
PERFORMANCE = PACKAGE_ROOT / "docs" / "performance.md"
RGB_BYTES_PER_PIXEL = 3
MIB = 2.0**20
QUANTITY_UNITS = {"": 1.0, "m": 1e-3, "k": 1e3, "M": 1e6, "G": 1e9, "Ki": 2.0**10, "Mi": MIB, "Gi": 2.0**30}
PROBES = ("startupProbe", "livenessProbe", "readinessProbe")

Manifest = dict[str, Any]


def documents(path: Path) -> list[Manifest]:
    return [doc for doc in yaml.safe_load_all(path.read_text(encoding="utf-8")) if doc is not None]


def applied(kind: str) -> Manifest:
    """The one manifest of this kind that kustomization.yaml applies."""
    docs = [doc for name in kustomization()["resources"] for doc in documents(K8S / name)]
    found = [doc for doc in docs if doc["kind"] == kind]
    assert len(found) == 1, f"expected one {kind} among the applied manifests, found {len(found)}"
    return found[0]


def kustomization() -> Manifest:
    return yaml.safe_load(KUSTOMIZATION.read_text(encoding="utf-8"))


def pod_spec() -> Manifest:
    return applied("Deployment")["spec"]["template"]["spec"]


def container() -> Manifest:
    containers = pod_spec()["containers"]
    assert len(containers) == 1, "the service runs as the pod's one container"
    return containers[0]


def pod_labels() -> dict[str, str]:
    return applied("Deployment")["spec"]["template"]["metadata"]["labels"]


def quantity(value: str | int) -> float:
    """A Kubernetes quantity ("2", "500m", "320Mi", "1Gi") as a number (cores or bytes)."""
    match = re.fullmatch(r"([0-9.]+)([A-Za-z]*)", str(value))
    assert match and match.group(2) in QUANTITY_UNITS, f"unexpected quantity {value!r}"
    return float(match.group(1)) * QUANTITY_UNITS[match.group(2)]


@pytest.fixture
def settings(monkeypatch: pytest.MonkeyPatch) -> Settings:
    """The service's settings in the pod: the Deployment's literal CKS_* values, else the defaults."""
    for name in [name for name in os.environ if name.startswith("CKS_")]:
        monkeypatch.delenv(name)
    literal = {var["name"]: var["value"] for var in container()["env"] if "value" in var}
    return Settings(**{name.removeprefix("CKS_").lower(): value for name, value in literal.items()})


def emptydir_mounts() -> dict[str, Manifest]:
    """Writable mount path -> its emptyDir volume."""
    volumes = {volume["name"]: volume for volume in pod_spec()["volumes"]}
    return {
        mount["mountPath"]: volumes[mount["name"]]["emptyDir"]
        for mount in container()["volumeMounts"]
        if not mount.get("readOnly") and "emptyDir" in volumes[mount["name"]]
    }


@pytest.mark.parametrize("path", MANIFESTS, ids=lambda path: path.name)
def test_manifest_is_valid_kubernetes(path: Path) -> None:
    for doc in documents(path):
        try:
            kubernetes_schemas.validate(doc)
        except jsonschema.ValidationError as error:
            where = "/".join(map(str, error.path))
            pytest.fail(f"{path.name}: {doc['kind']} {doc['metadata']['name']}: {error.message} at {where}")


def test_kustomization_applies_every_manifest_but_the_secrets_example() -> None:
    resources = kustomization()["resources"]
    assert len(resources) == len(set(resources))
    assert set(resources) == {path.name for path in MANIFESTS} - {SECRETS_EXAMPLE.name}


def test_every_setting_named_exists() -> None:
    for var in container()["env"]:
        name = var["name"]
        assert name.startswith("CKS_") and name[4:].lower() in Settings.fields(), f"no setting {name}"


def test_the_container_listens_where_the_service_and_probes_look(settings: Settings) -> None:
    ports = {port["name"]: port["containerPort"] for port in container()["ports"]}
    assert settings.server.host == "0.0.0.0" and ports == {"http": settings.server.port}
    service_ports = applied("Service")["spec"]["ports"]
    assert [port["targetPort"] for port in service_ports] == ["http"]

    get_routes = {path for path, item in create_app().openapi()["paths"].items() if "get" in item}
    probes = {kind: container()[kind]["httpGet"] for kind in PROBES}
    assert probes["livenessProbe"]["path"] == "/healthz" and probes["readinessProbe"]["path"] == "/readyz"
    for kind, probe in probes.items():
        assert probe["path"] in get_routes, f"{kind} asks for {probe['path']}, which the app does not serve"
        assert probe["port"] == "http", f"{kind} probes port {probe['port']}"


def test_selectors_find_the_pods_and_the_autoscaler_leaves_room_to_drain() -> None:
    labels = pod_labels().items()
    deployment, budget = applied("Deployment"), applied("PodDisruptionBudget")
    assert deployment["spec"]["selector"]["matchLabels"].items() <= labels
    assert budget["spec"]["selector"]["matchLabels"].items() <= labels
    assert applied("Service")["spec"]["selector"].items() <= labels
    autoscaler = applied("HorizontalPodAutoscaler")["spec"]
    target = {"apiVersion": "apps/v1", "kind": "Deployment", "name": deployment["metadata"]["name"]}
    assert autoscaler["scaleTargetRef"] == target
    assert "replicas" not in deployment["spec"], "the autoscaler owns the replica count"
    assert autoscaler["minReplicas"] > budget["spec"]["minAvailable"], "a drain could never evict a pod"


def test_runs_as_the_image_user_on_a_read_only_root(settings: Settings) -> None:
    uid = re.search(r"--uid (\d+)", (PACKAGE_ROOT / "Dockerfile").read_text(encoding="utf-8"))
    assert uid, "the Dockerfile no longer creates its user with --uid"
    pod_security, security = pod_spec()["securityContext"], container()["securityContext"]
    assert pod_security["runAsNonRoot"] is True and pod_security["runAsUser"] == int(uid.group(1))
    assert security["readOnlyRootFilesystem"] is True and security["allowPrivilegeEscalation"] is False
    assert security["capabilities"]["drop"] == ["ALL"]
    writable = emptydir_mounts()
    assert str(settings.storage.data_dir) in writable, "CKS_DATA_DIR is not writable"
    assert tempfile.gettempdir() in writable, "multipart uploads spool to the temporary directory"


def test_credentials_come_from_the_secrets_the_example_shows(settings: Settings, tmp_path: Path) -> None:
    secrets = {doc["metadata"]["name"]: doc["stringData"] for doc in documents(SECRETS_EXAMPLE)}
    env = {var["name"]: var for var in container()["env"]}
    assert "CKS_ADMIN_TOKEN" not in env, "admin tokens come from the mounted Secret, not a literal"
    store = env["CKS_STORE_URL"]["valueFrom"]["secretKeyRef"]
    assert secrets[store["name"]][store["key"]].startswith("postgresql://"), "replicas share one store"

    volumes = {volume["name"]: volume for volume in pod_spec()["volumes"]}
    token_files = {
        Path(mount["mountPath"]) / key: secrets[volumes[mount["name"]]["secret"]["secretName"]][key]
        for mount in container()["volumeMounts"]
        if "secret" in volumes[mount["name"]]
        for key in secrets[volumes[mount["name"]]["secret"]["secretName"]]
    }
    assert settings.admin.tokens_file in token_files, "CKS_ADMIN_TOKENS_FILE is not a mounted Secret key"
    example = tmp_path / "tokens"
    example.write_text(token_files[settings.admin.tokens_file], encoding="utf-8")
    assert sorted(load_operators(None, example).values()) == ["alice", "bob"]


def test_resources_follow_docs_performance(settings: Settings) -> None:
    report = PERFORMANCE.read_text(encoding="utf-8")
    cpus = re.search(r"Machine: (\d+) CPUs", report)
    headline = re.search(r"^- Headline settings: (.*)$", report, re.MULTILINE)
    memory_section = re.split(r"\n#{2,3} Memory\n", report, maxsplit=1)[-1]
    memory_section = re.split(r"\n#{2,3} ", memory_section, maxsplit=1)[0]
    rss_mib = [float(value) for value in re.findall(r"^\| \d+ \| ([\d.]+) \|$", memory_section, re.MULTILINE)]
    assert cpus and headline and rss_mib, f"{PERFORMANCE.name} no longer has the figures this test reads"

    for name, value in re.findall(r"`CKS_(\w+)=([^`]+)`", headline.group(1)):
        assert str(settings.value(name.lower())) == value, f"pod CKS_{name} != measured {value}"
    resources = container()["resources"]
    requests, limits = resources["requests"], resources["limits"]
    assert quantity(requests["cpu"]) == quantity(limits["cpu"]) == int(cpus.group(1))

    assert quantity(requests["memory"]) / MIB >= max(rss_mib)
    decoded_at_once = settings.predict.max_concurrent_inferences + settings.calibration.workers
    images_mib = decoded_at_once * settings.predict.max_image_pixels * RGB_BYTES_PER_PIXEL / MIB
    assert quantity(limits["memory"]) / MIB >= max(rss_mib) + images_mib

    writable = emptydir_mounts()
    one_upload = settings.calibration.max_upload_bytes + MAX_UNCOMPRESSED_BYTES
    assert quantity(writable[str(settings.storage.data_dir)]["sizeLimit"]) >= one_upload
    admitted = settings.predict.max_concurrent_inferences + settings.predict.max_queued_requests
    assert (
        quantity(writable[tempfile.gettempdir()]["sizeLimit"])
        >= admitted * settings.predict.max_request_bytes
    )


def test_the_image_is_this_release() -> None:
    assert container()["image"].rsplit(":", 1)[-1] == __version__
