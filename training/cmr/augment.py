"""Augmentations for transfer from synthetic to real frames (all off unless a config turns them on).

Every augmentation keeps the sample's geometry consistent:
- photometric ones change pixel values only (no pixel moves);
- the random zoom changes the resize factor, and the crop intrinsics come from the one place that
  computes them (`geometry.preprocess_plan` + `geometry.adjust_intrinsics`, the server's convention);
- LiDAR ones delete points (beams, density, an azimuth sector) or move a point along its own ray
  (range noise), in the LiDAR frame before the map motion, so labels computed afterwards stay right.

Sensors differ across rigs mostly in: colour response, exposure, sharpness, compression (camera);
number of beams, density and noise (LiDAR). The draws below aim at those.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageFilter

# ---------------------------------------------------------------------------------------------
# Options


@dataclass(frozen=True)
class AugmentOptions:
    """What `data.make_sample` applies in training. The defaults are today's behaviour."""
    photometric: str = "basic"  # "basic": brightness/contrast/saturation +-20 %; "heavy": `heavy_photometric`
    scale_max: float = 1.0  # random zoom factor drawn in [1, scale_max] on top of the preprocessing resize
    lidar: bool = False  # `lidar_augment` on the scan
    beams_min: int = 16
    beams_max: int = 32
    beam_dropout_p: float = 0.5  # share of samples whose scan is thinned to beams_min..beams_max rings
    density_min: float = 0.3  # keep a random share in [density_min, 1] of the points
    range_noise_m: float = 0.03  # max sigma of Gaussian range noise (drawn per sample in [0, this])
    occlusion_p: float = 0.3  # share of samples with one azimuth sector dropped
    occlusion_max_deg: float = 60.0
    # The map from other scans of the drive (`data.neighbour_map`): 0 = the frame's own scan.
    map_window: int = 0  # frames each side to draw from
    map_scans: int = 3  # scans in the union
    map_window_p: float = 1.0  # share of samples given such a map (the others keep their own scan)
    # The server's crop of a tiled region (`data.virtual_scan_map`): a virtual scan of such a union
    # from a sensor up to `virtual_scan_offset_m` from the camera, for this share of the samples
    # (drawn first; the rest go on to `map_window_p`).
    virtual_scan_p: float = 0.0
    virtual_scan_offset_m: float = 6.0
    virtual_scan_radius_m: float = 60.0  # the server's `--default-radius-m`
    # Fleet-like starts (`data.make_sample`): this share of the samples moves the map by a yaw within
    # +-`near_start_yaw_deg` and a ground shift within a disc of `near_start_shift_m` instead of the
    # protocol's (+-180 deg, +-10 m), so the agent learns to stop near a good prior.
    near_start_p: float = 0.0
    near_start_yaw_deg: float = 30.0
    near_start_shift_m: float = 5.0
    # Mirror images (`data.mirror_sample`): this share of the samples is flipped left to right,
    # the image and the map together, so the geometry stays exact (traffic keeps left there).
    mirror_p: float = 0.0
    # Maps without intensity (`data.intensity_rank` of a constant: 0.5 everywhere): this share of
    # the samples loses its points' intensity, so a model that reads it still works from geometry
    # alone (a PLY or fused region with no intensity field). Drawn last.
    intensity_drop_p: float = 0.0

    @property
    def active(self) -> bool:
        return (self.photometric != "basic" or self.scale_max > 1.0 or self.lidar or self.map_window > 0 or self.virtual_scan_p > 0
                or self.near_start_p > 0 or self.mirror_p > 0 or self.intensity_drop_p > 0)


DEFAULT = AugmentOptions()


# ---------------------------------------------------------------------------------------------
# Photometric (float RGB images in [0, 1], H x W x 3)


def _yiq_hue(x: np.ndarray, angle: float) -> np.ndarray:
    """Rotates the chroma plane of YIQ by `angle` (radians): a hue shift that keeps luma."""
    to_yiq = np.array([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]], dtype=np.float32)
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float32)
    m = np.linalg.inv(to_yiq) @ rot @ to_yiq
    return x @ m.T.astype(np.float32)


def heavy_photometric(rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Strong, per-sample colour and sensor changes. Each transform is drawn independently."""
    x = rgb.astype(np.float32)
    if rng.random() < 0.8:  # exposure
        x = x * rng.uniform(0.5, 1.6)
    if rng.random() < 0.8:  # contrast
        mean = x.mean()
        x = (x - mean) * rng.uniform(0.5, 1.5) + mean
    if rng.random() < 0.5:  # white balance: per-channel gains
        x = x * rng.uniform(0.8, 1.2, 3).astype(np.float32)
    x = np.clip(x, 0.0, 1.0)
    if rng.random() < 0.5:  # gamma
        x = x ** rng.uniform(0.6, 1.6)
    if rng.random() < 0.5:  # hue
        x = _yiq_hue(x, rng.uniform(-0.5, 0.5))
    grey = x @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    roll = rng.random()
    if roll < 0.1:  # greyscale
        x = np.repeat(grey[..., None], 3, axis=-1)
    else:
        if rng.random() < 0.7:  # saturation
            x = (x - grey[..., None]) * rng.uniform(0.3, 1.6) + grey[..., None]
        if rng.random() < 0.15:  # channel shuffle
            x = x[..., rng.permutation(3)]
    x = np.clip(x, 0.0, 1.0)
    if rng.random() < 0.3:  # defocus / motion blur stand-in
        im = Image.fromarray((x * 255.0 + 0.5).astype(np.uint8))
        x = np.asarray(im.filter(ImageFilter.GaussianBlur(rng.uniform(0.4, 1.5))), dtype=np.float32) / 255.0
    if rng.random() < 0.5:  # sensor noise
        x = x + rng.normal(0.0, rng.uniform(0.005, 0.04), x.shape).astype(np.float32)
        x = np.clip(x, 0.0, 1.0)
    if rng.random() < 0.3:  # compression artefacts
        x = jpeg(x, int(rng.integers(15, 70)))
    return np.clip(x, 0.0, 1.0).astype(np.float32)


def jpeg(x: np.ndarray, quality: int) -> np.ndarray:
    buf = io.BytesIO()
    Image.fromarray((np.clip(x, 0, 1) * 255.0 + 0.5).astype(np.uint8)).save(buf, format="JPEG", quality=quality)
    buf.seek(0)
    with Image.open(buf) as im:
        return np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0


# ---------------------------------------------------------------------------------------------
# Zoom: only the factor is drawn here; sizes and intrinsics come from geometry.preprocess_plan


def draw_zoom(rng: np.random.Generator, opts: AugmentOptions) -> float:
    return float(rng.uniform(1.0, opts.scale_max)) if opts.scale_max > 1.0 else 1.0


# ---------------------------------------------------------------------------------------------
# LiDAR (xyz in the LiDAR frame, [n, 3])


def elevation_deg(xyz: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))


def ring_ids(xyz: np.ndarray, gap_deg: float = 0.08, fallback_bin_deg: float = 0.4) -> np.ndarray:
    """Recovers each point's ring from its elevation angle: a spinning LiDAR's beams sit at fixed
    elevations, so sorted elevations form tight clusters with gaps between them. Ring 0 is the
    lowest. When the clusters do not look like 8-256 beams (noisy or non-spinning data), equal
    elevation bins of `fallback_bin_deg` stand in for rings."""
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.int64)
    elev = elevation_deg(xyz)
    order = np.argsort(elev, kind="stable")
    gaps = np.diff(elev[order]) > gap_deg
    ids_sorted = np.concatenate([[0], np.cumsum(gaps)])
    big = np.bincount(ids_sorted)
    real = int((big >= max(8, len(xyz) // 2000)).sum())  # clusters with a beam's worth of points
    if not 8 <= real <= 256:
        return np.floor((elev - elev.min()) / fallback_bin_deg).astype(np.int64)
    out = np.empty(len(xyz), dtype=np.int64)
    out[order] = ids_sorted
    return out


def keep_beams(xyz: np.ndarray, target: int, rng: np.random.Generator) -> np.ndarray:
    """Boolean mask keeping about `target` rings: every k-th ring from a random offset."""
    ids = ring_ids(xyz)
    # Stray clusters (a handful of points) do not count as beams.
    uniq, counts = np.unique(ids, return_counts=True)
    beams = uniq[counts >= max(8, len(xyz) // 2000)]
    if len(beams) <= target:
        return np.ones(len(xyz), dtype=bool)
    stride = len(beams) / target
    start = rng.uniform(0, stride)
    chosen = beams[np.floor(start + stride * np.arange(target)).astype(np.int64).clip(0, len(beams) - 1)]
    return np.isin(ids, chosen)


def lidar_augment(xyz: np.ndarray, rng: np.random.Generator, opts: AugmentOptions) -> np.ndarray:
    """Beam dropout, density subsampling, range noise and an occluded azimuth sector. Never
    returns fewer than 64 points (a step that would is skipped). `xyz`: [M, 3] or [M, 3 + k]; the
    geometry is the first three columns, any others (intensity) ride along with their points."""
    out = xyz
    if rng.random() < opts.beam_dropout_p:
        mask = keep_beams(out[:, :3], int(rng.integers(opts.beams_min, opts.beams_max + 1)), rng)
        if mask.sum() >= 64:
            out = out[mask]
    keep = rng.uniform(opts.density_min, 1.0)
    mask = rng.random(len(out)) < keep
    if mask.sum() >= 64:
        out = out[mask]
    if rng.random() < opts.occlusion_p:
        az = np.degrees(np.arctan2(out[:, 1], out[:, 0]))
        centre, width = rng.uniform(-180, 180), rng.uniform(10.0, opts.occlusion_max_deg)
        inside = np.abs((az - centre + 180.0) % 360.0 - 180.0) < width / 2
        if (~inside).sum() >= 64:
            out = out[~inside]
    sigma = rng.uniform(0.0, opts.range_noise_m)
    if sigma > 0:
        r = np.linalg.norm(out[:, :3], axis=1, keepdims=True)
        noisy = np.maximum(r + rng.normal(0.0, sigma, r.shape), 0.05)
        out = np.concatenate([out[:, :3] * (noisy / np.maximum(r, 1e-6)), out[:, 3:]], axis=1)
    return np.ascontiguousarray(out, dtype=np.float32)
