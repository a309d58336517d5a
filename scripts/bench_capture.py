"""One capture as it comes, printed: the demo's frames given split by hand, as one mixed set of
frames, and as an mp4 video, each calibrated and compared with the true camera.

    python scripts/bench_capture.py [--data out/demo/data] [--out out/bench_capture] [--workers 2]

Data: ``blurcalib demo``'s simulated dataset (20 sharp, 60 blurry frames; simulated with the
demo's defaults when ``--data`` holds none). Runs, each into its own folder under ``--out``
(resumable: a rerun reuses the extractions):

* ``split``: ``calibrate --sharp DATA/sharp --blurry DATA/blurry`` (the kinds given);
* ``mixed``: ``calibrate DATA/sharp DATA/blurry`` (every frame classified by its measured blur);
* ``video``: the 80 frames written as one mp4v video (25 fps), ``calibrate VIDEO.mp4``.

For each: frames used (sharp and blurry as classified), the generic camera's error against the
true camera (median over the image after the best-fit rotation, and its shape), the held-out
median, and the wall time. Targets: mixed within 10 % of split and >= 95 % of frames used;
video within 0.03 px of the truth and >= 90 % of frames used. The figures are also recorded as
JSON (``scripts/benchrecord.py``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import benchrecord
import cv2
import numpy as np

from blurcalib.camera.files import read_generic_yaml
from blurcalib.io.frames import list_frames, load_frame
from blurcalib.io.sources import frame_inputs
from blurcalib.pipeline.run import PipelineSettings, run_pipeline
from blurcalib.sim.evaluate import camera_accuracy
from blurcalib.sim.synth import SynthConfig, write_dataset
from blurcalib.sim.truth import GROUND_TRUTH_FILE, load_ground_truth
from blurcalib.target.pattern import load_pattern


def write_video(frames: list[Path], path: Path, fps: float = 25.0) -> Path:
    """The frames as one mp4v video (grey written as BGR)."""
    first = load_frame(frames[0])
    h, w = first.shape
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    for f in frames:
        grey = np.clip(load_frame(f), 0, 255).astype(np.uint8)
        writer.write(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=Path("out/demo/data"))
    parser.add_argument("--out", type=Path, default=Path("out/bench_capture"))
    parser.add_argument("--workers", type=int, default=2)
    benchrecord.add_option(parser)
    args = parser.parse_args()
    record = benchrecord.start(__file__, args)
    if not (args.data / GROUND_TRUTH_FILE).is_file():
        write_dataset(args.data, SynthConfig(), workers=args.workers)
    truth = load_ground_truth(args.data)
    pattern = load_pattern(args.data / "pattern.yaml")
    sharp, blurry = list_frames([args.data / "sharp"]), list_frames([args.data / "blurry"])
    args.out.mkdir(parents=True, exist_ok=True)
    video = args.out / "capture.mp4"
    if not video.is_file():
        write_video(sharp + blurry, video)
    settings = PipelineSettings(workers=args.workers)
    folders = frame_inputs([args.data / "sharp", args.data / "blurry"])
    runs = {"split": lambda out: run_pipeline(sharp, blurry, pattern, out, settings),
            "mixed": lambda out: run_pipeline([], [], pattern, out, settings, mixed=folders),
            "video": lambda out: run_pipeline([], [], pattern, out, settings, mixed=frame_inputs([video]))}
    results = {}
    for name, run in runs.items():
        t0 = time.perf_counter()
        report = run(args.out / name).to_dict()
        wall = time.perf_counter() - t0
        used = sum(r["status"] == "used" for r in report["frames"])
        kinds = {k: sum(r["status"] == "used" and r["kind"] == k for r in report["frames"])
                 for k in ("sharp", "blurry")}
        camera = read_generic_yaml(args.out / name / "calibration" / "intrinsics0.yaml")
        acc = camera_accuracy(truth.camera, camera)
        held = (report.get("validation") or {}).get("generic", {}).get("median_px")
        results[name] = acc.median
        print(f"{name}: {used} of {len(report['frames'])} frames used ({kinds['sharp']} sharp, "
              f"{kinds['blurry']} blurry); generic camera {acc.median:.4f} px from the truth (shape "
              f"{acc.shape_median:.4f} px); held-out median {held if held is None else f'{held:.4f}'} px; "
              f"{wall:.0f} s wall", flush=True)
        record.add(name, frames=len(report["frames"]), frames_used=used, sharp_used=kinds["sharp"],
                   blurry_used=kinds["blurry"], camera_error_px=acc.median, camera_shape_px=acc.shape_median,
                   held_out_median_px=held, wall_s=wall)
    split, mixed, vid = results["split"], results["mixed"], results["video"]
    print(f"mixed against split: {mixed / split - 1:+.1%} (target within 10 %); video {vid:.4f} px from the "
          f"truth (target <= 0.03 px)")
    record.add("comparison", mixed_over_split_pct=100 * (mixed / split - 1), video_error_px=vid)
    record.write()


if __name__ == "__main__":
    main()
