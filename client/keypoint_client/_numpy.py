"""numpy, when installed: only the set geometry and numpy images need it."""

from __future__ import annotations

try:
    import numpy as np
except ImportError:
    np = None  # type: ignore[assignment]

__all__ = ["np", "require_numpy"]


def require_numpy(what: str) -> None:
    if np is None:
        raise ImportError(f"{what} needs numpy: pip install 'keypoint-client[numpy]'")
