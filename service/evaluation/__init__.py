"""The paper's evaluation of a calibration version on a labeled batch (Yang & Pavone): validity against
the exact coverage law, tightness, adaptiveness, written by ``keypoint-service evaluate`` as Markdown
with PNG figures; every set, score and threshold comes from the service's own code.
"""
