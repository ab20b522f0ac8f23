"""OpenAPI links: where a job's id, and what the job made, go next (generated clients and
schemathesis's stateful phase follow them)."""

from __future__ import annotations

JOB_LINKS = {
    "GetJob": {"operationId": "get_job", "parameters": {"job_id": "$response.body#/id"}},
    "RetryJob": {"operationId": "retry_job", "parameters": {"job_id": "$response.body#/id"}},
}
JOB_RESULT_LINKS = {
    "GetCalibration": {
        "operationId": "get_calibration",
        "parameters": {"version": "$response.body#/version"},
    },
    "ActivateCalibration": {
        "operationId": "activate_calibration",
        "parameters": {"version": "$response.body#/version"},
    },
    "GetAudit": {"operationId": "get_audit", "parameters": {"audit_id": "$response.body#/result/audit"}},
}
