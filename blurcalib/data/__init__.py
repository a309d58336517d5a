"""Data shipped with the package: the reference tool's pattern YAMLs (``patterns/``, BSD-3-Clause,
licence in ``patterns/LICENSE``).

They are the compatibility fixtures of the target: ``blurcalib pattern`` reproduces each of them
byte for byte, and the default (17x24 squares of about 12 mm on A4, 16-segment stars, AprilTag
tag36h11 #0) is the page the simulator and the demo use.
"""

from __future__ import annotations

from pathlib import Path

PATTERNS_DIR = Path(__file__).resolve().parent / "patterns"
DEFAULT_PATTERN = "pattern_resolution_17x24_segments_16_apriltag_0.yaml"
REFERENCE_PATTERNS = (
    DEFAULT_PATTERN,
    "pattern_resolution_25x36_segments_16_apriltag_6.yaml",
    "pattern_resolution_50x72_segments_16_apriltag_3.yaml",
)


def reference_pattern_path(name: str = DEFAULT_PATTERN) -> Path:
    """Path of a shipped reference pattern YAML.

    Args:
        name: one of :data:`REFERENCE_PATTERNS` (file name).
    Raises:
        ValueError: an unknown name (the message lists the known ones).
    """
    if name not in REFERENCE_PATTERNS:
        raise ValueError(f"{name}: not a shipped reference pattern (one of {', '.join(REFERENCE_PATTERNS)})")
    return PATTERNS_DIR / name
