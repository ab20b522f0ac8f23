"""Crash points for fault-injection tests of real processes.

With ``CKS_FAULT=<point>`` in its environment, a process is killed with SIGKILL when it reaches
that point, exactly as a power cut or the OOM killer would stop it there: ``version-written``
(a version, its activation, its job's success and audit entries are written but not committed)
and ``version-committed`` (just committed, nothing else done). Unset, a point costs one
environment lookup.
"""

from __future__ import annotations

import os
import signal

FAULT_ENV = "CKS_FAULT"


def crash_point(name: str) -> None:
    if os.environ.get(FAULT_ENV) == name:
        os.kill(os.getpid(), signal.SIGKILL)
