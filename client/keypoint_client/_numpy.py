"""numpy, when installed: only the set geometry and numpy images need it."""

from __future__ import annotations

try:
    import numpy as np
except ImportError:
    np = None  # type: ignore[assignment]

__all__ = ["np", "require_numpy"]


# The client is installed from a checkout of the service (it is not on a package index).
INSTALL_NUMPY = "pip install './client[numpy]'"


def require_numpy(what: str) -> None:
    if np is None:
        raise ImportError(
            f"{what} needs numpy: {INSTALL_NUMPY} from the service's checkout (or pip install numpy)"
        )
