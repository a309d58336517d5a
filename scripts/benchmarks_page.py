"""Write ``docs/benchmarks.md`` and the README's headline figures from the benchmark records.

    python scripts/benchmarks_page.py [--check]

Every ``scripts/bench_*.py`` records the figures it prints in ``docs/benchmarks/<script>.json``
(``scripts/benchrecord.py``). This script makes, from those files alone, the page
``docs/benchmarks.md`` (one section per script: what it measures, the command, the machine and
its load when the run started, then the figures) and the headline figures of ``README.md`` (the
region between :data:`START` and :data:`END`, replaced). A script without a record shows "not run
yet"; no figure is typed by hand. ``--check`` writes nothing and exits with 1 when either file
differs from what the records make (``tests/scripts/test_benchmarks_page.py`` runs the same comparison).
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "scripts"
RECORDS = ROOT / "docs" / "benchmarks"
PAGE = ROOT / "docs" / "benchmarks.md"
README = ROOT / "README.md"
START = "<!-- headline figures: written by python scripts/benchmarks_page.py -->"
END = "<!-- end of headline figures -->"
NOT_RUN = "not run yet"
LOADED = 0.5
"""A run started while the 1-minute load average was at least this share of the usable cores is
marked as timed under load."""
_UNITS = {"pct": "%", "gb": "GB", "mb": "MB", "cpu": "CPU", "rms": "RMS", "lm": "LM", "ba": "BA",
          "ms": "ms", "px": "px", "s": "s", "bc": "BC"}


@dataclass(frozen=True)
class Headline:
    """One row of the README's headline figures: ``template``'s ``{key}`` fields are filled from
    ``section`` of ``script``'s record."""

    label: str
    script: str
    section: str
    template: str


HEADLINES = (
    Headline("the demo's 80 frames, split by hand: generic camera, sharp + blurry",
             "bench_capture", "split",
             "{camera_error_px} px from the true camera (shape {camera_shape_px} px); {frames_used} of "
             "{frames} frames used"),
    Headline("the same frames as one mp4 video", "bench_capture", "video",
             "{camera_error_px} px from the true camera; {frames_used} of {frames} frames used"),
    Headline("real camera, held-out median (5-fold)", "bench_validation", "held out",
             "generic {generic_median_px} px, OpenCV rational-8 {rational8_median_px} px, "
             "Brown-Conrady {brown_conrady_median_px} px"),
    Headline("simulated frames, 12-25 px of blur", "bench_yield",
             "12-25 px blur, adaptive window (default)",
             "{returned_pct} % of the visible features, pose-consistent median "
             "{pose_consistent_median_px} px; {frames_extracted} of {frames} frames; {cpu_s_per_frame} s CPU "
             "per frame"),
    Headline("real frames, 5-12 px of blur", "bench_real_texture", "hints",
             "{yield_pct} % of the reference detector's features, median {median_px} px; "
             "{cpu_s_per_frame} s CPU per frame"),
    Headline("close-up 1280x720 frames, one thread", "bench_speed", "close-up frames (blur 4-15 px)",
             "{cpu_s_per_frame} s CPU per frame; {returned_pct} % of the visible features, median "
             "{median_px} px"),
    Headline("real sharp frames, Brown-Conrady", "bench_calibrate",
             "real fixture frames, sharp-set calibration",
             "median reprojection error {median_px} px over {frames_used} of {frames} frames"),
    Headline("1,000 frames' features: calibration and assessment", "bench_scale", "1000 frames",
             "{cpu_s} s CPU, {peak_gb} GB; camera {error_px} px from the truth; {frames_used} of {frames} "
             "frames used"),
    Headline("rolling shutter (readout 2 exposures), `auto`", "bench_rolling_shutter",
             "rolling shutter, --rolling-shutter auto",
             "camera {camera_median_px} px from the truth; {blurry_frames_used} of {blurry_frames} blurry "
             "frames used; readout ratio {readout_ratio}"),
)


# ----------------------------------------------------------------------------------- values
def value_text(value: Any) -> str:
    """A recorded figure as the page shows it: floats to about four significant digits."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        if abs(value) >= 1000:
            return f"{value:,.0f}"
        if abs(value) >= 100:
            return f"{value:.1f}"
        return f"{value:.4g}"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, list):
        return ", ".join(value_text(v) for v in value)
    if isinstance(value, dict):
        return ", ".join(f"{k} {value_text(v)}" for k, v in value.items())
    return str(value).replace("|", "/")


def key_text(key: str) -> str:
    """A figure's name as the page shows it: words, with its unit spelled (``median_px`` ->
    ``median px``, ``returned_pct`` -> ``returned %``)."""
    return " ".join(_UNITS.get(word, word) for word in key.split("_"))


# ----------------------------------------------------------------------------------- records
def load_records(folder: Path = RECORDS) -> dict[str, dict[str, Any]]:
    """The records in ``folder``, by script name."""
    return {p.stem: json.loads(p.read_text(encoding="utf-8")) for p in sorted(folder.glob("bench_*.json"))}


def scripts(folder: Path = SCRIPTS) -> dict[str, str]:
    """Every benchmark script's name and the first paragraph of its docstring."""
    out = {}
    for path in sorted(folder.glob("bench_*.py")):
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
        out[path.stem] = " ".join(doc.split("\n\n")[0].split()).replace("``", "`")
    return out


def conditions(record: dict[str, Any]) -> str:
    """The run's command, time, machine and load, as a sentence."""
    m = record["machine"]
    device = m["device"] + (f" ({m['gpu']})" if m.get("gpu") else "")
    load = (record.get("load_average") or {}).get("start")
    cores = m.get("usable_cores") or m.get("cores") or 1
    if load:
        loaded = load[0] >= LOADED * cores
        note = f" on {cores} usable cores: **timed under load**, compare CPU times only" if loaded else ""
        load_text = f"load average {load[0]:.2f} when it started{note}"
    else:
        load_text = "load average unknown"
    seconds = record.get("seconds") or {}
    took = (f"; the run took {value_text(seconds.get('wall'))} s wall, {value_text(seconds.get('cpu'))} s CPU"
            if seconds.get("wall") is not None else "")
    commit = f", commit `{record['commit']}`" if record.get("commit") else ""
    return (f"`{record['command']}` at {record['date']}{commit}, on {m['cpu']} ({m['cores']} cores, "
            f"{cores} usable), Python {m.get('python', '?')}, torch {m['torch']}, device {device}; "
            f"{load_text}{took}.")


def _tables(figures: dict[str, dict[str, Any]]) -> list[str]:
    """The figures as tables: consecutive sections with the same names side by side (one row
    each), any other section as a table of its own."""
    groups: list[list[str]] = []
    for section, values in figures.items():
        if groups and list(figures[groups[-1][0]]) == list(values):
            groups[-1].append(section)
        else:
            groups.append([section])
    lines: list[str] = []
    for group in groups:
        keys = list(figures[group[0]])
        if len(group) > 1:
            lines += ["| | " + " | ".join(key_text(k) for k in keys) + " |",
                      "|---" * (len(keys) + 1) + "|"]
            lines += [f"| {s} | " + " | ".join(value_text(figures[s][k]) for k in keys) + " |" for s in group]
        else:
            lines += [f"| {group[0]} | |", "|---|---|"]
            lines += [f"| {key_text(k)} | {value_text(v)} |" for k, v in figures[group[0]].items()]
        lines.append("")
    return lines


def render_page(records: dict[str, dict[str, Any]], described: dict[str, str]) -> str:
    """The text of ``docs/benchmarks.md``."""
    lines = ["# Benchmarks", "",
             "Written by `python scripts/benchmarks_page.py` from the records in "
             "[benchmarks/](benchmarks/); do not edit it by hand. Each `scripts/bench_*.py` prints its "
             "figures and records them, with the conditions of the run (command, machine, torch, device, "
             "the load average when it started), in `docs/benchmarks/<script>.json`. Rerun a script, then "
             "this page's script, to bring both up to date.", "",
             "Times depend on the machine and on what else runs on it: compare CPU times, and only between "
             "runs on the same machine. Accuracy, yield and counts do not depend on the machine.", "",
             "| script | what it measures | recorded |", "|---|---|---|"]
    for name, what in described.items():
        rec = records.get(name)
        when = f"{rec['date'][:10]}, {rec['machine']['cpu']}" if rec else NOT_RUN
        lines.append(f"| [`{name}`](#{name}) | {what} | {when} |")
    lines.append("")
    for name, what in described.items():
        lines += [f"## `{name}`", "", what, ""]
        rec = records.get(name)
        if rec is None:
            lines += [f"Not run yet: `python scripts/{name}.py`.", ""]
            continue
        lines += [f"Run: {conditions(rec)}", ""]
        lines += _tables(rec["figures"]) if rec["figures"] else ["No figures recorded.", ""]
    return "\n".join(lines).rstrip() + "\n"


class _MissingFigureError(KeyError):
    pass


class _Figures(dict):
    def __missing__(self, key: str) -> str:
        raise _MissingFigureError(key)


def headline_value(headline: Headline, records: dict[str, dict[str, Any]]) -> str:
    """A headline's text from the records, or why it has none."""
    rec = records.get(headline.script)
    if rec is None:
        return NOT_RUN
    section = rec["figures"].get(headline.section)
    if section is None:
        return f"not in the recorded run (`{rec['command']}`)"
    try:
        return headline.template.format_map(_Figures({k: value_text(v) for k, v in section.items()}))
    except _MissingFigureError as exc:
        return f"not in the recorded run ({exc.args[0]} missing)"


def render_headlines(records: dict[str, dict[str, Any]]) -> str:
    """The README's headline region, markers included."""
    lines = [START, "", "| figure | measured | benchmark |", "|---|---|---|"]
    for h in HEADLINES:
        lines.append(f"| {h.label} | {headline_value(h, records)} | "
                     f"[`{h.script}`](docs/benchmarks.md#{h.script}) |")
    lines += ["", END]
    return "\n".join(lines)


def replace_region(text: str, region: str) -> str:
    """``text`` with the region from :data:`START` to :data:`END` replaced by ``region``."""
    pattern = re.compile(re.escape(START) + r".*?" + re.escape(END), re.S)
    if not pattern.search(text):
        raise ValueError(f"README.md: no headline region ({START} ... {END})")
    return pattern.sub(lambda _: region, text, count=1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit with 1 when docs/benchmarks.md or the README is out of date")
    args = ap.parse_args(argv)
    records = load_records()
    page = render_page(records, scripts())
    try:
        readme = replace_region(README.read_text(encoding="utf-8"), render_headlines(records))
    except ValueError as exc:
        print(f"benchmarks_page: error: {exc}", file=sys.stderr)
        return 2
    targets = {PAGE: page, README: readme}
    if args.check:
        stale = [p for p, text in targets.items() if not p.is_file() or p.read_text(encoding="utf-8") != text]
        for p in stale:
            print(f"{p.relative_to(ROOT)} is out of date: run python scripts/benchmarks_page.py",
                  file=sys.stderr)
        return 1 if stale else 0
    for p, text in targets.items():
        p.write_text(text, encoding="utf-8")
    print(f"wrote {PAGE.relative_to(ROOT)} ({len(records)} of {len(scripts())} benchmarks recorded) and the "
          "README's headline figures")
    return 0


if __name__ == "__main__":
    sys.exit(main())
