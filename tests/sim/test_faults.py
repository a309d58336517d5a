"""Faults rendered into simulated frames (blurcalib/sim/faults.py) and the built-in dataset's
frames (blurcalib/sim/showcase.py): what each fault changes, and the exact set of blocks it
touches."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from blurcalib.sim.faults import (
    FOOTPRINT_TOLERANCE,
    Defocus,
    Finger,
    Glare,
    apply_faults,
    block_quads,
    fault_from_dict,
    fault_to_dict,
    touched_blocks,
)
from blurcalib.sim.showcase import PASS_FRAMES, SQUARE_PX, showcase_camera, showcase_frames
from blurcalib.target.pattern import layout_pattern

SHAPE = (120, 200)


def _grid_quads(side: int = 20) -> np.ndarray:
    """Squares of ``side`` px tiling the image, row by row."""
    quads = []
    for y in range(0, SHAPE[0] - side + 1, side):
        for x in range(0, SHAPE[1] - side + 1, side):
            quads.append([[x, y], [x + side - 1, y], [x + side - 1, y + side - 1], [x, y + side - 1]])
    return np.asarray(quads, dtype=np.float64)


@pytest.mark.parametrize("fault", [Glare((100.0, 60.0), 25.0, 0.8), Finger((0.0, 0.0), (60.0, 40.0), 10.0),
                                   Defocus((50.0, 70.0), 30.0, 3.0)])
def test_a_fault_changes_only_its_footprint_and_touches_the_blocks_that_meet_it(fault) -> None:
    rng = np.random.default_rng(0)
    irradiance = rng.uniform(0.0, 1.0, SHAPE).astype(np.float32)
    out = apply_faults(irradiance, [fault])
    footprint = fault.footprint(SHAPE)
    assert footprint.any() and not footprint.all()
    change = np.abs(out - irradiance)
    if not isinstance(fault, Defocus):  # outside, less than the footprint's tolerance
        assert change[~footprint].max() <= FOOTPRINT_TOLERANCE + 1e-6
    else:  # the blur reads up to three sigmas beyond its region's edge
        near = cv2.dilate(footprint.astype(np.uint8), np.ones((19, 19), np.uint8)).astype(bool)
        assert change[~near].max() == 0
    assert (change[footprint] > 1e-6).mean() > 0.5
    quads = _grid_quads()
    touched = touched_blocks(footprint, quads)
    for quad, hit in zip(quads, touched, strict=True):
        x0, y0 = quad.min(axis=0).astype(int)
        x1, y1 = quad.max(axis=0).astype(int)
        assert hit == bool(footprint[y0:y1 + 1, x0:x1 + 1].any())
    wider = touched_blocks(footprint, quads, margin_px=21.0)  # a whole block further out
    assert wider.sum() > touched.sum() and np.all(wider[touched])
    assert fault_from_dict(fault_to_dict(fault)) == fault


def test_glare_adds_light_that_the_sensor_clips_and_a_finger_hides_the_target() -> None:
    flat = np.full(SHAPE, 1.0, np.float32)
    glare = Glare((100.0, 60.0), 25.0, 0.8, softness=4.0)
    assert apply_faults(flat, [glare])[60, 100] == pytest.approx(1.8)
    finger = Finger((0.0, 60.0), (100.0, 60.0), 12.0, level=0.6)
    hidden = apply_faults(flat, [finger])
    assert hidden[60, 50] == pytest.approx(0.6) and hidden[10, 50] == 1.0


def test_the_built_in_pass_is_slow_enough_to_seed_frames_from_their_neighbours() -> None:
    """The hand-held pass moves the tag by well under half a square from frame to frame (a
    neighbour's seed grows onto the right stars only then); each fault is named in its frame's
    file name; the thumb of the tag-hidden frame covers the tag's centre."""
    pattern, camera = layout_pattern(), showcase_camera()
    frames = showcase_frames(pattern, camera)
    assert len(frames) >= 12 and len({f.name for f in frames}) == len(frames)
    names = " ".join(f.name for f in frames)
    for fault in ("glare", "finger", "defocus", "grazing", "tag-hidden", "heavy-blur"):
        assert fault in names
    tag = pattern.apriltags[0].feature_box
    centre = np.array([[(tag[0] + tag[2]) / 2 * pattern.square_length_m,
                        (tag[1] + tag[3]) / 2 * pattern.square_length_m, 0.0]])
    passing = [f for f in frames if f.kind == "blurry"]
    assert len(passing) == PASS_FRAMES
    at = np.stack([camera.project(f.pose.transform(centre))[0] for f in passing])
    steps = np.linalg.norm(np.diff(at, axis=0), axis=1) / SQUARE_PX
    assert steps.max() < 0.5
    hidden = next(f for f in passing if "tag-hidden" in f.name)
    assert hidden.faults[0].footprint((camera.model.height, camera.model.width))[
        tuple(np.round(at[passing.index(hidden)][::-1]).astype(int))]
    quads = block_quads(pattern, camera, hidden.pose)
    assert np.isfinite(quads).all()
