"""The service as a Ray Serve application: N replicas of the same FastAPI app on one PostgreSQL store.

Settings are read once, where the application is built, and handed to every replica. It lives in the
package because every node of a Ray cluster must import it (deploy/ray/README.md).
"""

from __future__ import annotations

import argparse
import signal
import sys
from dataclasses import dataclass, fields
from typing import Any

import ray
from fastapi import FastAPI
from ray import serve
from ray.serve import Application
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from calibration_store import store_location
from service.infra.processes import remove_dead_process_folders
from service.infra.settings import Settings
from service.serving.app import create_app

APP_NAME = "keypoints"
DEPLOYMENT_NAME = "KeypointService"
REPLICA_HEADER = "X-Replica"
#: Serve slots of a replica beyond its admission's: probes and admin calls are not held back
ADMIN_HEADROOM = 4


@dataclass(frozen=True)
class Scaling:
    """How many replicas, how big (autoscaling with ``max_replicas``); Serve sends each what its
    admission holds plus ADMIN_HEADROOM by default, so the app, not Serve, queues and refuses."""

    replicas: int = 2
    min_replicas: int = 1
    max_replicas: int | None = None
    target_ongoing_requests: float | None = None
    max_ongoing_requests: int | None = None
    num_cpus: float = 1.0
    num_gpus: float = 0.0  # for a GPU provider in CKS_EXECUTION_PROVIDERS: Ray gives each replica one

    def __post_init__(self) -> None:
        if self.replicas < 1 or self.min_replicas < 1:
            raise ValueError("replicas and min_replicas must be at least 1 (replicas run calibration jobs)")
        if self.max_replicas is not None and self.max_replicas < self.min_replicas:
            raise ValueError(f"max_replicas {self.max_replicas} is below min_replicas {self.min_replicas}")
        if self.num_cpus <= 0:
            raise ValueError("num_cpus must be positive")
        if self.num_gpus < 0:
            raise ValueError("num_gpus must be 0 or more")

    def deployment_options(self, settings: Settings) -> dict[str, Any]:
        slots = settings.predict.max_concurrent_inferences
        ongoing = self.max_ongoing_requests or slots + settings.predict.max_queued_requests + ADMIN_HEADROOM
        actor = {"num_cpus": self.num_cpus} | ({"num_gpus": self.num_gpus} if self.num_gpus else {})
        options: dict[str, Any] = {"max_ongoing_requests": ongoing, "ray_actor_options": actor}
        if self.max_replicas is None:
            options["num_replicas"] = self.replicas
        else:
            options["autoscaling_config"] = {
                "min_replicas": self.min_replicas,
                "max_replicas": self.max_replicas,
                "target_ongoing_requests": self.target_ongoing_requests or slots,
            }
        return options


class ReplicaHeader:
    """ASGI middleware naming the replica that answered in REPLICA_HEADER."""

    def __init__(self, app: ASGIApp, replica: str) -> None:
        self._app = app
        self._header = (REPLICA_HEADER.lower().encode(), replica.encode())

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        async def send_named(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", ()), self._header]}
            await send(message)

        await self._app(scope, receive, send_named if scope["type"] == "http" else send)


@serve.deployment(name=DEPLOYMENT_NAME)
@serve.ingress()
class KeypointService:
    """One replica: the service's FastAPI app, built on the replica (``__serve_build_asgi_app__``)."""

    def __init__(self, settings: Settings) -> None:
        self._settings = settings
        # upload workspaces of replicas killed on this node: their uploads were never stored
        remove_dead_process_folders(settings.storage.data_dir / "uploads", starting=True)

    def __serve_build_asgi_app__(self) -> FastAPI:
        app = create_app(self._settings)
        app.add_middleware(ReplicaHeader, replica=serve.get_replica_context().replica_id.unique_id)
        return app


def application(settings: Settings, scaling: Scaling) -> Application:
    """The Serve application: KeypointService with ``scaling``, every replica on ``settings``."""
    kind, location = store_location(settings.storage.resolved_url)
    if kind != "postgresql":
        raise ValueError(
            f"the calibration store is {kind} ({location}), a file of one node; Ray may start replicas on"
            " any node, so give them one PostgreSQL store: CKS_STORE_URL=postgresql://user@host/db"
        )
    return KeypointService.options(**scaling.deployment_options(settings)).bind(settings)


def build_app(args: dict[str, Any]) -> Application:
    """The application builder of deploy/ray/serve_config.yaml: ``args`` are Scaling's fields;
    settings come from the CKS_* variables of the application's ``runtime_env``."""
    return application(Settings(), Scaling(**args))


def deploy(settings: Settings, scaling: Scaling, http_options: dict[str, Any]) -> str:
    """Start Serve's proxies (on the connected Ray cluster) and run the application; its URL."""
    serve.start(http_options=http_options)
    serve.run(application(settings, scaling), name=APP_NAME, route_prefix="/")
    return f"http://{http_options['host']}:{http_options['port']}"


def _parser() -> argparse.ArgumentParser:
    defaults = Scaling()
    parser = argparse.ArgumentParser(
        prog="python -m service.deploy_ray",
        description="Serve the keypoint service with Ray Serve: replicas on a Ray cluster, one PostgreSQL"
        " store. Other settings come from the CKS_* environment variables, as for keypoint-service serve.",
    )
    cluster = parser.add_argument_group("Ray").add_argument
    cluster("--address", help="Ray cluster to join (default: RAY_ADDRESS, `ray start`'s, or a new one)")
    cluster("--detach", action="store_true", help="deploy and exit (default: serve until Ctrl-C or SIGTERM)")
    http = parser.add_argument_group("Serve's HTTP proxy (one per node)")
    http.add_argument("--host", help="address the proxies listen on (default CKS_HOST)")
    http.add_argument("--port", type=int, help="port the proxies listen on (default CKS_PORT)")
    http.add_argument("--request-timeout-s", type=float, help="end-to-end limit per request (408 beyond)")
    http.add_argument("--keep-alive-timeout-s", type=int, default=90, help="idle connections close after it")
    scale = parser.add_argument_group("replicas")
    scale.add_argument("--replicas", type=int, default=defaults.replicas, help="fixed number of replicas")
    scale.add_argument("--min-replicas", type=int, default=defaults.min_replicas, help="autoscaling floor")
    scale.add_argument("--max-replicas", type=int, help="autoscale up to this many (default: no autoscaling)")
    scale.add_argument("--target-ongoing-requests", type=float, help="autoscaling target per replica")
    scale.add_argument("--max-ongoing-requests", type=int, help="requests Serve sends one replica at once")
    scale.add_argument("--num-cpus", type=float, default=defaults.num_cpus, help="CPUs reserved per replica")
    scale.add_argument("--num-gpus", type=float, default=defaults.num_gpus, help="GPUs reserved per replica")
    service = parser.add_argument_group("service settings (override the CKS_* variables)")
    service.add_argument("--store-url", help="CKS_STORE_URL: postgresql://user@host:5432/db")
    service.add_argument("--data-dir", help="CKS_DATA_DIR, the same path on every node (shared, for retries)")
    service.add_argument("--model-dir", help="CKS_MODEL_DIR, the same path on every node")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    overrides = {name: getattr(args, name) for name in ("store_url", "data_dir", "model_dir")}
    settings = Settings(**{name: value for name, value in overrides.items() if value is not None})
    scaling = Scaling(**{field.name: getattr(args, field.name) for field in fields(Scaling)})
    http_options = {"host": args.host or settings.server.host, "port": args.port or settings.server.port}
    http_options |= {name: getattr(args, name) for name in ("request_timeout_s", "keep_alive_timeout_s")}
    ray.init(address=args.address)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # as Ctrl-C (ray.init's handler just exits)
    try:
        url = deploy(settings, scaling, http_options)
        print(f"serving {url} (application {APP_NAME!r}; `serve status` shows its replicas)", flush=True)
        while not args.detach:
            signal.pause()
    except KeyboardInterrupt:
        serve.delete(APP_NAME)  # replicas finish their requests and close their state
    return 0


if __name__ == "__main__":
    sys.exit(main())
