"""Calibration: parametric camera of the sharp set, global alignment, generic bundle adjustment and trust."""
