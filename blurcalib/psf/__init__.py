"""Point-spread functions: one kernel's moments and re-centring, and the frame's PSF field."""
