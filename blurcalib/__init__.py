"""blurcalib: sub-pixel features and spatially varying PSFs from motion-blurred calibration frames."""

from importlib.metadata import PackageNotFoundError, version

from blurcalib.runs.runtime import passive_openmp_wait, quiet_openblas

passive_openmp_wait()  # before any module imports torch (blurcalib.runs.runtime)
quiet_openblas()  # before any module imports NumPy

try:
    __version__ = version("blurcalib")  # pyproject.toml's version, from the installed package
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "unknown"
