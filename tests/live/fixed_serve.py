"""``keypoint-service serve`` with fixed values of ``service.serving.container`` changed, for a live
test: ``python -m tests.live.fixed_serve '{"MAX_DECODED_BYTES": 67108864}' serve --port 8123``.
One process only: uvicorn's worker processes (CKS_WORKERS > 1) import the module afresh."""

from __future__ import annotations

import json
import sys

from service.cli import main
from service.serving import container

if __name__ == "__main__":
    for name, value in json.loads(sys.argv[1]).items():
        assert hasattr(container, name), f"service.serving.container has no {name}"
        setattr(container, name, value)
    sys.exit(main(sys.argv[2:]))
