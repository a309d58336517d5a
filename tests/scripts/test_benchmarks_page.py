"""Benchmark records: every bench script writes one, and docs/benchmarks.md and the README's
headline figures are what scripts/benchmarks_page.py makes from the records in the repository."""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import re
import sys

import numpy as np
import pytest

from tests.conftest import ROOT

SCRIPTS = ROOT / "scripts"


def _load(name: str):
    sys.path.insert(0, str(SCRIPTS))  # the bench scripts import benchrecord as run from scripts/
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def page():
    return _load("benchmarks_page")


def test_benchmarks_page_is_what_the_records_make(page) -> None:
    records = page.load_records()
    text = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    assert text == page.render_page(records, page.scripts()), \
        "docs/benchmarks.md is out of date: run python scripts/benchmarks_page.py"


def test_readme_headlines_are_what_the_records_make(page) -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    region = page.render_headlines(page.load_records())
    assert region in readme, \
        "the README's headline figures are out of date: run python scripts/benchmarks_page.py"


def test_every_benchmark_records_its_figures() -> None:
    scripts = sorted(SCRIPTS.glob("bench_*.py"))
    assert len(scripts) >= 15
    for path in scripts:
        text = path.read_text(encoding="utf-8")
        assert "benchrecord.add_option(" in text and "benchrecord.start(" in text, path.name
        assert "record.add(" in text and "record.write()" in text, path.name


def test_a_record_holds_the_conditions_and_the_figures(tmp_path, monkeypatch) -> None:
    benchrecord = _load("benchrecord")
    monkeypatch.setattr(sys, "argv", ["bench_x.py", "--frames", "2"])
    out = tmp_path / "rec" / "bench_x.json"
    record = benchrecord.start(str(SCRIPTS / "bench_x.py"), argparse.Namespace(record=str(out), device="cpu"))
    record.add("set", frames=np.int64(2), median_px=np.float32(0.0123456789), worst_px=math.nan,
               kinds={"sharp": 1}, ok=True)
    record.add("set", cpu_s_per_frame=1.5)
    assert record.write() == out
    data = json.loads(out.read_text(encoding="utf-8"))
    assert data["script"] == "bench_x" and data["command"] == "python scripts/bench_x.py --frames 2"
    assert {"cpu", "cores", "usable_cores", "torch", "device", "python"} <= set(data["machine"])
    assert data["machine"]["device"] == "cpu" and data["machine"]["cores"] >= 1
    assert len(data["load_average"]["start"]) == 3 and data["date"].endswith("Z")
    assert data["seconds"]["wall"] >= 0 and data["seconds"]["cpu"] >= 0
    assert data["figures"] == {"set": {"frames": 2, "median_px": 0.0123457, "worst_px": None,
                                       "kinds": {"sharp": 1}, "ok": True, "cpu_s_per_frame": 1.5}}


def test_record_none_writes_nothing(tmp_path) -> None:
    benchrecord = _load("benchrecord")
    record = benchrecord.start(str(SCRIPTS / "bench_x.py"), argparse.Namespace(record="none"))
    record.add("set", frames=1)
    assert record.write() is None


def test_a_benchmark_without_a_record_is_not_run_yet(page) -> None:
    described = {"bench_a": "What A measures.", "bench_b": "What B measures."}
    record = {"command": "python scripts/bench_b.py --frames 2", "date": "2030-01-01T00:00:00Z",
              "commit": "abc", "machine": {"cpu": "Some CPU", "cores": 8, "usable_cores": 2, "python": "3.11",
                                           "torch": "2.13", "device": "cpu"},
              "load_average": {"start": [3.5, 2.0, 1.0], "end": [1.0, 1.0, 1.0]},
              "seconds": {"wall": 12.0, "cpu": 10.0},
              "figures": {"frames 200": {"frames": 200, "error_px": 0.0017},
                          "frames 400": {"frames": 400, "error_px": 0.0016},
                          "memory": {"peak_gb": 1.35}}}
    text = page.render_page({"bench_b": record}, described)
    section_a = text.split("## `bench_a`")[1].split("## `bench_b`")[0]
    assert "Not run yet" in section_a and "| [`bench_a`](#bench_a) | What A measures. | not run yet |" in text
    assert "**timed under load**" in text and "2 usable" in text and "Some CPU" in text
    assert "| frames 200 | 200 | 0.0017 |" in text and "| peak GB | 1.35 |" in text
    headlines = page.render_headlines({})
    assert headlines.count(page.NOT_RUN) == len(page.HEADLINES)
    assert page.replace_region(f"a\n{page.START}\nold\n{page.END}\nb", headlines) == f"a\n{headlines}\nb"
    with pytest.raises(ValueError):
        page.replace_region("no region", headlines)


def test_headline_templates_name_recorded_figures(page) -> None:
    """Each headline names its script's section and figures as the script records them."""
    for h in page.HEADLINES:
        source = (SCRIPTS / f"{h.script}.py").read_text(encoding="utf-8")
        for key in re.findall(r"\{(\w+)\}", h.template):
            assert f"{key}=" in source or f'"{key}"' in source or f"{key}_" in source, (h.script, key)


def test_readme_stays_within_10_kb_with_every_headline_filled(page) -> None:
    records: dict = {}
    for h in page.HEADLINES:
        figures = records.setdefault(h.script, {"command": "python scripts/x.py", "figures": {}})["figures"]
        figures[h.section] = {key: 12345.678 for key in re.findall(r"\{(\w+)\}", h.template)}
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    filled = page.replace_region(readme, page.render_headlines(records))
    assert page.NOT_RUN not in page.render_headlines(records)
    assert len(filled.encode("utf-8")) <= 10_000, len(filled.encode("utf-8"))
