"""The HTTP server: uvicorn serving ``service.serving.main:app``, configured from Settings.

What a public port needs beyond this (slow request heads and bodies, connection caps, shares by
network, header limits before the app reads them) is the proxy's: deploy/haproxy/haproxy.cfg.
Here, uvicorn serves at most ``MAX_CONNECTIONS`` connections per process (503 beyond), believes
``X-Forwarded-For`` only from CKS_TRUSTED_PROXIES, and on SIGTERM stops accepting, closes idle
connections and gives in-flight requests up to CKS_SHUTDOWN_GRACE_SECONDS; then the app's shutdown
marks running calibration jobs interrupted (``ServiceState.close``), and the process exits 0.
"""

from __future__ import annotations

import signal
from types import FrameType

import uvicorn

from service.infra.logs import uvicorn_log_config
from service.infra.settings import Settings

APP = "service.serving.main:app"
MAX_CONNECTIONS = 1000  # each takes a file descriptor


def serve(settings: Settings, host: str | None = None, port: int | None = None) -> int:
    """Serve until SIGTERM or SIGINT, then stop gracefully; 0 after a graceful stop."""
    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        uvicorn.run(
            APP,
            host=host or settings.server.host,
            port=port or settings.server.port,
            workers=settings.server.workers,
            limit_concurrency=MAX_CONNECTIONS + 1,  # uvicorn counts the request's own connection
            proxy_headers=bool(settings.predict.trusted_proxies),
            forwarded_allow_ips=list(settings.predict.trusted_proxies) or None,
            timeout_graceful_shutdown=settings.server.shutdown_grace_seconds,
            log_config=uvicorn_log_config(settings),  # uvicorn's lines in the service's format
            access_log=False,  # the access line is the service's own
        )
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0


def _exit_on_sigterm(signum: int, frame: FrameType | None) -> None:
    """SIGTERM outside uvicorn's own handler: before the server runs, stop at once; after its
    graceful stop uvicorn raises the signal again for the handler it found (this one), which
    would otherwise be the default action, killing the process (exit status 143, not 0)."""
    raise SystemExit(0)
