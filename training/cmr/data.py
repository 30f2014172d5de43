"""KITTI-odometry reader and the paper's sample protocol (see the common brief).

A sequence directory holds `calib.txt`, `velodyne/NNNNNN.bin` (float32 x, y, z, intensity) and
`image_2/NNNNNN.png`. One sample = one frame with:
- the image resized per `geometry.preprocess_plan` and cropped to 160 x 512 (random crop when
  training, centre crop otherwise), intrinsics adjusted to the crop, ImageNet-normalised;
- the scan sampled to N points (random permutation, refilled with replacement when short);
- a random map-frame motion Q (yaw over the full circle, ground shift within +-10 m):
  map = Q * scan, truth camera_from_map = camera_from_lidar * Q^-1, initial pose camera_from_lidar;
- optionally (training, `AugmentOptions.map_window` > 0, for a `map_window_p` share of the
  samples) the map is not this frame's own scan but
  the union of the scans of `map_scans` frames drawn within +-`map_window` of it, moved into this
  frame's LiDAR frame with `poses.txt`: the camera is then not at the centre of the map's rings,
  as in a region built from a drive (a model trained only on own scans learns to put the camera
  where the scan was taken);
- optionally (training, `AugmentOptions.virtual_scan_p` > 0) the map is what the server cuts out
  of a region built from a drive: a virtual scan (`virtual_scan`, the twin of the server's) of
  such a union from a sensor moved up to `virtual_scan_offset_m` along the ground from the
  camera. A localize in a tiled region takes its virtual scan from the prior, so the scan's
  centre is where the prior is, not where the camera is (docs/server.md, "Known limit");
- in-frustum labels of every sampled point under the true pose;
- each point's intensity as its rank among the N (`intensity_rank`), read by intensity models.

Decoded frames (resized image, xyz) are cached in memory: PNG decode dominates on 2 cores.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from PIL import Image

from . import augment as aug
from . import geometry as g

OUT_W, OUT_H = 512, 160
NOMINAL_SCALE = 0.5
# The focal lengths (model-input pixels) every camera is brought to (`geometry.input_scale`): the
# KITTI rigs' at NOMINAL_SCALE (odometry 707.0912 and colour 721.5377 px, halved), where most training
# frames are (the synthetic rig's 718.856 too). Another lens, or a KITTI image sent at another
# resolution, is resized to the nearer end instead of by NOMINAL_SCALE, so the model reads pixels of
# one angular size whatever the camera (docs/evaluation.md, "One focal length"). Exported
# manifests carry it as `image.focal_range_px`, which the server applies alike.
FOCAL_RANGE_PX = (353.5456, 360.76885)
IMAGE_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGE_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


class DataError(ValueError):
    """A sequence on disk does not follow the KITTI-odometry layout."""


@dataclass(frozen=True)
class Calibration:
    camera_from_lidar: np.ndarray  # 4x4, velodyne -> rectified image_2 camera
    intrinsics: np.ndarray  # (fx, fy, cx, cy) of image_2
    cam0_from_lidar: np.ndarray | None = None  # 4x4, Tr: velodyne -> camera 0 (the frame of poses.txt)


def parse_calib(path: Path) -> Calibration:
    """`calib.txt`'s P2 (image_2's projection) and Tr (velodyne -> cam0, 3x4 row-major).
    Raises DataError naming the file (and line): a key missing, a bad number, or a Tr whose 3x3
    block is not a rotation (`geometry.check_rotation`, as the Rust reader)."""
    rows: dict[str, np.ndarray] = {}
    line_of: dict[str, int] = {}
    for line_no, line in enumerate(Path(path).read_text().splitlines(), 1):
        if ":" not in line:
            continue
        key, values = line.split(":", 1)
        try:
            rows[key.strip()] = np.array([float(v) for v in values.split()])
        except ValueError as e:
            raise DataError(f"{path}:{line_no}: bad number in line {key!r}") from e
        line_of[key.strip()] = line_no
    for key in ("P2", "Tr"):
        if key not in rows or rows[key].size != 12:
            raise DataError(f"{path}: missing or malformed {key} (need 12 floats)")
    p2 = rows["P2"].reshape(3, 4)
    tr = np.eye(4)
    tr[:3, :] = rows["Tr"].reshape(3, 4)
    try:
        g.check_rotation(tr[:3, :3])
    except ValueError as e:
        raise DataError(f"{path}:{line_of['Tr']}: Tr's rotation block {e}") from None
    shift = np.eye(4)
    shift[:3, 3] = (p2[0, 3] / p2[0, 0], p2[1, 3] / p2[1, 1], p2[2, 3])
    return Calibration(shift @ tr, np.array([p2[0, 0], p2[1, 1], p2[0, 2], p2[1, 2]]), tr)


def read_scan(path: Path, intensity: bool = False) -> np.ndarray:
    """A scan's finite points: [M, 3] float32 x, y, z (LiDAR frame, metres), or [M, 4] with the
    intensity column when `intensity` (a non-finite intensity reads as 0)."""
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size % 4:
        raise DataError(f"{path}: size is not a multiple of 4 float32 values")
    rows = raw.reshape(-1, 4)
    rows = rows[np.isfinite(rows[:, :3]).all(axis=1)]
    if not intensity:
        return rows[:, :3]
    return np.concatenate([rows[:, :3], np.nan_to_num(rows[:, 3:], nan=0.0, posinf=0.0, neginf=0.0)], axis=1)


def intensity_rank(values: np.ndarray) -> np.ndarray:
    """Each point's intensity as its mid-rank among the model's N input points: (number below +
    half the number equal) / N, in (0, 1), float32. Monotone rescalings of a rig's intensity (the
    rigs here report medians from 0.03 to 0.3) leave it unchanged, and a cloud without intensity
    (constant) reads 0.5 everywhere. The twin of `maps::intensity_rank` (Rust), pinned by
    `fixtures/conventions.json`."""
    v = np.asarray(values, dtype=np.float32)
    if v.size == 0:
        return v.copy()
    ordered = np.sort(v)
    below = np.searchsorted(ordered, v, side="left")
    equal = np.searchsorted(ordered, v, side="right") - below
    return ((below + 0.5 * equal) / v.size).astype(np.float32)


@dataclass(frozen=True)
class Frame:
    sequence: Path
    index: int
    calib: Calibration

    @property
    def image_path(self) -> Path:
        return self.sequence / "image_2" / f"{self.index:06d}.png"

    @property
    def scan_path(self) -> Path:
        return self.sequence / "velodyne" / f"{self.index:06d}.bin"


@lru_cache(maxsize=64)
def read_poses(sequence: Path) -> np.ndarray:
    """`poses.txt` of a KITTI-odometry sequence: [F, 4, 4] world_from_cam0 per frame (12 numbers a
    line, the 3x4 row-major top of each matrix; blank lines skipped). Raises DataError naming the
    file and line: not 12 finite numbers, or a 3x3 block that is not a rotation
    (`geometry.check_rotation`: a lost track's zeros, a scaled or reflected block), as the Rust
    reader (`kitti::poses::parse_poses`) does; nothing is repaired."""
    path = Path(sequence) / "poses.txt"
    try:
        text = path.read_text()
    except OSError as e:
        raise DataError(f"{path}: cannot read poses ({e})") from e
    poses = []
    for line_no, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            values = np.array([float(v) for v in line.split()])
        except ValueError as e:
            raise DataError(f"{path}:{line_no}: {e}") from None
        if values.size != 12:
            raise DataError(f"{path}:{line_no}: expected 12 numbers, found {values.size}")
        if not np.isfinite(values).all():
            raise DataError(f"{path}:{line_no}: a number is not finite")
        pose = np.eye(4)
        pose[:3, :] = values.reshape(3, 4)
        try:
            g.check_rotation(pose[:3, :3])
        except ValueError as e:
            raise DataError(f"{path}:{line_no}: the pose's rotation block (numbers 1-3, 5-7, 9-11) {e}") from None
        poses.append(pose)
    return np.array(poses).reshape(-1, 4, 4)


def lidar_from_lidar(frame: "Frame", other: int) -> np.ndarray:
    """4x4 mapping the LiDAR frame of frame `other` of the same sequence into `frame`'s LiDAR frame:
    Tr^-1 * pose_i^-1 * pose_j * Tr."""
    tr = frame.calib.cam0_from_lidar
    if tr is None:
        raise DataError(f"{frame.sequence}: the calibration has no Tr")
    poses = read_poses(frame.sequence)
    if not (0 <= frame.index < len(poses) and 0 <= other < len(poses)):
        raise DataError(f"{frame.sequence}/poses.txt has {len(poses)} poses, frames {frame.index} and {other} asked")
    return g.invert(tr) @ g.invert(poses[frame.index]) @ poses[other] @ tr


def neighbour_map(frame: "Frame", rng: np.random.Generator, window: int, scans: int,
                  augment: "aug.AugmentOptions | None" = None, intensity: bool = False) -> np.ndarray:
    """The union of the scans of `scans` distinct frames drawn within +-`window` of `frame` (frames
    that exist in its sequence; possibly `frame` itself), each LiDAR-augmented in its own frame
    when `augment.lidar`, moved into `frame`'s LiDAR frame. [M, 3] float64 ([M, 4] with the
    intensity column when `intensity`; the draws are the same either way)."""
    candidates = [j for j in range(frame.index - window, frame.index + window + 1)
                  if (frame.sequence / "velodyne" / f"{j:06d}.bin").is_file()]
    picks = rng.choice(candidates, size=min(scans, len(candidates)), replace=False)
    parts = []
    for j in sorted(int(j) for j in picks):
        xyz = read_scan(frame.sequence / "velodyne" / f"{j:06d}.bin", intensity=intensity)
        if augment is not None and augment.lidar:
            xyz = aug.lidar_augment(xyz, rng, augment)
        moved = g.transform(lidar_from_lidar(frame, j), xyz[:, :3].astype(np.float64))
        parts.append(np.concatenate([moved, xyz[:, 3:].astype(np.float64)], axis=1))
    return np.concatenate(parts)


# The server's virtual scan of a tiled region (src/maps/tiles.rs): an HDL-64E-like grid.
SCAN_BEAMS = 64
SCAN_COLUMNS = 2048
SCAN_ELEVATION_DEG = (-25.0, 3.0)


def virtual_scan(points: np.ndarray, sensor, radius_m: float) -> np.ndarray:
    """Indices of the points a LiDAR at `sensor` would see: of the points within `radius_m`
    (ground-plane distance) of it, the nearest in each cell of a SCAN_BEAMS x SCAN_COLUMNS
    elevation x azimuth grid (elevations SCAN_ELEVATION_DEG; points outside the span are
    dropped), in cell order (row-major from the lowest elevation and azimuth -180 deg; the
    earlier point wins a tie). `points`: [M, 3] (read as float32, like the server's storage),
    `sensor`: (x, y, z) metres, same frame. The twin of `maps::tiles::virtual_scan` (with the
    radius test of `within`), pinned by `fixtures/conventions.json`. A tie in range goes to the
    earlier point here and to the earlier candidate there (the region's storage order), which
    agree for candidates in index order, as in the fixture."""
    p = np.asarray(points, dtype=np.float32).astype(np.float64)
    d = p - np.asarray(sensor, dtype=np.float64)
    ground = np.hypot(d[:, 0], d[:, 1])
    low, high = SCAN_ELEVATION_DEG
    row = np.floor((np.degrees(np.arctan2(d[:, 2], ground)) - low) / (high - low) * SCAN_BEAMS)
    keep = np.flatnonzero((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] <= radius_m * radius_m) & (row >= 0) & (row < SCAN_BEAMS))
    column = np.minimum(((np.arctan2(d[keep, 1], d[keep, 0]) + math.pi) / (2 * math.pi) * SCAN_COLUMNS).astype(np.int64),
                        SCAN_COLUMNS - 1)
    cell = row[keep].astype(np.int64) * SCAN_COLUMNS + column
    distance = np.sqrt(ground[keep] ** 2 + d[keep, 2] ** 2).astype(np.float32)
    order = np.lexsort((keep, distance, cell))  # by cell, then range, then input order
    first = np.ones(len(order), dtype=bool)
    first[1:] = cell[order][1:] != cell[order][:-1]
    return keep[order][first]


def virtual_scan_map(frame: "Frame", rng: np.random.Generator, augment: "aug.AugmentOptions",
                     intensity: bool = False) -> np.ndarray:
    """The server's crop of a region built from the drive, seen from a wrong place: the union of
    neighbour scans (`neighbour_map`, `augment.map_window` / `map_scans`), virtually scanned
    (`virtual_scan`, `augment.virtual_scan_radius_m`) from the camera's position moved along the
    LiDAR's ground plane by a uniform draw in a disc of `augment.virtual_scan_offset_m`. [M, 3]
    float64 in `frame`'s LiDAR frame ([M, 4] with intensity when `intensity`)."""
    union = neighbour_map(frame, rng, max(augment.map_window, 1), augment.map_scans, augment, intensity)
    camera = g.invert(frame.calib.camera_from_lidar)[:3, 3]
    r = augment.virtual_scan_offset_m * math.sqrt(rng.random())
    a = rng.uniform(-math.pi, math.pi)
    sensor = camera + np.array([r * math.cos(a), r * math.sin(a), 0.0])
    seen = union[virtual_scan(union[:, :3], sensor, augment.virtual_scan_radius_m)]
    if len(seen) == 0:
        raise DataError(f"{frame.sequence} frame {frame.index}: the virtual scan from {sensor} sees no point")
    return seen


def list_frames(sequences: list[Path]) -> list[Frame]:
    frames = []
    for seq in sequences:
        seq = Path(seq)
        if not (seq / "calib.txt").is_file():
            raise DataError(f"{seq}: no calib.txt (expected a KITTI-odometry sequence directory)")
        calib = parse_calib(seq / "calib.txt")
        for scan in sorted((seq / "velodyne").glob("*.bin")):
            idx = int(scan.stem)
            if (seq / "image_2" / f"{idx:06d}.png").is_file():
                frames.append(Frame(seq, idx, calib))
    if not frames:
        raise DataError(f"no frames with both velodyne/*.bin and image_2/*.png under {sequences}")
    return frames


def find_sequences(root: Path) -> list[Path]:
    """`root` itself when it is a sequence, else its `sequences/*` or `*` sub-directories that are."""
    root = Path(root)
    if (root / "calib.txt").is_file():
        return [root]
    base = root / "sequences" if (root / "sequences").is_dir() else root
    seqs = sorted(p for p in base.iterdir() if (p / "calib.txt").is_file()) if base.is_dir() else []
    if not seqs:
        raise DataError(f"{root}: no KITTI-odometry sequences found")
    return seqs


@lru_cache(maxsize=1024)
def _decoded(image_path: Path, scan_path: Path, scale: float) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """(image resized by `scale` (raised to cover the input) as uint8 HxWx3, the scan's x, y, z,
    intensity [M, 4] float32, original (W, H)); resizing does not depend on the crop."""
    with Image.open(image_path) as im:
        im = im.convert("RGB")
        w, h = im.size
        plan = g.preprocess_plan(w, h, scale, OUT_W, OUT_H)
        resized = np.asarray(im.resize((plan["resized_width"], plan["resized_height"]), Image.BILINEAR))
    return resized, read_scan(scan_path, intensity=True), (w, h)


@dataclass
class Sample:
    image: np.ndarray  # [3, 160, 512] float32, normalised
    intrinsics: np.ndarray  # crop intrinsics (fx, fy, cx, cy)
    points: np.ndarray  # [N, 3] float32, map frame
    labels: np.ndarray  # [N] bool, in the true frustum
    truth: np.ndarray  # 4x4 camera_from_map
    initial: np.ndarray  # 4x4 camera_from_map (the rig calibration)
    motion: np.ndarray  # Q, 4x4
    intensity: np.ndarray | None = None  # [N] float32, `intensity_rank` of the points' intensity


def point_input(samples: "list[Sample]", channels: int = 3) -> np.ndarray:
    """The point encoder's input for a batch: [B, N, 3] x, y, z (map frame, metres), or with
    `channels` = 4 the points' `intensity_rank` as a fourth column (0.5 where a sample has none)."""
    xyz = np.stack([s.points for s in samples]).astype(np.float32)
    if channels == 3:
        return xyz
    if channels != 4:
        raise ValueError(f"a point encoder reads 3 or 4 channels, not {channels}")
    rank = np.stack([s.intensity if s.intensity is not None else np.full(len(s.points), 0.5, np.float32)
                     for s in samples]).astype(np.float32)
    return np.concatenate([xyz, rank[..., None]], axis=-1)


def sample_points(xyz: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    if len(xyz) == 0:
        raise DataError("empty scan")
    order = rng.permutation(len(xyz))[:n]
    if len(order) < n:
        order = np.concatenate([order, rng.integers(0, len(xyz), n - len(order))])
    return xyz[order]


def colour_jitter(rgb: np.ndarray, rng: np.random.Generator, strength: float = 0.2) -> np.ndarray:
    """Brightness, contrast and saturation jitter on a float image in [0, 1]."""
    x = rgb * rng.uniform(1 - strength, 1 + strength)
    mean = x.mean()
    x = (x - mean) * rng.uniform(1 - strength, 1 + strength) + mean
    grey = x.mean(axis=-1, keepdims=True)
    x = (x - grey) * rng.uniform(1 - strength, 1 + strength) + grey
    return np.clip(x, 0.0, 1.0)


def make_sample(frame: Frame, rng: np.random.Generator, train: bool, num_points: int = 40960,
                max_shift_m: float = 10.0, motion: np.ndarray | None = None,
                augment: aug.AugmentOptions = aug.DEFAULT, focal_range_px=FOCAL_RANGE_PX) -> Sample:
    """`motion`: a given Q (a frozen test case) instead of a random one. The random draw still
    happens, so the rest of the sample does not depend on whether a motion was given.
    `augment` (training only): the default draws exactly what it always drew (random crop, basic
    colour jitter); other options add draws after those (see `augment.py`).
    `focal_range_px`: the model's (lo, hi) focal lengths (`geometry.input_scale`; None: NOMINAL_SCALE
    for every image)."""
    scale = g.input_scale(NOMINAL_SCALE, focal_range_px, float(frame.calib.intrinsics[0]))
    resized, xyz, (w, h) = _decoded(frame.image_path, frame.scan_path, scale)  # xyz: [M, 4] with intensity
    rh, rw = resized.shape[:2]
    zoom = aug.draw_zoom(rng, augment) if train and augment.scale_max > 1.0 else 1.0
    if zoom != 1.0:
        zw, zh = g.resized_size(w, h, scale, OUT_W, OUT_H, zoom)
        # Resizing the cached image again composes exactly with the first resize (pixel-centre
        # convention), so the plan's intrinsics (original -> zoomed size) hold.
        resized = np.asarray(Image.fromarray(resized).resize((zw, zh), Image.BILINEAR))
        rh, rw = zh, zw
    crop = (int(rng.integers(0, rw - OUT_W + 1)), int(rng.integers(0, rh - OUT_H + 1))) if train else None
    plan = g.preprocess_plan(w, h, scale, OUT_W, OUT_H, crop, zoom)
    assert (plan["resized_width"], plan["resized_height"]) == (rw, rh)
    x0, y0 = plan["crop_x"], plan["crop_y"]
    rgb = resized[y0:y0 + OUT_H, x0:x0 + OUT_W].astype(np.float32) / 255.0
    if train:
        rgb = aug.heavy_photometric(rgb, rng) if augment.photometric == "heavy" else colour_jitter(rgb, rng)
    image = ((rgb - IMAGE_MEAN) / IMAGE_STD).transpose(2, 0, 1).astype(np.float32)
    k = g.adjust_intrinsics(plan, frame.calib.intrinsics, w, h)

    if train and augment.virtual_scan_p > 0 and rng.random() < augment.virtual_scan_p:
        xyz = virtual_scan_map(frame, rng, augment, intensity=True)
    elif train and augment.map_window > 0 and (augment.map_window_p >= 1.0 or rng.random() < augment.map_window_p):
        xyz = neighbour_map(frame, rng, augment.map_window, augment.map_scans, augment, intensity=True)
    elif train and augment.lidar:
        xyz = aug.lidar_augment(xyz, rng, augment)
    sampled = sample_points(xyz, num_points, rng)
    scan, intensity = sampled[:, :3].astype(np.float64), intensity_rank(sampled[:, 3])
    q = g.ground_motion(rng.uniform(-math.pi, math.pi), *rng.uniform(-max_shift_m, max_shift_m, 2))
    if train and augment.near_start_p > 0 and rng.random() < augment.near_start_p:
        # drawn after the protocol's motion, so the other options' draws stay as they were
        radius = augment.near_start_shift_m * math.sqrt(rng.random())
        heading = rng.uniform(-math.pi, math.pi)
        q = g.ground_motion(math.radians(rng.uniform(-augment.near_start_yaw_deg, augment.near_start_yaw_deg)),
                            radius * math.cos(heading), radius * math.sin(heading))
    if motion is not None:
        q = motion
    points = g.transform(q, scan)
    truth = frame.calib.camera_from_lidar @ g.invert(q)
    labels = g.in_frustum(k, g.transform(truth, points), OUT_W, OUT_H)
    sample = Sample(image=np.ascontiguousarray(image), intrinsics=k, points=points.astype(np.float32),
                    labels=labels, truth=truth, initial=frame.calib.camera_from_lidar.copy(), motion=q,
                    intensity=intensity)
    # drawn last, so the other options' draws stay as they were
    if train and augment.mirror_p > 0 and rng.random() < augment.mirror_p:
        sample = mirror_sample(sample)
    if train and augment.intensity_drop_p > 0 and rng.random() < augment.intensity_drop_p:
        sample.intensity = np.full(len(sample.points), 0.5, np.float32)
    return sample


# Left-right reflections: of the camera frame (x right) and of the map and LiDAR frames (y left).
_MIRROR_CAMERA = np.diag([-1.0, 1.0, 1.0, 1.0])
_MIRROR_MAP = np.diag([1.0, -1.0, 1.0, 1.0])


def mirror_sample(s: Sample) -> Sample:
    """The same sample seen in a mirror: the image flipped left to right (its principal point with
    it: cx' = OUT_W - 1 - cx, pixel centres at integers), the map reflected across its x-z plane
    (y -> -y) and every pose conjugated, P' = S_camera P S_map, a proper rotation again. Each point
    projects to the mirrored pixel of where it projected before (u' = OUT_W - 1 - u, v' = v), so
    labels, correspondences and the true pose stay exact. Ground motions stay ground motions."""
    k = s.intrinsics.copy()
    k[2] = OUT_W - 1 - k[2]
    conj = lambda pose: _MIRROR_CAMERA @ pose @ _MIRROR_MAP  # noqa: E731
    return Sample(image=np.ascontiguousarray(s.image[:, :, ::-1]), intrinsics=k,
                  points=(s.points * np.array([1.0, -1.0, 1.0], np.float32)).astype(np.float32), labels=s.labels,
                  truth=conj(s.truth), initial=conj(s.initial), motion=_MIRROR_MAP @ s.motion @ _MIRROR_MAP,
                  intensity=s.intensity)


def split_frames(frames: list[Frame], holdout_every: int) -> tuple[list[Frame], list[Frame]]:
    """Deterministic hold-out (every k-th frame) for validation when no test set is given."""
    if holdout_every <= 1:
        return frames, []
    return ([f for i, f in enumerate(frames) if i % holdout_every],
            [f for i, f in enumerate(frames) if not i % holdout_every])
