"""Paper-style evidence (validity, tightness, adaptiveness, baseline) for the served detector.

``python -m training.evaluate_conformal`` runs it and writes ``docs/evaluation.md``.
Every set, score and threshold comes from the service's own code (``service.calibration``,
``service.conformal``); this package only collects, summarizes and draws.
"""
