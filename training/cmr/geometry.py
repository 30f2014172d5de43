"""Geometry conventions, mirrored from the Rust crate's `src/geometry/`.

The Rust module is the reference; `fixtures/conventions.json` (written by the Rust tests) pins
both implementations. Frames: camera is OpenCV (x right, y down, z forward), the map frame is
z-up, and the estimated pose is camera_from_map (p_cam = R p_map + t), kept as 4x4 float64.
"""

from __future__ import annotations

import math

import numpy as np

MIN_DEPTH_M = 0.1
RR_MAX_ROTATION_DEG = 10.0
RR_MAX_TRANSLATION_M = 5.0
REWARD_WORSE, REWARD_SAME, REWARD_BETTER = -0.5, 0.0, 0.5


def _symmetric(unit: float, magnitudes: list[float]) -> np.ndarray:
    return np.array([-m * unit for m in reversed(magnitudes)] + [0.0] + [m * unit for m in magnitudes])


# Ascending steps; the middle index is the zero step. DoF order: yaw (deg), then the two
# translations (m); which axes they act along is the action frame (see "Actions" below).
ROTATION_STEPS_DEG = _symmetric(0.1, [1, 5, 25, 125, 625])
TRANSLATION_STEPS_M = _symmetric(0.1, [1, 3, 9, 27, 81])
DOFS = ("yaw_deg", "tx_m", "tz_m")

# The action frames (Rust: geometry::actions::ActionFrame; a model's manifest names its own in
# `actions.frame`, absent = "camera_y"):
# - "camera_y": yaw about the camera's y axis, translation along camera x and camera z;
# - "map_z": yaw about the map's z (up) axis, translation in the map's xy plane along the camera's
#   ground heading (`ground_heading`). Same motion as "camera_y" for a level camera.
CAMERA_Y, MAP_Z = "camera_y", "map_z"
ACTION_FRAMES = (CAMERA_Y, MAP_Z)


def check_frame(frame: str) -> str:
    if frame not in ACTION_FRAMES:
        raise ValueError(f"unknown action frame {frame!r}; expected one of {ACTION_FRAMES}")
    return frame


def step_values(indices) -> tuple[float, float, float]:
    """Action indices per DoF -> (yaw_deg, tx_m, tz_m)."""
    return (float(ROTATION_STEPS_DEG[indices[0]]), float(TRANSLATION_STEPS_M[indices[1]]),
            float(TRANSLATION_STEPS_M[indices[2]]))


# ---------------------------------------------------------------------------------------------
# Poses

# Every entry of R^T R - I within +-this (dimensionless) for a 3x3 to be read as a rotation;
# Rust: geometry::ROTATION_TOLERANCE. Pinned by fixtures/conventions.json.
ROTATION_TOLERANCE = 1e-3


def check_rotation(r) -> None:
    """Raises ValueError unless the 3x3 `r` is a rotation: finite, orthonormal (every entry of
    R^T R - I within +-ROTATION_TOLERANCE) and det R = +1, checked by its sign (with R^T R that
    close to I, det R is +-1 to within 1.5 x the tolerance, so a negative one is a reflection).

    The twin of Rust's `geometry::check_rotation`, with the same messages (pinned by
    fixtures/conventions.json): each starts "is not a rotation: " and says what is wrong, for the
    caller to prefix with what was read (file and line). Nothing is repaired.
    """
    r = np.asarray(r, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(r).all():
        raise ValueError("is not a rotation: it has a non-finite entry")
    if not r.any():
        raise ValueError("is not a rotation: every entry is 0 (an unset pose, such as a lost track)")
    deviation = float(np.abs(r.T @ r - np.eye(3)).max())
    if deviation > ROTATION_TOLERANCE:
        lengths = ", ".join(f"{float(np.linalg.norm(row)):.4f}" for row in r)
        raise ValueError(f"is not a rotation: its rows have lengths {lengths} and RᵀR differs from the "
                         f"identity by up to {deviation:.4f} (tolerance {ROTATION_TOLERANCE})")
    det = float(np.linalg.det(r))
    if det < 0.0:
        raise ValueError(f"is not a rotation: its determinant is {det:.4f}, a reflection (a rotation's is +1)")


def rot_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def ground_motion(yaw_rad: float, dx: float, dy: float) -> np.ndarray:
    """Rotation about the map's z axis followed by a ground-plane translation (4x4)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[0, 3], m[1, 3] = dx, dy
    return m


def transform(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Applies a 4x4 pose to (..., 3) points."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def invert(pose: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = pose[:3, :3].T
    out[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return out


# ---------------------------------------------------------------------------------------------
# Camera

def project(k: np.ndarray, points_cam: np.ndarray):
    """k = (fx, fy, cx, cy). Returns (uv (n, 2), valid (n,)) where valid means in front of the camera."""
    fx, fy, cx, cy = k
    z = points_cam[..., 2]
    valid = z >= MIN_DEPTH_M
    safe_z = np.where(valid, z, 1.0)
    uv = np.stack([fx * points_cam[..., 0] / safe_z + cx, fy * points_cam[..., 1] / safe_z + cy], axis=-1)
    return uv, valid


def in_frustum(k: np.ndarray, points_cam: np.ndarray, width: int, height: int) -> np.ndarray:
    uv, valid = project(k, points_cam)
    return (valid & (uv[..., 0] >= -0.5) & (uv[..., 1] >= -0.5)
            & (uv[..., 0] < width - 0.5) & (uv[..., 1] < height - 0.5))


def _round_half_away(x: float) -> int:
    # Rust's f64::round; Python's round() would round half to even.
    return int(math.floor(x + 0.5))


# Most a focal range may enlarge an image beyond its nominal scale (Rust's MAX_FOCAL_SCALE).
MAX_FOCAL_SCALE = 1.0


def input_scale(nominal_scale: float, focal_range_px, fx: float) -> float:
    """The factor an image with focal length `fx` (pixels) is resized by before the crop:
    `nominal_scale`, or with `focal_range_px` = (lo, hi) (the model's trained focal lengths, in
    model-input pixels) the factor nearest it that brings `fx` into [lo, hi], at most
    max(MAX_FOCAL_SCALE, nominal). Twin of `geometry::input_scale` in the crate (fixture-pinned)."""
    if focal_range_px is None:
        return nominal_scale
    lo, hi = focal_range_px
    return min(max(nominal_scale, lo / fx), hi / fx, max(MAX_FOCAL_SCALE, nominal_scale))


def resized_size(in_w: int, in_h: int, scale: float, out_w: int, out_h: int,
                 zoom: float = 1.0) -> tuple[int, int]:
    """The server's resize (zoom 1): `scale` (`input_scale`), raised to cover the output. Training's
    random zoom (`zoom` > 1) multiplies the factor; it is Python-only, and the intrinsics follow
    through `adjust_intrinsics` like every other plan."""
    s = max(scale, out_h / in_h, out_w / in_w)
    if zoom != 1.0:
        s *= zoom
    return max(_round_half_away(in_w * s), out_w), max(_round_half_away(in_h * s), out_h)


def preprocess_plan(in_w, in_h, scale, out_w, out_h, crop_xy=None, zoom: float = 1.0) -> dict:
    """Resize-then-crop plan; centre crop unless `crop_xy` is given (random crops in training),
    resize factor (`resized_size`) times `zoom` (training's random scale; 1 = the server's plan)."""
    rw, rh = resized_size(in_w, in_h, scale, out_w, out_h, zoom)
    cx, cy = crop_xy if crop_xy is not None else ((rw - out_w) // 2, (rh - out_h) // 2)
    return dict(resized_width=rw, resized_height=rh, crop_x=cx, crop_y=cy, out_width=out_w, out_height=out_h)


def adjust_intrinsics(plan: dict, k, in_w: int, in_h: int) -> np.ndarray:
    sx = plan["resized_width"] / in_w
    sy = plan["resized_height"] / in_h
    fx, fy, cx, cy = k
    return np.array([fx * sx, fy * sy, (cx + 0.5) * sx - 0.5 - plan["crop_x"], (cy + 0.5) * sy - 0.5 - plan["crop_y"]])


# ---------------------------------------------------------------------------------------------
# Actions (disentangled update) and the greedy expert

def ground_heading(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The camera's ground heading in the map frame: (right, forward), unit vectors in the map's xy
    plane. forward = the optical axis projected onto xy and normalised (if it is within 1e-6 of
    vertical: map z x the camera's x axis projected onto xy); right = forward x map z, which is
    the camera's x axis for a level camera."""
    r = pose[:3, :3]
    forward = np.array([r[2, 0], r[2, 1], 0.0])
    if np.linalg.norm(forward) < 1e-6:
        forward = np.cross([0.0, 0.0, 1.0], [r[0, 0], r[0, 1], 0.0])
    forward = forward / np.linalg.norm(forward)
    return np.cross(forward, [0.0, 0.0, 1.0]), forward


def apply_action(pose: np.ndarray, pivot_map: np.ndarray, yaw_deg: float, tx: float, tz: float,
                 frame: str = CAMERA_Y) -> np.ndarray:
    """The disentangled update: rotate about the frame's vertical axis through the pivot (cloud
    centroid), then translate.
    - camera_y: R' = Ry(yaw) R, t' = Ry(yaw) (t - c) + c + (tx, 0, tz), c = R p + t;
    - map_z:    R' = R Rz(-yaw), t' = t + R (p - Rz(-yaw) p) + R (tx right + tz forward).
    A positive yaw turns the camera's heading counter-clockwise about map +z (both frames, for a
    level camera); a positive tx / tz moves the map along right / forward relative to the camera."""
    out = np.eye(4)
    if check_frame(frame) == MAP_Z:
        r, t = pose[:3, :3], pose[:3, 3]
        turn = rot_z(-yaw_deg)
        right, forward = ground_heading(pose)
        p = np.asarray(pivot_map, dtype=np.float64)
        out[:3, :3] = r @ turn
        out[:3, 3] = t + r @ (p - turn @ p) + r @ (tx * right + tz * forward)
        return out
    pivot_cam = transform(pose, pivot_map)
    turn = rot_y(yaw_deg)
    out[:3, :3] = turn @ pose[:3, :3]
    out[:3, 3] = turn @ (pose[:3, 3] - pivot_cam) + pivot_cam + np.array([tx, 0.0, tz])
    return out


def start_yaw_offsets(h: int) -> list[float]:
    """The multi-start search's H yaw offsets (deg) about the map pivot: evenly spaced from 0, wrapped
    to (-180, 180]. Coarse yaw is what a single start fails on, so the starts cover the circle."""
    if h < 1:
        raise ValueError(f"need at least one start, got {h}")
    offsets = []
    for k in range(h):
        off = k * 360.0 / h
        offsets.append(off - 360.0 if off > 180.0 else off)
    return offsets


def needed_motion(current: np.ndarray, target: np.ndarray, pivot_map: np.ndarray,
                  frame: str = CAMERA_Y) -> tuple[float, float, float]:
    """The continuous (yaw, tx, tz) the update in `frame` needs to take `current` to `target`.
    map_z: yaw = atan2(M01 - M10, M00 + M11) of M = R_current^T R_target; the translations are the
    pivot's shift as seen from the camera, dotted with R right and R forward (its vertical part is
    out of reach and dropped)."""
    shift = transform(target, pivot_map) - transform(current, pivot_map)
    if check_frame(frame) == MAP_Z:
        r = current[:3, :3]
        m = r.T @ target[:3, :3]
        yaw = math.degrees(math.atan2(m[0, 1] - m[1, 0], m[0, 0] + m[1, 1]))
        right, forward = ground_heading(current)
        return yaw, float((r @ right) @ shift), float((r @ forward) @ shift)
    delta_r = target[:3, :3] @ current[:3, :3].T
    yaw = math.degrees(math.atan2(delta_r[0, 2], delta_r[2, 2]))
    return yaw, float(shift[0]), float(shift[2])


def nearest_step(steps: np.ndarray, value: float) -> int:
    """Closest step; ties go to the smaller magnitude."""
    best = len(steps) // 2
    for i, s in enumerate(steps):
        d, d_best = abs(s - value), abs(steps[best] - value)
        if d < d_best - 1e-12 or (abs(d - d_best) <= 1e-12 and abs(s) < abs(steps[best])):
            best = i
    return best


def expert_indices(current: np.ndarray, target: np.ndarray, pivot_map: np.ndarray,
                   frame: str = CAMERA_Y) -> tuple[int, int, int]:
    yaw, tx, tz = needed_motion(current, target, pivot_map, frame)
    return (nearest_step(ROTATION_STEPS_DEG, yaw), nearest_step(TRANSLATION_STEPS_M, tx),
            nearest_step(TRANSLATION_STEPS_M, tz))


# ---------------------------------------------------------------------------------------------
# Metrics and reward

def euler_zyx(r: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) with R = Rz(yaw) Ry(pitch) Rx(roll)."""
    pitch = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    if abs(r[2, 0]) < 1.0 - 1e-9:
        return math.atan2(r[2, 1], r[2, 2]), pitch, math.atan2(r[1, 0], r[0, 0])
    return 0.0, pitch, math.atan2(-r[0, 1], r[1, 1])


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> dict:
    delta = estimate[:3, :3].T @ truth[:3, :3]
    roll, pitch, yaw = euler_zyx(delta)
    cos = max(-1.0, min(1.0, (np.trace(delta) - 1.0) / 2.0))
    return dict(rte_m=float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3])),
                rre_euler_deg=math.degrees(abs(roll) + abs(pitch) + abs(yaw)),
                rre_geodesic_deg=math.degrees(math.acos(cos)))


def protocol_pose(truth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One camera_from_map pose [4, 4] drawn around `truth` like the paper protocol's starts, as
    `cmr.diagnose` and the ranking term's hard negatives draw them: a turn uniform in -180..180 deg
    about map z through the camera centre, then a ground shift uniform in -10..10 m on each axis of
    the map_z action frame (`apply_action`)."""
    yaw = rng.uniform(-180.0, 180.0)
    tx, tz = rng.uniform(-10.0, 10.0, 2)
    return apply_action(truth, invert(truth)[:3, 3], yaw, tx, tz, frame=MAP_Z)


def registered(estimate: np.ndarray, truth: np.ndarray) -> bool:
    """Protocol A's success test for one camera_from_map pose: RTE < 5 m and RRE (Euler sum) < 10 deg."""
    e = pose_error(estimate, truth)
    return e["rte_m"] < RR_MAX_TRANSLATION_M and e["rre_euler_deg"] < RR_MAX_ROTATION_DEG


def p2p_distance(current: np.ndarray, truth: np.ndarray, points_map: np.ndarray) -> float:
    if len(points_map) == 0:
        return 0.0
    return float(np.linalg.norm(transform(truth, points_map) - transform(current, points_map), axis=-1).mean())


def step_reward(before: float, after: float) -> float:
    if after < before - 1e-9:
        return REWARD_BETTER
    if after > before + 1e-9:
        return REWARD_WORSE
    return REWARD_SAME
