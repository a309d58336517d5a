"""scripts/check_docs.py: the repository's markdown is sound, and the check catches what it must."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.conftest import ROOT

SCRIPT = ROOT / "scripts" / "check_docs.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True,
                          timeout=120, check=False)


def test_repository_docs_are_sound() -> None:
    result = _run(str(ROOT))
    assert result.returncode == 0, result.stdout
    assert "0 problems" in result.stderr


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")


def test_sound_links_pass(tmp_path: Path) -> None:
    _write(tmp_path / "README.md", "# Top\n\nSee [the guide](docs/guide.md#step-2-run-it), [a repeat]"
           "(docs/guide.md#notes-1), ![figure](docs/fig.png), [top](#top) and [web](https://example.com).\n"
           "\n```\n[inside code](missing.md)\n```\n\nA span: `[x](missing.md)`.\n"
           "[Code in a heading](docs/guide.md#speed-python-bench_speedpy---pair).\n")
    _write(tmp_path / "docs" / "guide.md", "# Guide\n\n## Step 2: run it\n\n## Notes\n\n## Notes\n"
           "\n## Speed (`python bench_speed.py --pair`)\n")
    (tmp_path / "docs" / "fig.png").write_bytes(b"\x89PNG")
    result = _run(str(tmp_path))
    assert result.returncode == 0, result.stdout
    assert "2 markdown files, 0 problems" in result.stderr


def test_planted_problems_are_caught(tmp_path: Path) -> None:
    _write(tmp_path / "README.md", "# Top\n\n[gone](docs/missing.md)\n\n[bad anchor](docs/ok.md#nowhere)\n"
           "\n[ref]: docs/also-missing.png\n")
    _write(tmp_path / "docs" / "ok.md", "# Ok\n\n![img](../img/none.png)\n")
    _write(tmp_path / "docs" / "huge.md", "# Huge\n\n" + "x" * 201_000 + "\n")
    result = _run(str(tmp_path))
    assert result.returncode == 1
    lines = result.stdout.splitlines()
    assert len(lines) == 5, result.stdout
    assert "README.md:3: broken link 'docs/missing.md': no such file" in lines
    assert "README.md:5: broken link 'docs/ok.md#nowhere': no heading #nowhere in ok.md" in lines
    assert "README.md:7: broken link 'docs/also-missing.png': no such file" in lines
    assert any(line.startswith("docs/ok.md:3: broken link '../img/none.png'") for line in lines)
    assert any(line.startswith("docs/huge.md:1: 201 kB, over the 200 kB limit") for line in lines)
    assert "5 problems" in result.stderr
