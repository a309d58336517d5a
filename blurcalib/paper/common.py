"""What the experiments share: the simulated scene, the settings of simulated blurry frames,
extraction of simulated frames, JSON numbers and the command-line scaffolding of ``blurcalib
experiment NAME`` (options read into settings dataclasses, defaults from their fields).

Units: pixels in the OpenCV convention (top-left pixel centre at ``(0, 0)``).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from blurcalib.deconv.settings import DeconvSettings
from blurcalib.extract.frame import ExtractSettings, FrameResult, extract_frame
from blurcalib.growth.ledger import Growth
from blurcalib.growth.settings import GrowSettings
from blurcalib.growth.window import WindowPolicy
from blurcalib.io.atomic import OutputError
from blurcalib.io.record import FrameStatus
from blurcalib.runs.runtime import check_device
from blurcalib.sim.synth import Simulator, SynthConfig
from blurcalib.sim.truth import FrameTruth, TrueCamera, d435i_like_camera

DEFAULT_OUT = Path("out") / "experiments"
"""Default output folder of every experiment."""
S = TypeVar("S")


# ------------------------------------------------------------------------------ the scene
def experiment_camera(seed: int = 0, scale: float = 0.5, deviation_px: float = 0.01) -> TrueCamera:
    """The simulated camera of the real-world experiments.

    :func:`blurcalib.sim.truth.d435i_like_camera` (1280 x 720 px) resized by ``scale``
    (:meth:`BrownConrady.scaled`), with its smooth non-parametric deviation of ``deviation_px``
    px peak in the resized image (the paper's sharp-set calibration fits its camera to about
    0.03 px, so the deviation is kept small, as in the alignment experiment).
    """
    full = d435i_like_camera(seed, deviation_px)
    return TrueCamera(full.model.scaled(scale), full.waves)


def experiment_simulator(sharp: int, blurry: int, blur_px: tuple[float, float], seed: int,
                         scale: float, deviation_px: float) -> Simulator:
    """``sharp`` sharp frames (indices first) then ``blurry`` blurry ones, median blur length
    uniform in ``blur_px`` (px), seen by :func:`experiment_camera`."""
    config = SynthConfig(sharp=sharp, blurry=blurry, blur_min_px=blur_px[0], blur_max_px=blur_px[1],
                         seed=seed)
    return Simulator(config, camera=experiment_camera(seed, scale, deviation_px))


def extract_settings(kernel_size: int = WindowPolicy.start, max_blocks: int = 5000,
                     device: str = "cpu") -> ExtractSettings:
    """Blurry-frame extraction settings: ``K x K`` PSF window (px), growth capped at about
    ``max_blocks`` attempted blocks, solve on the torch ``device``."""
    return ExtractSettings(window=WindowPolicy(start=kernel_size), deconv=DeconvSettings(device=device),
                           grow=GrowSettings(max_blocks=max_blocks))


@dataclass(frozen=True)
class Option:
    """One option of ``blurcalib experiment NAME``, read into the field ``field`` of the
    experiment's settings dataclass; its default and type are the field's."""

    flag: str
    field: str
    help: str


@dataclass(frozen=True)
class BlurryFrameSettings:
    """The simulated blurry frames of an experiment and their extraction: the base of the
    settings of the experiments that extract them.

    Attributes:
        blur_min_px, blur_max_px: range of a frame's median blur path length (px).
        scale: image scale relative to the 1280 x 720 D435I-like camera.
        deviation_px: peak non-parametric lens deviation (px).
        kernel_size: ``K``, the blurry frames' PSF window (px, odd; the paper's 17).
        max_blocks: growth stops after about this many attempted blocks per frame.
        device: torch device of the deconvolution.
    """

    blur_min_px: float = 2.0
    blur_max_px: float = 20.0
    scale: float = 0.5
    deviation_px: float = 0.01
    kernel_size: int = WindowPolicy.start
    max_blocks: int = 5000
    device: str = "cpu"

    def __post_init__(self) -> None:
        if not 0 <= self.blur_min_px <= self.blur_max_px:
            raise ValueError(f"need 0 <= blur_min_px <= blur_max_px, got {self.blur_min_px}, "
                             f"{self.blur_max_px}")
        if not 0.1 <= self.scale <= 2.0:
            raise ValueError(f"scale must be in [0.1, 2], got {self.scale}")
        if self.kernel_size < 5 or self.kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd and >= 5, got {self.kernel_size}")
        if self.deviation_px < 0 or self.max_blocks < 1:
            raise ValueError(f"deviation_px must be >= 0 and max_blocks >= 1, got {self.deviation_px}, "
                             f"{self.max_blocks}")
        check_device(self.device)

    def simulator(self, sharp: int, blurry: int, seed: int) -> Simulator:
        """:func:`experiment_simulator` of ``sharp`` sharp and ``blurry`` blurry frames."""
        return experiment_simulator(sharp, blurry, (self.blur_min_px, self.blur_max_px), seed, self.scale,
                                    self.deviation_px)

    def extraction(self) -> ExtractSettings:
        """The blurry frames' :func:`extract_settings`."""
        return extract_settings(self.kernel_size, self.max_blocks, self.device)


BLURRY_FRAME_OPTIONS: tuple[Option, ...] = (
    Option("--blur-min", "blur_min_px", "smallest median blur length of a blurry frame, px"),
    Option("--blur-max", "blur_max_px", "largest median blur length of a blurry frame, px"),
    Option("--scale", "scale", "image scale relative to the 1280x720 D435I-like camera"),
    Option("--kernel", "kernel_size", "PSF window side of the blurry frames, px"),
    Option("--max-blocks", "max_blocks", "stop growing a frame after about this many blocks"),
    Option("--device", "device", "torch device of the deconvolution"))
"""The options of :class:`BlurryFrameSettings`."""


# ------------------------------------------------------------------------- extracted frames
@dataclass(eq=False)
class ExtractedFrame:
    """One simulated blurry frame and its extraction (kept in memory, extracted once).

    Attributes:
        name: the frame's name (``blurry/0003.png``).
        truth: its ground truth.
        result: :func:`blurcalib.extract.frame.extract_frame`'s result (``growth.fit`` holds every
            attempted block's figures, ``local`` the local alignment of the accepted ones).
        image_size: ``(width, height)`` px.
        seconds: render and extraction time (s).
    """

    name: str
    truth: FrameTruth = field(repr=False)
    result: FrameResult = field(repr=False)
    image_size: tuple[int, int]
    seconds: float

    @property
    def ok(self) -> bool:
        """Extraction succeeded with at least one accepted block."""
        return self.result.status is FrameStatus.OK and self.result.growth is not None

    @property
    def growth(self) -> Growth:
        """The growth of a frame whose extraction reached it (every frame that is :attr:`ok`)."""
        assert self.result.growth is not None, f"{self.name}: extraction ended before the growth"
        return self.result.growth

    def summary(self) -> str:
        """One progress line: status, block counts, true median blur, time."""
        growth = self.result.growth
        blocks = 0 if growth is None else len(growth.feature_id)
        accepted = 0 if growth is None else int(growth.accepted.sum())
        blur = float(np.median(self.truth.blur_length[self.truth.visible]))
        return (f"  {self.name}: {self.result.status.value}, {accepted}/{blocks} blocks accepted, "
                f"median blur {blur:.1f} px, {self.seconds:.1f} s")


def extract_frames(sim: Simulator, indices: Sequence[int], settings: ExtractSettings,
                   progress: Callable[[str], None] | None = None) -> list[ExtractedFrame]:
    """Render and extract the simulator's frames ``indices`` once each.

    A frame whose extraction raises (ValueError, RuntimeError, LinAlgError) is kept with status
    ``failed`` and its message, as :func:`blurcalib.runs.folder.extract_to_folder` records it.
    """
    out = []
    size = (sim.camera.model.width, sim.camera.model.height)
    for index in indices:
        t0 = time.perf_counter()
        frame = sim.frame(index)
        name = frame.truth.name
        try:
            result = extract_frame(frame.image.astype(np.float32), sim.pattern, name, settings)
        except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
            result = FrameResult(name, FrameStatus.FAILED, f"{type(exc).__name__}: {exc}")
        extracted = ExtractedFrame(name, frame.truth, result, size, time.perf_counter() - t0)
        out.append(extracted)
        if progress is not None:
            progress(extracted.summary())
    return out


# ------------------------------------------------------------------------------- outputs
def finite(v: float | None) -> float | None:
    """``v`` rounded to 6 decimals for JSON, or None when missing or not finite."""
    return round(float(v), 6) if v is not None and math.isfinite(v) else None


def experiment_parser(name: str, description: str, outputs: str, settings: type | None = None,
                      options: Sequence[Option] = ()) -> argparse.ArgumentParser:
    """The parser of ``blurcalib experiment NAME``: ``--out``, ``--seed`` and ``options``, each
    with the default of its field of the ``settings`` dataclass."""
    parser = argparse.ArgumentParser(prog=f"blurcalib experiment {name}", description=description)
    parser.add_argument("--out", default=str(DEFAULT_OUT),
                        help=f"output folder for {outputs} (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    for o in options:
        default = getattr(settings, o.field)
        parser.add_argument(o.flag, dest=o.field, metavar=o.flag[2:].replace("-", "_").upper(),
                            type=type(default), default=default, help=f"{o.help} (default %(default)s)")
    return parser


def settings_from(settings: type[S], options: Sequence[Option], args: argparse.Namespace, **fixed: Any) -> S:
    """The ``settings`` dataclass of the parsed ``options``, with the ``fixed`` fields."""
    return settings(**{o.field: getattr(args, o.field) for o in options}, **fixed)


def run_experiment_cli(parser: argparse.ArgumentParser, argv: Sequence[str] | None,
                       run: Callable[[argparse.Namespace], Sequence[Path]]) -> int:
    """Parse ``argv``, call ``run(args)`` (which prints its tables and returns the files it
    wrote) and list the outputs.

    Returns 0, or 2 with ``blurcalib: error: ...`` on stderr for bad options (``ValueError``)
    or an unwritable output folder (:class:`OutputError`).
    """
    args = parser.parse_args(argv)
    try:
        paths = run(args)
    except (OutputError, ValueError) as exc:
        print(f"blurcalib: error: {exc}", file=sys.stderr)
        return 2
    print("  outputs: " + ", ".join(str(p) for p in paths))
    return 0
