"""OpenAPI links: where a job's id, and what the job made, go next (generated clients and
schemathesis's stateful phase follow them)."""

from __future__ import annotations

_JOB_ID = {"job_id": "$response.body#/id"}
_VERSION = {"version": "$response.body#/version"}
JOB_LINKS = {
    "GetJob": {"operationId": "get_job", "parameters": _JOB_ID},
    "RetryJob": {"operationId": "retry_job", "parameters": _JOB_ID},
}
JOB_RESULT_LINKS = {
    "GetCalibration": {"operationId": "get_calibration", "parameters": _VERSION},
    "ActivateCalibration": {"operationId": "activate_calibration", "parameters": _VERSION},
    "GetAudit": {"operationId": "get_audit", "parameters": {"audit_id": "$response.body#/result/audit"}},
}
