"""Thread policy and device checks of blurcalib.runs.runtime, and their CLI errors."""

from __future__ import annotations

import ctypes
import platform

import cv2
import numpy as np
import pytest
import torch

from blurcalib.cli import main
from blurcalib.runs.runtime import (
    DeviceError,
    available_cores,
    check_device,
    compute_threads,
    configure_threads,
    default_workers,
    keep_large_allocations,
)
from tests.conftest import FIXTURE_YAML


def test_configure_threads_sets_torch_threads() -> None:
    before = torch.get_num_threads()
    try:
        assert configure_threads(2) == 2 and torch.get_num_threads() == 2
        assert configure_threads(None) == 1 and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    with pytest.raises(ValueError, match="threads must be >= 0"):
        configure_threads(-1)


def test_compute_threads_sets_them_inside_the_block_only() -> None:
    before = torch.get_num_threads()
    try:
        configure_threads(1)
        with compute_threads(3) as n:
            assert n == 3 and torch.get_num_threads() == 3 and cv2.getNumThreads() == 1
        assert torch.get_num_threads() == 1
        with pytest.raises(RuntimeError, match="inside"), compute_threads(2):
            raise RuntimeError("inside")
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_default_workers_one_per_core_at_most_one_per_frame() -> None:
    cores = available_cores()
    assert default_workers(1) == 1
    assert default_workers(10_000) == cores
    assert default_workers(0) == 1


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
                 "fordblks", "keepcost")]


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt only")
def test_large_allocations_stay_on_the_heap() -> None:
    """After the setting, a 64 MiB tensor (above glibc's largest mmap threshold, as the bundle
    adjustment's matrices) is not mapped on its own, and its memory stays in the heap for the
    next one when freed instead of going back to the system (glibc's mallinfo2: mapped bytes,
    free heap bytes)."""
    libc = ctypes.CDLL("libc.so.6")
    if not hasattr(libc, "mallinfo2"):
        pytest.skip("glibc older than 2.33 has no mallinfo2")
    libc.mallinfo2.restype = _MallInfo2
    assert keep_large_allocations()
    mapped = libc.mallinfo2().hblkhd
    block = torch.ones(8 << 20, dtype=torch.float64)  # 64 MiB
    assert libc.mallinfo2().hblkhd == mapped
    del block
    info = libc.mallinfo2()
    assert info.hblkhd == mapped and info.fordblks >= 64 << 20


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_without_cuda_is_a_one_line_error(tmp_path, capsys) -> None:
    assert check_device("cpu") == "cpu"
    with pytest.raises(DeviceError, match="CUDA is not available"):
        check_device("cuda")
    with pytest.raises(DeviceError, match="not a torch device"):
        check_device("gpu0")
    frame = tmp_path / "f.png"
    cv2.imwrite(str(frame), np.full((40, 40), 128, np.uint8))
    code = main(["extract", str(frame), "--pattern", str(FIXTURE_YAML), "--out", str(tmp_path / "o"),
                 "--device", "cuda"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "CUDA is not available" in err[0]
    assert not (tmp_path / "o").exists()


def _after_import(given: dict[str, str], cleared: str, checked: str, names: list[str]) -> str:
    """The variables ``names`` printed by a fresh interpreter after ``import blurcalib``, in an
    environment without the variables starting ``cleared`` but with ``given``; it also asserts
    that the import left the module ``checked`` unloaded."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {k: v for k, v in os.environ.items() if not k.startswith(cleared)}
    env.update(given, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    code = (f"import os, sys, blurcalib; assert {checked!r} not in sys.modules; "
            f"print(*(os.environ[n] for n in {names!r}))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


@pytest.mark.parametrize(("given", "expected"), [({}, "PASSIVE"), ({"OMP_WAIT_POLICY": "ACTIVE"}, "ACTIVE")])
def test_openmp_threads_sleep_while_they_wait(given: dict[str, str], expected: str) -> None:
    """Importing blurcalib makes torch's OpenMP threads sleep at barriers (spinning threads took
    4 to 8 times the CPU of a frame on a busy machine), before torch reads the policy; a policy
    the user set is kept."""
    assert _after_import(given, "OMP_WAIT_POLICY", "torch", ["OMP_WAIT_POLICY"]) == expected


@pytest.mark.parametrize(("given", "expected"), [({}, "1 4"), ({"OPENBLAS_NUM_THREADS": "2"}, "2 4")])
def test_openblas_computes_with_one_thread(given: dict[str, str], expected: str) -> None:
    """Importing blurcalib gives NumPy's OpenBLAS one thread whose waits sleep at once (two
    spinning threads took a small Cholesky solve from 0.016 to 0.17 s on a busy machine), before
    NumPy loads OpenBLAS; threads the user set are kept."""
    names = ["OPENBLAS_NUM_THREADS", "OPENBLAS_THREAD_TIMEOUT"]
    assert _after_import(given, "OPENBLAS_", "numpy", names) == expected
