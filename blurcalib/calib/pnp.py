"""A frame's pose from its target points and their observations, for a camera of any field of view.

For the Brown-Conrady camera (:class:`blurcalib.camera.parametric.BrownConrady`) the pose is
OpenCV's: ``cv2.solvePnPRansac`` (SQPnP hypotheses) and ``cv2.solvePnPRefineLM``. For a camera of
the parametric family (:class:`blurcalib.camera.lens.ParametricCamera`) it is solved in viewing
directions, so that observations beyond 90 degrees off the axis count as any other:

1. each observation's unit ray ``v_i`` (:meth:`ParametricCamera.unproject`);
2. the target plane's homography in directions, ``v_i ~ H (X_i, Y_i, 1)``: each point gives the
   linear constraints ``[v_i]_x H p_i = 0`` (a direct linear transform on the sphere, no division
   by ``Z``); RANSAC over 4-point samples scores a hypothesis by the angle between ``v_i`` and
   ``H p_i`` (times the focal length: about px), the inliers give it again;
3. ``H = lambda [r1 r2 t]`` with ``lambda`` the sign that puts the points along their rays
   (``v_i . H p_i > 0``) and the mean length of ``h1, h2``; ``R`` the rotation nearest
   ``[r1 r2 r1 x r2]``;
4. Gauss-Newton with Huber weights on the reprojection error ``|pi(R P_i + t) - p_i|`` (px) with
   the analytic Jacobian (:func:`blurcalib.camera.lens.project_poses_camera`), Marquardt's damping
   (:func:`refine_pose`).

Pixels follow OpenCV (top-left pixel centre at ``(0, 0)``); poses map target to camera,
``X_cam = R X + t`` (m).
"""

from __future__ import annotations

import math
from typing import cast

import cv2
import numpy as np
from numpy.typing import ArrayLike

from blurcalib.camera.lens import ParametricCamera, project_poses_camera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.geometry.pose import Pose

__all__ = ["homography_pose", "plane_homography", "refine_pose", "solve_pose"]

RANSAC_SAMPLES = 200
"""4-point hypotheses of the homography in directions."""


def _normalised_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous plane points ``(N, 3)`` centred and scaled to unit mean distance, and the
    transform ``T (3, 3)`` that did it."""
    xy = points[:, :2]
    mean = xy.mean(axis=0)
    scale = math.sqrt(2.0) / max(float(np.mean(np.linalg.norm(xy - mean, axis=1))), 1e-12)
    T = np.array([[scale, 0.0, -scale * mean[0]], [0.0, scale, -scale * mean[1]], [0.0, 0.0, 1.0]])
    return np.column_stack([(xy - mean) * scale, np.ones(len(xy))]), T


def _dlt_rows(rays: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``(..., N, 3, 9)``: the rows of ``[v]_x H p = 0`` in ``H``'s 9 entries (row-major)."""
    zero = np.zeros_like(p)
    vx, vy, vz = rays[..., 0:1], rays[..., 1:2], rays[..., 2:3]
    r0 = np.concatenate([zero, -vz * p, vy * p], axis=-1)
    r1 = np.concatenate([vz * p, zero, -vx * p], axis=-1)
    r2 = np.concatenate([-vy * p, vx * p, zero], axis=-1)
    return np.stack([r0, r1, r2], axis=-2)


def plane_homography(rays: ArrayLike, points: ArrayLike) -> np.ndarray:
    """``H (3, 3)`` with ``rays_i ~ H (X_i, Y_i, 1)`` in least squares (module docstring, step 2)
    from unit rays ``(N, 3)`` and target points ``(N, 3)`` m (``Z`` ignored), ``N >= 4``; its sign
    puts the points along their rays."""
    v = np.asarray(rays, dtype=np.float64).reshape(-1, 3)
    p, T = _normalised_plane(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    Hn = np.linalg.svd(_dlt_rows(v, p).reshape(-1, 9))[2][-1].reshape(3, 3)
    sign = 1.0 if float(np.einsum("ij,nj,ni->", Hn, p, v)) >= 0 else -1.0
    return cast(np.ndarray, sign * Hn @ T)


def homography_pose(H: np.ndarray) -> Pose | None:
    """The pose ``[R | t]`` of a plane homography in directions ``H ~ [r1 r2 t]`` (positive
    scale: :func:`plane_homography`'s sign); None when ``H`` is degenerate."""
    h1, h2, h3 = H[:, 0], H[:, 1], H[:, 2]
    norm = 0.5 * (np.linalg.norm(h1) + np.linalg.norm(h2))
    if not norm > 0 or not np.all(np.isfinite(H)):
        return None
    r1, r2 = h1 / norm, h2 / norm
    U, _, Vt = np.linalg.svd(np.column_stack([r1, r2, np.cross(r1, r2)]))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return Pose(R, h3 / norm)


def _ransac_inliers(rays: np.ndarray, points: np.ndarray, threshold_rad: float, seed: int = 0) -> np.ndarray:
    """``(N,) bool``: the largest set of observations within ``threshold_rad`` of a 4-point
    homography in directions (module docstring, step 2)."""
    n = len(rays)
    if n <= 4:
        return np.ones(n, dtype=bool)
    rng = np.random.default_rng(seed)
    picks = np.stack([rng.choice(n, 4, replace=False) for _ in range(RANSAC_SAMPLES)])
    p, _ = _normalised_plane(points)
    A = _dlt_rows(rays[picks], p[picks]).reshape(RANSAC_SAMPLES, 12, 9)
    H = np.linalg.svd(A)[2][:, -1].reshape(-1, 3, 3)
    seen = np.einsum("kij,nj->kni", H, p)  # (K, N, 3)
    sign = np.sign(np.einsum("kmi,kmi->k", seen[np.arange(RANSAC_SAMPLES)[:, None], picks], rays[picks]))
    seen *= sign[:, None, None]
    cos = np.einsum("kni,ni->kn", seen, rays) / np.maximum(np.linalg.norm(seen, axis=2), 1e-300)
    inliers = np.arccos(np.clip(cos, -1.0, 1.0)) < threshold_rad
    return cast(np.ndarray, inliers[int(np.argmax(inliers.sum(axis=1)))])


def refine_pose(camera: ParametricCamera, pose: Pose, points: ArrayLike, observed: ArrayLike, *,
                huber_px: float = 1.0, iterations: int = 30, tol: float = 1e-12) -> Pose:
    """Gauss-Newton on ``sum rho(|pi(R P_i + t) - p_i|)`` (Huber at ``huber_px`` on the error norm,
    by iteratively reweighted least squares) over the pose's ``(rvec, tvec)``, with Marquardt's
    damping (x10 after a step that raises the cost, /10 after one that lowers it). Observations
    outside the camera's valid field carry no weight. Stops when a step moves no parameter by
    more than ``tol`` (rad, m) or no damping lowers the cost."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    obs = np.asarray(observed, dtype=np.float64).reshape(-1, 2)

    def evaluate(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        proj = project_poses_camera(camera, x[None, :3], x[None, 3:], P, jacobian=True)
        valid = camera.valid_directions(_camera_points(x, P))
        r = np.where(valid[:, None], proj.pixels - obs, 0.0)
        e = np.linalg.norm(r, axis=1)
        cost = float(np.sum(np.where(e <= huber_px, e * e, 2 * huber_px * e - huber_px**2)))
        assert proj.d_pose is not None  # asked for
        J = np.where(valid[:, None, None], proj.d_pose, 0.0)
        return r, J, cost

    x = np.r_[pose.rvec, pose.t]
    r, J, cost = evaluate(x)
    lam = 1e-6
    for _ in range(iterations):
        e = np.linalg.norm(r, axis=1)
        w = np.minimum(1.0, huber_px / np.maximum(e, 1e-300))
        H = np.einsum("n,nij,nik->jk", w, J, J)
        g = np.einsum("n,nij,ni->j", w, J, r)
        moved = False
        while lam < 1e12:
            try:
                step = -np.linalg.solve(H + lam * np.diag(np.maximum(np.diag(H), 1e-12)), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            r_new, J_new, cost_new = evaluate(x + step)
            if np.isfinite(cost_new) and cost_new <= cost:
                x, r, J, cost, lam, moved = x + step, r_new, J_new, cost_new, max(lam / 10.0, 1e-12), True
                break
            lam *= 10.0
        if not moved or np.abs(step).max() <= tol:
            break
    return Pose.from_rvec_tvec(x[:3], x[3:])


def _camera_points(x: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Camera-frame points ``R P + t`` ``(N, 3)`` of the pose ``x = (rvec, tvec)``."""
    R, _ = cv2.Rodrigues(np.ascontiguousarray(x[:3]))
    return cast(np.ndarray, P @ R.T + x[3:])


def solve_pose(camera: BrownConrady | ParametricCamera, points: ArrayLike, obs_xy: ArrayLike, *,
               ransac_px: float = 3.0) -> Pose:
    """Robust pose ``M = [R | t]`` of one frame from 3D-2D correspondences (module docstring).

    Brown-Conrady (:class:`BrownConrady`): ``cv2.solvePnPRansac`` (SQPnP hypotheses, inliers
    within ``ransac_px``) followed by ``cv2.solvePnPRefineLM`` on the inliers, minimising
    ``sum |pi_d(M, P_i) - p_i|^2``. A camera of the family: in viewing directions (any angle off
    the axis), the inliers within ``ransac_px`` of the homography's hypothesis refined by
    :func:`refine_pose`.

    Args:
        camera: the calibrated camera.
        points: ``(N, 3)`` target points (m), ``N >= 4``.
        obs_xy: ``(N, 2)`` observed pixels (OpenCV convention).
        ransac_px: inlier threshold (px).

    Raises:
        ValueError: fewer than 4 correspondences, mismatched shapes, or no pose found.
    """
    pts = np.asarray(points, dtype=np.float64)
    xy = np.asarray(obs_xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or xy.shape != (len(pts), 2):
        raise ValueError(f"need points (N, 3) and obs_xy (N, 2), got {pts.shape} and {xy.shape}")
    finite = np.isfinite(pts).all(axis=1) & np.isfinite(xy).all(axis=1)
    pts, xy = pts[finite], xy[finite]
    if len(pts) < 4:
        raise ValueError(f"solve_pose needs at least 4 finite correspondences, got {len(pts)}")
    if isinstance(camera, BrownConrady):
        return _opencv_pose(camera, pts, xy, ransac_px)
    rays = camera.unproject(xy)
    seen = np.all(np.isfinite(rays), axis=1)
    if seen.sum() < 4:
        raise ValueError(f"only {int(seen.sum())} of {len(pts)} observations have a ray in the camera's "
                         "field")
    pts, xy, rays = pts[seen], xy[seen], rays[seen]
    keep = _ransac_inliers(rays, pts, float(ransac_px) / camera.fx)
    if keep.sum() < 4:
        raise ValueError(f"no pose found for {len(pts)} correspondences within {ransac_px} px")
    pose = homography_pose(plane_homography(rays[keep], pts[keep]))
    if pose is None:
        raise ValueError(f"no pose found for {len(pts)} correspondences (degenerate homography)")
    pose = refine_pose(camera, pose, pts[keep], xy[keep])
    err = np.linalg.norm(project_poses_camera(camera, pose.rvec[None], pose.t[None], pts).pixels - xy, axis=1)
    keep = err <= ransac_px
    if keep.sum() < 4:
        raise ValueError(f"no pose found for {len(pts)} correspondences within {ransac_px} px")
    return refine_pose(camera, pose, pts[keep], xy[keep])


def _opencv_pose(camera: BrownConrady, pts: np.ndarray, xy: np.ndarray, ransac_px: float) -> Pose:
    """OpenCV's robust PnP with the Brown-Conrady camera (:func:`solve_pose`)."""
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(pts, xy, camera.K, camera.dist, iterationsCount=200,
                                                 reprojectionError=float(ransac_px), confidence=0.999,
                                                 flags=cv2.SOLVEPNP_SQPNP)
    if not ok or inliers is None or len(inliers) < 4:
        raise ValueError(f"no pose found for {len(pts)} correspondences within {ransac_px} px")
    keep = inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(pts[keep], xy[keep], camera.K, camera.dist, rvec, tvec)
    return Pose.from_rvec_tvec(rvec.ravel(), tvec.ravel())
