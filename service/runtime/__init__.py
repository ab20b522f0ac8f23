"""The infrastructure around the domain: settings, the long-lived parts (container), the server,
admission, metrics, logs, the audit trail, operators."""
