"""The whole calibration pipeline: extract, calibrate the sharp set, filter, align globally.

``run_pipeline`` is what ``blurcalib calibrate`` runs:

1. feature extraction of the sharp frames (small PSF window) and the blurry frames (17 x 17),
   resumable, into ``OUT/sharp/`` and ``OUT/blurry/`` (:mod:`blurcalib.extract`);
2. Brown-Conrady calibration of the sharp set together with the target points
   (:mod:`blurcalib.calibrate`), saved in ``OUT/calibration/``;
3. per blurry frame, the optional blur pre-filter (off by default; the paper's 3.8 px is
   ``QualitySettings(min_sigma_major=3.8)``) and the BE / loss / connectivity filter on the saved
   block figures (:mod:`blurcalib.quality`);
4. per blurry frame, global alignment to the calibrated camera (``eq:global_align``, Huber
   loss; a global translation by default, the bilinear bias field ``eq:bilinear_bias`` or the
   four quadrants on request; :mod:`blurcalib.global_alignment`),
   with the orientation filter flagging frames seen nearly frontally;
5. outputs: ``OUT/features.csv`` (sharp features and aligned blurry features, flagged),
   ``OUT/features.bin`` (the reference tool's format, pixel-corner convention),
   ``OUT/frames.csv`` (per-frame status), ``OUT/report.json`` and figures (the
   reprojection-error direction image, per-frame errors).

Frame statuses (``frames.csv``, one row per input frame, sharp and blurry): ``used`` marks every
frame whose features enter the outputs unflagged (a sharp frame: the sharp-set calibration; a
blurry frame: the global alignment and ``features.bin``). Every other status comes with its
reason: the extraction's own (``not_seeded``, ``no_blocks``, ``unreadable``, ``failed``),
``too_few_features`` (a sharp frame left out of the calibration), ``low_blur`` (the optional
pre-filter), ``too_few_blocks`` (after the block filter) or ``ill_conditioned`` (seen nearly
frontally: its global translation is ill-conditioned, its features are flagged ``filtered_out``).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from blurcalib.calibrate import Calibration, calibrate_sharp, save_calibration
from blurcalib.extract import ExtractSettings, extract_to_folder, frame_names
from blurcalib.fileio import atomic_path, atomic_write_csv, atomic_write_text, ensure_writable_dir
from blurcalib.global_alignment import align_global, grid_coordinates, loss_weights
from blurcalib.pattern import StarPattern
from blurcalib.quality import QualitySettings, filter_frame
from blurcalib.refformat import to_ref_dataset, write_ref_dataset
from blurcalib.report import error_direction_image, save_frame_error_plot
from blurcalib.results import (
    FeatureFlags,
    FeatureTable,
    read_block_table,
    read_feature_table,
    write_features,
)


class PipelineError(RuntimeError):
    """Nothing useful can be produced; the message says which frames and which step."""


@dataclass(frozen=True)
class PipelineSettings:
    """Settings of :func:`run_pipeline`.

    Attributes:
        quality: the block filter and the blur pre-filter.
        loss: robust loss of the global alignment (``huber``, ``mean``, ``median``).
        bias: bias model of the global alignment (``translation``, ``bilinear``, ``quadrants``).
            ``translation`` by default: the features are PSF-centroid positions without the
            drift the paper's bilinear field compensates, and on simulated data the bilinear
            field also absorbs part of the true lens's non-parametric deviation (aligned
            blurry features 0.037 px against the true camera with ``translation``, 0.068 px
            with ``bilinear``; docs/pipeline.md).
        angle_threshold: frames whose optical axis is within this angle (rad) of the target
            normal are flagged (translation ill-conditioned).
        blurry_kernel: PSF window of blurry frames (px, odd).
        local_alignment: use the local-alignment translations for blurry frames.
        workers: frames extracted in parallel.
    """

    quality: QualitySettings = field(default_factory=QualitySettings)
    loss: str = "huber"
    bias: str = "translation"
    angle_threshold: float = math.pi / 10
    blurry_kernel: int = 17
    local_alignment: bool = False
    workers: int = 1


@dataclass
class PipelineReport:
    """What :func:`run_pipeline` did (also written as ``report.json``): ``frames`` one row per
    input frame (see the module docstring), ``counts`` frames per status of each kind
    (``{"sharp": {...}, "blurry": {...}}``)."""

    calibration: dict
    frames: list[dict]
    outputs: dict[str, str]
    counts: dict[str, dict[str, int]]
    settings: dict

    def to_dict(self) -> dict:
        return asdict(self)


def image_size_of(path: Path) -> tuple[int, int] | None:
    """``(width, height)`` of an image file, or None when it cannot be read."""
    data = np.fromfile(str(path), dtype=np.uint8) if path.is_file() else np.zeros(0, np.uint8)
    if data.size == 0:
        return None
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    return None if img is None else (int(img.shape[1]), int(img.shape[0]))


def _check_sizes(sharp: Sequence[Path], blurry: Sequence[Path]) -> tuple[int, int]:
    sizes = [image_size_of(p) for p in sharp]
    known = [s for s in sizes if s is not None]
    if not known:
        raise PipelineError("none of the sharp frames can be read")
    size = max(set(known), key=known.count)
    other = [(p, s) for p, s in zip(list(sharp) + list(blurry),
                                    sizes + [image_size_of(p) for p in blurry], strict=True)
             if s is not None and s != size]
    if other:
        listed = ", ".join(f"{p} ({s[0]}x{s[1]})" for p, s in other[:5])
        more = f" and {len(other) - 5} more" if len(other) > 5 else ""
        raise PipelineError(f"frames of another resolution than the sharp set's {size[0]}x{size[1]}: "
                            f"{listed}{more}")
    return size


def run_pipeline(sharp: Sequence[Path], blurry: Sequence[Path], pattern: StarPattern,
                 out_dir: str | os.PathLike, settings: PipelineSettings | None = None,
                 progress: Callable[[str, int, int, dict], None] | None = None) -> PipelineReport:
    """Run the whole pipeline (see the module docstring); partial results are kept on error.

    Args:
        sharp, blurry: frame files.
        pattern: the target.
        out_dir: output folder (re-running resumes the extraction).
        settings: pipeline settings.
        progress: ``progress(stage, done, total, row)`` during extraction.
    Raises:
        PipelineError: unusable input (no readable sharp frame, mixed resolutions, too few
            usable sharp frames, no tag found in any frame, no blurry frame surviving).
    """
    from blurcalib.calibrate import CalibrationError
    from blurcalib.deconv import DeconvSettings

    s = settings or PipelineSettings()
    out = ensure_writable_dir(out_dir)
    size = _check_sizes(sharp, blurry)

    def stage(name: str) -> Callable[[int, int, dict], None] | None:
        if progress is None:
            return None
        return lambda done, total, row: progress(name, done, total, row)

    all_names = frame_names(list(sharp) + list(blurry))
    sharp_names, names = all_names[:len(sharp)], all_names[len(sharp):]
    sharp_run = extract_to_folder(sharp, pattern, out / "sharp", ExtractSettings.sharp(),
                                  workers=s.workers, progress=stage("sharp"), expected_size=size,
                                  names=sharp_names)
    blurry_settings = ExtractSettings(deconv=DeconvSettings(kernel_size=s.blurry_kernel),
                                      local_alignment=s.local_alignment)
    blurry_run = extract_to_folder(blurry, pattern, out / "blurry", blurry_settings,
                                   workers=s.workers, progress=stage("blurry"), expected_size=size,
                                   names=names)
    seeded = [r for r in sharp_run.frames + blurry_run.frames if r["status"] != "not_seeded"]
    if not any(r["status"] == "ok" for r in seeded):
        raise PipelineError("no AprilTag of the pattern was found in any frame: does the pattern "
                            "YAML match the target in the frames?")
    sharp_features = read_feature_table(out / "sharp" / "features.csv")
    try:
        calibration = calibrate_sharp(sharp_features, pattern, size)
    except CalibrationError as exc:
        bad = [f"{r['frame']} ({r['status']})" for r in sharp_run.frames if r["status"] != "ok"]
        hint = f"; sharp frames without features: {', '.join(bad[:10])}" if bad else ""
        raise PipelineError(f"sharp-set calibration: {exc}{hint}") from None
    save_calibration(out / "calibration", calibration)

    sharp_rows = [_sharp_row(r, calibration) for r in sharp_run.frames]
    left_out = np.isin(sharp_features.frame, [r["frame"] for r in sharp_rows
                                              if r["status"] != "used"])
    sharp_features.flags[left_out] |= int(FeatureFlags.FILTERED_OUT)
    blocks = read_block_table(out / "blurry")
    extracted = {r["frame"]: r for r in blurry_run.frames}
    rows, aligned, residuals = [], [], []
    for name in names:
        row, table, res = _align_frame(name, extracted.get(name, {}), blocks, pattern,
                                       calibration, size, s)
        rows.append(row)
        if table is not None:
            aligned.append(table)
            residuals.append(res)
    usable = [r for r in rows if r["status"] == "used"]
    rows = sharp_rows + rows
    outputs = _write_outputs(out, pattern, size, sharp_features, aligned, residuals, rows,
                             calibration)
    counts: dict[str, dict[str, int]] = {"sharp": {}, "blurry": {}}
    for r in rows:
        counts[r["kind"]][r["status"]] = counts[r["kind"]].get(r["status"], 0) + 1
    report = PipelineReport(calibration={k: v for k, v in calibration.to_dict().items()
                                         if k in ("camera", "median_error_px", "rms_error_px",
                                                  "num_frames", "num_observations")},
                            frames=rows, outputs={k: str(v) for k, v in outputs.items()},
                            counts=counts,
                            settings={"quality": asdict(s.quality), "loss": s.loss, "bias": s.bias,
                                      "angle_threshold": s.angle_threshold,
                                      "blurry_kernel": s.blurry_kernel,
                                      "local_alignment": s.local_alignment})
    atomic_write_text(out / "report.json", json.dumps(report.to_dict(), indent=2, default=str))
    if blurry and not usable:
        raise PipelineError(f"no blurry frame survived the filters ({counts['blurry']}); the sharp-set "
                            f"calibration and all features are kept in {out}")
    return report


def _extraction_row(extracted: dict, kind: str) -> dict:
    """The start of a frame's row from its extraction summary; not-ok extractions keep their
    status and message as the row's status and reason."""
    row = {"frame": extracted["frame"], "kind": kind, "extraction": extracted.get("status", ""),
           "seeded_by": extracted.get("seeded_by", ""), "features": extracted.get("features", 0)}
    if row["extraction"] != "ok":
        row["status"] = row["extraction"] or "failed"
        row["reason"] = extracted.get("message") or f"extraction ended with {row['status']!r}"
    return row


def _sharp_row(extracted: dict, calibration: Calibration) -> dict:
    """A sharp frame's row: ``used`` when it entered the sharp-set calibration."""
    row = _extraction_row(extracted, "sharp")
    if "status" in row:
        return row
    errors = calibration.frame_errors().get(row["frame"])
    if errors is None:
        row.update(status="too_few_features",
                   reason=f"{row['features']} features: too few for the sharp-set calibration "
                           f"(its features are flagged filtered_out)")
    else:
        row.update(status="used", reason="",
                   calibration_median_error=round(errors["median_error_px"] or float("nan"), 4))
    return row


def _align_frame(name: str, extracted: dict, blocks, pattern: StarPattern, calibration: Calibration,
                 size: tuple[int, int], s: PipelineSettings
                 ) -> tuple[dict, FeatureTable | None, np.ndarray | None]:
    row = _extraction_row({"frame": name, **extracted}, "blurry")
    if "status" in row:
        return row, None, None
    sel = np.flatnonzero(blocks.frame == name)
    b = blocks.select(sel)
    centre = b.H[:, :2, 2] / b.H[:, 2:, 2]
    filt = filter_frame(b.fx, b.fy, centre, b.status, b.loss, b.boundary_energy, b.sigma_major,
                        size, s.quality)
    row.update(blocks=len(sel), kept=int(filt.kept.sum()),
               centre_sigma_major=round(filt.centre_sigma_major, 3), filter_counts=filt.counts())
    if not filt.frame_ok:
        row["status"] = "low_blur"
        row["reason"] = (f"centre median sigma_major {filt.centre_sigma_major:.2f} px < "
                          f"{s.quality.min_sigma_major} px")
        return row, None, None
    if filt.kept.sum() < 12:
        row["status"] = "too_few_blocks"
        row["reason"] = f"{int(filt.kept.sum())} blocks survive the BE/loss/connectivity filter"
        return row, None, None
    k = np.flatnonzero(filt.kept)
    ids = b.feature_id[k]
    points = calibration.points[ids]
    nominal = pattern.points_3d(ids)
    points = np.where(np.isfinite(points), points, nominal)
    grid = grid_coordinates(pattern, np.stack([b.fx[k], b.fy[k]], axis=1))
    ga = align_global(calibration.camera, points, centre[k], loss_weights(b.loss[k]), grid,
                      loss=s.loss, bias=s.bias, angle_threshold=s.angle_threshold)
    flags = FeatureFlags.STAR_CENTRE | FeatureFlags.BLURRY_FRAME | FeatureFlags.GLOBALLY_ALIGNED
    if s.local_alignment:
        flags |= FeatureFlags.LOCALLY_ALIGNED
    if ga.ill_conditioned:
        flags |= FeatureFlags.FILTERED_OUT
    L = pattern.square_length_m
    n = len(k)
    table = FeatureTable(frame=np.array([name] * n, dtype=object), feature_id=ids.astype(np.int64),
                         fx=b.fx[k].astype(np.int64), fy=b.fy[k].astype(np.int64),
                         X=b.fx[k] * L, Y=b.fy[k] * L, x=ga.corrected[:, 0], y=ga.corrected[:, 1],
                         weight=1.0 / (1.0 + b.loss[k]),
                         flags=np.full(n, int(flags), dtype=np.int64))
    row.update(status="ill_conditioned" if ga.ill_conditioned else "used", reason="",
               median_error=round(ga.median_error, 4), mean_error=round(ga.mean_error, 4),
               angle_deg=round(math.degrees(ga.angle_to_normal), 2),
               translation=[round(float(v), 4) for v in ga.translation])
    if ga.ill_conditioned:
        row["reason"] = (f"optical axis {math.degrees(ga.angle_to_normal):.1f} deg from the "
                          f"target normal: translation ill-conditioned, features flagged")
    return row, table, ga.residuals


def _write_outputs(out: Path, pattern: StarPattern, size: tuple[int, int],
                   sharp_features: FeatureTable, aligned: list[FeatureTable],
                   residuals: list[np.ndarray], rows: list[dict], calibration: Calibration
                   ) -> dict[str, Path]:
    tables = [sharp_features, *aligned]
    features = FeatureTable.concat(tables)
    outputs = {"features": write_features(out / "features.csv", features)}
    frames = sorted(set(features.frame.tolist()))
    index = {f: i for i, f in enumerate(frames)}
    usable = (features.flags & int(FeatureFlags.FILTERED_OUT)) == 0
    ref = to_ref_dataset(size, frames, np.array([index[f] for f in features.frame[usable]]),
                         features.feature_id[usable], features.x[usable], features.y[usable],
                         pattern)
    outputs["reference_features"] = write_ref_dataset(out / "features.bin", ref)
    cols = ["frame", "kind", "status", "reason", "extraction", "seeded_by", "features", "blocks",
            "kept", "centre_sigma_major", "median_error", "mean_error", "angle_deg"]
    outputs["frames"] = atomic_write_csv(out / "frames.csv", cols,
                                         [[r.get(c, "") for c in cols] for r in rows])
    # Figures: reprojection-error directions of the aligned blurry features and of the sharp set.
    if aligned:
        xy = np.concatenate([np.stack([t.x, t.y], axis=1) for t in aligned])
        img = error_direction_image(xy, np.concatenate(residuals), size)
        with atomic_path(out / "error_directions_blurry.png") as tmp:
            cv2.imwrite(str(tmp), img)
        outputs["error_directions_blurry"] = out / "error_directions_blurry.png"
    img = error_direction_image(calibration.observed, calibration.residuals, size)
    with atomic_path(out / "error_directions_sharp.png") as tmp:
        cv2.imwrite(str(tmp), img)
    outputs["error_directions_sharp"] = out / "error_directions_sharp.png"
    blurry_rows = [r for r in rows if r["kind"] == "blurry"]
    outputs["frame_errors"] = save_frame_error_plot(out / "frame_errors.png", blurry_rows,
                                                    calibration.frame_errors())
    return outputs
