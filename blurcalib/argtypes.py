"""Command-line value types: each parses and checks one option's text (argparse ``type=``) and
raises :class:`argparse.ArgumentTypeError` with a one-line message naming the value."""

from __future__ import annotations

import argparse
import math

from blurcalib.calib.rolling_shutter import parse_rolling_shutter
from blurcalib.io.frames import frame_size_problem
from blurcalib.runs.cluster import ClusterError, check_address
from blurcalib.target.pattern import PAGE_SIZES_MM

__all__ = ["cluster_address", "fold_count", "image_size", "non_negative_number", "page_size", "positive_int",
           "positive_number", "psf_window", "readout_ratio", "rolling_shutter_mode"]

MAX_PSF_WINDOW = 255
"""Largest ``--psf-size`` (px): four times the largest window the growth reaches by itself (61 px);
every block's deconvolution grows with its square."""


def page_size(text: str) -> tuple[float, float]:
    """A page: one of :data:`blurcalib.target.pattern.PAGE_SIZES_MM` or ``WIDTHxHEIGHT`` in mm."""
    if text in PAGE_SIZES_MM:
        return PAGE_SIZES_MM[text]
    try:
        w, h = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"page must be one of {', '.join(PAGE_SIZES_MM)} or WIDTHxHEIGHT in mm, got {text!r}"
        ) from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"page size must be positive, got {text!r}")
    return (w, h)


def image_size(text: str) -> tuple[int, int]:
    """An image size ``WxH`` in px that a frame may have
    (:func:`blurcalib.io.frames.frame_size_problem`: sides of 32 px or more, at most 50 MP)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH in px (e.g. 1280x720), got {text!r}") from None
    problem = frame_size_problem(w, h)
    if problem is not None:
        raise argparse.ArgumentTypeError(problem.removeprefix("is "))
    return w, h


def positive_int(text: str) -> int:
    """An argparse type: a whole number >= 1 (counts of workers, threads, folds, frames)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _finite_number(text: str, zero_allowed: bool) -> float:
    """A finite number > 0, or >= 0 with ``zero_allowed``."""
    least = ">= 0" if zero_allowed else "> 0"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number {least}, got {text!r}") from None
    if not (math.isfinite(value) and (value >= 0 if zero_allowed else value > 0)):
        raise argparse.ArgumentTypeError(f"must be a finite number {least}, got {text!r}")
    return value


def positive_number(text: str) -> float:
    """A finite number > 0."""
    return _finite_number(text, zero_allowed=False)


def non_negative_number(text: str) -> float:
    """A finite number >= 0."""
    return _finite_number(text, zero_allowed=True)


def fold_count(text: str) -> int:
    """A number of validation folds: a whole number >= 2."""
    value = positive_int(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"must be >= 2 (each fold's frames are scored by the others), "
                                         f"got {value}")
    return value


def psf_window(text: str) -> int:
    """A PSF window side in px: odd, from 3 to :data:`MAX_PSF_WINDOW`; 0 picks the default."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an odd whole number of px, got {text!r}") from None
    if value != 0 and not (3 <= value <= MAX_PSF_WINDOW and value % 2):
        raise argparse.ArgumentTypeError(f"must be odd, from 3 to {MAX_PSF_WINDOW} px, got {value}")
    return value


def cluster_address(text: str) -> str:
    """A Dask scheduler address (:func:`blurcalib.runs.cluster.check_address`)."""
    try:
        return check_address(text)
    except ClusterError as exc:
        raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[1]) from None


def rolling_shutter_mode(text: str) -> str | float:
    """``off``, ``auto`` or a readout ratio
    (:func:`blurcalib.calib.rolling_shutter.parse_rolling_shutter`)."""
    try:
        return parse_rolling_shutter(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def readout_ratio(text: str) -> float:
    """A simulated rolling shutter's readout ratio: a number in [0, 10] (0: a global shutter)."""
    value = rolling_shutter_mode(text)
    if not isinstance(value, float):
        raise argparse.ArgumentTypeError(f"rolling shutter {text!r}: expected a readout ratio in [0, 10]")
    return value
