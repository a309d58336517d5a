"""The figures a benchmark script prints, also written as JSON, with the conditions of the run.

Every ``scripts/bench_*.py`` records its figures through this module::

    parser = argparse.ArgumentParser(...)
    benchrecord.add_option(parser)            # --record FILE
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    ...
    record.add("simulated frames", median_px=0.0123, returned_pct=91.2, cpu_s_per_frame=1.4)
    record.write()

:func:`start` notes the machine (CPU model, cores, torch version, the torch device of the run),
the command line, the UTC time and the load average when the run starts; :meth:`BenchRecord.write`
adds the load average at the end and the run's wall and CPU seconds, and writes the record to
``docs/benchmarks/<script>.json`` (``--record FILE`` elsewhere, ``--record none`` not at all).
``python scripts/benchmarks_page.py`` makes ``docs/benchmarks.md`` and the README's headline
figures from those files.

A figure's key ends with its unit: ``_px``, ``_s``, ``_ms``, ``_pct``, ``_gb``, ``_mb`` (none for
counts and ratios). Floats that are not finite are written as ``null``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import resource
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RECORD_DIR = ROOT / "docs" / "benchmarks"
"""Where the records live, one ``<script>.json`` per benchmark script."""
SIGNIFICANT = 6
"""Significant digits kept of a float figure."""


def add_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--record FILE`` to a benchmark's parser."""
    parser.add_argument("--record", metavar="FILE", default=None,
                        help="write the printed figures as JSON to FILE (default "
                             "docs/benchmarks/<script>.json; none: do not write them)")


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), or what :mod:`platform` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace").splitlines():
            if line.lower().startswith("model name"):
                return " ".join(line.split(":", 1)[1].split())
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def machine(device: str = "cpu") -> dict[str, Any]:
    """The conditions a time depends on: CPU model, cores (all, and those this process may use),
    Python and torch versions, the torch device (with its GPU's name on CUDA)."""
    import torch

    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    info: dict[str, Any] = {"cpu": cpu_model(), "cores": os.cpu_count(), "usable_cores": usable,
                            "python": platform.python_version(), "torch": torch.__version__,
                            "device": device}
    if device.startswith("cuda") and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    return info


def _commit() -> str | None:
    """The checkout's commit, with ``+changes`` when its code (``blurcalib/``, ``scripts/``)
    differs from it."""
    try:
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=12", "HEAD"],
                              capture_output=True, text=True, timeout=10, check=False).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no",
                                "--", "blurcalib", "scripts"],
                               capture_output=True, text=True, timeout=10, check=False).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return (head + ("+changes" if dirty else "")) or None


def _load() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def clean(value: Any) -> Any:
    """A figure as JSON holds it: floats to :data:`SIGNIFICANT` digits (not finite: None), numpy
    scalars and arrays as Python numbers and lists, mappings and sequences element by element."""
    if hasattr(value, "tolist"):  # numpy scalars and arrays
        value = value.tolist()
    if isinstance(value, bool) or value is None or isinstance(value, (int, str)):
        return value
    if isinstance(value, float):
        return float(f"{value:.{SIGNIFICANT}g}") if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean(v) for v in value]
    return str(value)


@dataclass
class BenchRecord:
    """One run of a benchmark script: its conditions and the figures it printed, by section."""

    script: str
    path: Path | None
    command: str
    date: str
    machine: dict[str, Any]
    load_start: list[float] | None
    commit: str | None
    figures: dict[str, dict[str, Any]] = field(default_factory=dict)
    _wall0: float = field(default_factory=time.perf_counter, repr=False)
    _cpu0: float = field(default_factory=time.process_time, repr=False)

    def add(self, section: str, **figures: Any) -> None:
        """Record ``figures`` (name with its unit suffix -> value) under ``section``, after any
        recorded there before."""
        self.figures.setdefault(section, {}).update({k: clean(v) for k, v in figures.items()})

    def to_dict(self) -> dict[str, Any]:
        children = resource.getrusage(resource.RUSAGE_CHILDREN)
        return {"script": self.script, "command": self.command, "date": self.date, "commit": self.commit,
                "machine": self.machine,
                "load_average": {"start": self.load_start, "end": _load()},
                "seconds": {"wall": clean(time.perf_counter() - self._wall0),
                            "cpu": clean(time.process_time() - self._cpu0),
                            "cpu_children": clean(children.ru_utime + children.ru_stime)},
                "figures": self.figures}

    def write(self) -> Path | None:
        """Write the record (atomically) where ``--record`` says; returns the path, or None."""
        if self.path is None:
            return None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
        tmp.replace(self.path)
        print(f"figures recorded in {self._shown(self.path)}", file=sys.stderr)
        return self.path

    @staticmethod
    def _shown(path: Path) -> str:
        try:
            return str(path.resolve().relative_to(ROOT))
        except ValueError:
            return str(path)


def start(script_file: str, args: argparse.Namespace | None = None, device: str | None = None) -> BenchRecord:
    """Begin the record of the script ``script_file`` (its ``__file__``) run with ``args``
    (``--record`` and ``--device`` are read from them when present)."""
    script = Path(script_file).stem
    choice = getattr(args, "record", None)
    path = None if choice == "none" else Path(choice) if choice else RECORD_DIR / f"{script}.json"
    device = device or getattr(args, "device", None) or "cpu"
    command = shlex.join(["python", f"scripts/{Path(script_file).name}", *sys.argv[1:]])
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    return BenchRecord(script, path, command, date, machine(device), _load(), _commit())
