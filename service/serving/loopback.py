"""The service on a loopback port, in a thread of this process: the command line's ``predict``
talks to it through the client as it would to any server."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import uvicorn

from service.infra.settings import Settings
from service.serving.app import create_app
from service.serving.container import build_state

STARTUP_TIMEOUT_S = 30.0


@contextmanager
def served(settings: Settings) -> Iterator[str]:
    """Load the model and store as ``serve`` does (refusing a bad model or store the same way),
    serve them on a free loopback port until the block ends, and yield the base URL."""
    state = build_state(settings)
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        listener.bind(("127.0.0.1", 0))
        app = create_app(state=state)
        server = uvicorn.Server(uvicorn.Config(app, log_config=None, log_level="warning", access_log=False))
        thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]}, daemon=True)
        thread.start()
        try:
            deadline = time.monotonic() + STARTUP_TIMEOUT_S
            while not server.started:
                if not thread.is_alive() or time.monotonic() > deadline:
                    raise RuntimeError("the in-process server did not start")
                time.sleep(0.01)
            host, port = listener.getsockname()
            yield f"http://{host}:{port}"
        finally:
            server.should_exit = True
            thread.join()
    finally:
        listener.close()
        state.close()
