"""The paper's evaluation (Yang & Pavone) of a calibration version on a labeled batch: validity, tightness,
adaptiveness, as Markdown with PNG figures; every set, score and threshold is the service's own."""
