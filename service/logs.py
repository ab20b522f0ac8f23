"""Logging of the service's own loggers, in the format uvicorn uses for its lines.

``keypoint-service`` configures logging for the whole process; a server started any other
way (``uvicorn service.api.main:app``, a process manager) has no handler for the
service's loggers, and their INFO lines (the start-up summary, the audit trail) would be
lost. ``ensure_logging`` gives them one, unless the process configured logging itself.
"""

from __future__ import annotations

import logging

FORMAT = "%(levelname)s:     %(name)s: %(message)s"
SERVICE_LOGGERS = ("service", "calibration_store")


def ensure_logging() -> None:
    """Send INFO and above of the service's loggers to stderr if nothing else was configured."""
    if logging.getLogger().handlers:
        return
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter(FORMAT))
    for name in SERVICE_LOGGERS:
        logger = logging.getLogger(name)
        if not logger.handlers:
            logger.addHandler(handler)
            logger.setLevel(logging.INFO)
            logger.propagate = False
