"""blurcalib: sub-pixel features and spatially varying PSFs from motion-blurred calibration frames."""

__version__ = "0.1.0"
