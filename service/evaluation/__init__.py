"""The paper's evaluation of a calibration version on a labeled batch (Yang & Pavone):
validity against the exact coverage law, tightness, adaptiveness.

``keypoint-service evaluate FOLDER`` runs it (``service.evaluation.run``) and writes
Markdown with PNG figures; ``docs/evaluation.md`` is its output on the rendered test split.
Every set, score and threshold comes from the service's own code (``service.calibration``,
``service.conformal``); this package only collects, summarizes and draws.
"""
