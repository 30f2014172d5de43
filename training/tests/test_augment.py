"""Augmentations for transfer keep the sample's geometry consistent.

The camera test uses a hand-made KITTI sequence whose image is a smooth analytic pattern f(u, v)
evaluated at the original pixel centres: after any zoom + crop, every labelled point projected with
the sample's intrinsics must read (bilinearly) the colour f has where the point projects in the
original image."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

import cmr.data as data
from cmr import augment as aug
from cmr import geometry as g
from cmr.data import IMAGE_MEAN, IMAGE_STD, OUT_H, OUT_W, list_frames, make_sample, read_scan, sample_points

W0, H0 = 900, 280
K0 = (450.0, 452.0, 437.3, 131.8)  # fx, fy, cx, cy, off-centre on purpose


def pattern(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """RGB in [0.1, 0.9], periods of 90-150 px: smooth enough for bilinear reads after resizing."""
    r = 0.5 + 0.4 * np.sin(2 * math.pi * u / 140.0)
    gch = 0.5 + 0.4 * np.sin(2 * math.pi * v / 90.0 + 0.7)
    b = 0.5 + 0.4 * np.sin(2 * math.pi * (u + v) / 150.0 + 1.3)
    return np.stack([r, gch, b], axis=-1)


@pytest.fixture(scope="module")
def pattern_frame(tmp_path_factory):
    seq = tmp_path_factory.mktemp("pattern") / "00"
    (seq / "image_2").mkdir(parents=True)
    (seq / "velodyne").mkdir()
    fx, fy, cx, cy = K0
    p2 = [fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0]
    tr = [0, -1, 0, 0, 0, 0, -1, 0, 1, 0, 0, 0]  # cam x = -lidar y, cam y = -lidar z, cam z = lidar x
    (seq / "calib.txt").write_text("P2: " + " ".join(map(str, p2)) + "\nTr: " + " ".join(map(str, tr)) + "\n")
    vv, uu = np.mgrid[0:H0, 0:W0].astype(np.float64)
    Image.fromarray((pattern(uu, vv) * 255 + 0.5).astype(np.uint8)).save(seq / "image_2" / "000000.png")
    rng = np.random.default_rng(3)
    n = 6000
    lidar = np.stack([rng.uniform(4, 40, n), rng.uniform(-25, 25, n), rng.uniform(-2, 3, n), np.zeros(n)], 1)
    lidar.astype(np.float32).tofile(seq / "velodyne" / "000000.bin")
    return list_frames([seq])[0]


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    u, v = uv[:, 0], uv[:, 1]
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    du, dv = (u - u0)[:, None], (v - v0)[:, None]
    h, w = img.shape[:2]
    c = lambda a, b: img[np.clip(b, 0, h - 1), np.clip(a, 0, w - 1)]  # noqa: E731
    return (c(u0, v0) * (1 - du) * (1 - dv) + c(u0 + 1, v0) * du * (1 - dv)
            + c(u0, v0 + 1) * (1 - du) * dv + c(u0 + 1, v0 + 1) * du * dv)


@pytest.mark.parametrize("scale_max", [1.0, 1.6])
def test_zoom_and_crop_keep_points_on_their_pixels(pattern_frame, monkeypatch, scale_max):
    monkeypatch.setattr(data, "colour_jitter", lambda rgb, rng: rgb)  # pixels only move, colours stay
    data._decoded.cache_clear()
    opts = aug.AugmentOptions(scale_max=scale_max)
    k_seen = set()
    for seed in range(6):
        s = make_sample(pattern_frame, np.random.default_rng(seed), train=True, num_points=4000, augment=opts)
        k_seen.add(round(float(s.intrinsics[0]), 3))
        rgb = s.image.transpose(1, 2, 0) * IMAGE_STD + IMAGE_MEAN
        cam = g.transform(s.truth, s.points[s.labels].astype(np.float64))
        uv, _ = g.project(s.intrinsics, cam)
        inner = (uv[:, 0] > 1) & (uv[:, 0] < OUT_W - 2) & (uv[:, 1] > 1) & (uv[:, 1] < OUT_H - 2)
        assert inner.sum() > 200
        got = _bilinear(rgb, uv[inner])
        # Where the same point lands in the original image, by the original intrinsics.
        cam_lidar = g.transform(pattern_frame.calib.camera_from_lidar,
                                g.transform(g.invert(s.motion), s.points[s.labels].astype(np.float64)))
        uv0, _ = g.project(np.array(K0), cam_lidar)
        want = pattern(uv0[inner, 0], uv0[inner, 1])
        err = np.abs(got - want)
        assert np.median(err) < 0.01 and np.percentile(err, 99) < 0.04, (seed, np.median(err), err.max())
    if scale_max > 1.0:
        assert len(k_seen) > 1, "the zoom must change the focal length"


def test_a_mirrored_sample_reads_each_point_where_it_was(pattern_frame, monkeypatch):
    """mirror_p = 1: every point, projected with the mirrored sample's pose and intrinsics, reads the
    colour the original image has where the unmirrored point projects; poses stay rotations."""
    monkeypatch.setattr(data, "colour_jitter", lambda rgb, rng: rgb)
    data._decoded.cache_clear()
    reflect = np.diag([1.0, -1.0, 1.0, 1.0])
    for seed in range(4):
        s = make_sample(pattern_frame, np.random.default_rng(seed), train=True, num_points=4000,
                        augment=aug.AugmentOptions(mirror_p=1.0))
        plain = make_sample(pattern_frame, np.random.default_rng(seed), train=True, num_points=4000)
        assert np.array_equal(s.labels, plain.labels)
        assert np.allclose(s.image, plain.image[:, :, ::-1])
        for pose in (s.truth, s.initial, s.motion):
            assert abs(np.linalg.det(pose[:3, :3]) - 1.0) < 1e-9
        cam = g.transform(s.truth, s.points.astype(np.float64))
        assert np.array_equal(g.in_frustum(s.intrinsics, cam, OUT_W, OUT_H), s.labels)
        uv, _ = g.project(s.intrinsics, cam[s.labels])
        uv_plain, _ = g.project(plain.intrinsics, g.transform(plain.truth, plain.points[plain.labels].astype(np.float64)))
        assert np.allclose(uv[:, 0], OUT_W - 1 - uv_plain[:, 0], atol=1e-6) and np.allclose(uv[:, 1], uv_plain[:, 1], atol=1e-6)
        rgb = s.image.transpose(1, 2, 0) * IMAGE_STD + IMAGE_MEAN
        inner = (uv[:, 0] > 1) & (uv[:, 0] < OUT_W - 2) & (uv[:, 1] > 1) & (uv[:, 1] < OUT_H - 2)
        assert inner.sum() > 200
        lidar = g.transform(reflect @ g.invert(s.motion), s.points[s.labels].astype(np.float64))
        uv0, _ = g.project(np.array(K0), g.transform(pattern_frame.calib.camera_from_lidar, lidar))
        err = np.abs(_bilinear(rgb, uv[inner]) - pattern(uv0[inner, 0], uv0[inner, 1]))
        assert np.median(err) < 0.01 and np.percentile(err, 99) < 0.04, (seed, np.median(err), err.max())


def test_zoomed_plan_is_the_servers_plan_at_zoom_one():
    for w, h in [(1241, 376), (620, 188), (1600, 900), (960, 300)]:
        assert g.preprocess_plan(w, h, 0.5, OUT_W, OUT_H) == g.preprocess_plan(w, h, 0.5, OUT_W, OUT_H, None, 1.0)
        big = g.preprocess_plan(w, h, 0.5, OUT_W, OUT_H, (3, 2), 1.5)
        base = g.preprocess_plan(w, h, 0.5, OUT_W, OUT_H)
        assert big["resized_width"] >= base["resized_width"] * 1.5 - 1


def test_default_options_draw_what_they_always_drew(tiny_dataset):
    frame = list_frames([next(p for p in sorted(tiny_dataset.iterdir()) if p.is_dir())])[0]
    a = make_sample(frame, np.random.default_rng(5), train=True, num_points=3000)
    b = make_sample(frame, np.random.default_rng(5), train=True, num_points=3000, augment=aug.AugmentOptions())
    assert np.array_equal(a.image, b.image) and np.array_equal(a.points, b.points)
    assert not aug.AugmentOptions().active


def test_heavy_photometric_keeps_shape_and_range():
    rng = np.random.default_rng(0)
    vv, uu = np.mgrid[0:OUT_H, 0:OUT_W].astype(np.float64)
    img = pattern(uu, vv).astype(np.float32)
    outs = [aug.heavy_photometric(img, np.random.default_rng(i)) for i in range(12)]
    for out in outs:
        assert out.shape == img.shape and out.dtype == np.float32
        assert out.min() >= 0.0 and out.max() <= 1.0
    assert np.mean([np.abs(o - img).mean() for o in outs]) > 0.03  # heavy means heavy
    again = aug.heavy_photometric(img, np.random.default_rng(3))
    assert np.array_equal(again, outs[3])
    del rng


def _spinning_scan(beams: int, rng: np.random.Generator, top=2.0, bottom=-24.8) -> tuple[np.ndarray, np.ndarray]:
    elev = np.linspace(bottom, top, beams)
    az = np.radians(np.arange(-180, 180, 0.4))
    e, a = np.meshgrid(np.radians(elev), az, indexing="ij")
    r = rng.uniform(3, 60, e.shape)
    xyz = np.stack([r * np.cos(e) * np.cos(a), r * np.cos(e) * np.sin(a), r * np.sin(e)], -1).reshape(-1, 3)
    ring = np.repeat(np.arange(beams), len(az))
    keep = rng.random(len(xyz)) > 0.05  # base dropout
    return xyz[keep].astype(np.float32), ring[keep]


def test_rings_are_recovered_from_elevation():
    rng = np.random.default_rng(1)
    for beams in (16, 32, 64, 128):
        xyz, truth = _spinning_scan(beams, rng)
        ids = aug.ring_ids(xyz)
        assert len(np.unique(ids)) == beams
        # The same partition: each recovered ring is exactly one true ring.
        pairs = np.unique(np.stack([ids, truth], 1), axis=0)
        assert len(pairs) == beams


def test_beam_dropout_keeps_16_to_32_whole_rings():
    rng = np.random.default_rng(2)
    xyz, truth = _spinning_scan(64, rng)
    for target in (16, 24, 32):
        mask = aug.keep_beams(xyz, target, rng)
        kept = np.unique(truth[mask])
        assert len(kept) == target
        for ring in kept:  # whole rings, not a thinning
            assert mask[truth == ring].all()


def test_rings_of_a_generated_kitti_scan(tiny_dataset):
    seq = next(p for p in sorted(tiny_dataset.iterdir()) if p.is_dir())
    xyz = read_scan(sorted((seq / "velodyne").glob("*.bin"))[0])
    mask = aug.keep_beams(xyz, 16, np.random.default_rng(0))
    rings = np.unique(aug.ring_ids(xyz[mask]))
    assert 12 <= len(rings) <= 20
    assert mask.mean() < 0.45


def test_lidar_augment_only_drops_points_or_moves_them_along_their_ray():
    rng = np.random.default_rng(4)
    xyz, _ = _spinning_scan(64, rng)
    opts = aug.AugmentOptions(lidar=True, beam_dropout_p=1.0, occlusion_p=1.0, range_noise_m=0.05)
    out = aug.lidar_augment(xyz, np.random.default_rng(9), opts)
    assert 64 <= len(out) < len(xyz) * 0.6
    unit_in = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    unit_out = out / np.linalg.norm(out, axis=1, keepdims=True)
    # Every output direction is an input direction (nearest by dot product), ranges within 5 sigma.
    best = (unit_out[:2000] @ unit_in.T).max(axis=1)
    assert best.min() > 1 - 1e-6
    az = np.degrees(np.arctan2(out[:, 1], out[:, 0]))
    hist = np.histogram(az, bins=72, range=(-180, 180))[0]
    assert (hist == 0).sum() >= 2, "an occluded sector of at least 10 degrees"


def test_short_scans_are_sampled_up_to_n():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(100, 3)).astype(np.float32)
    out = sample_points(xyz, 1000, rng)
    assert out.shape == (1000, 3)
    # Every point appears (the permutation comes first), the rest are repeats of real points.
    assert len(np.unique(out, axis=0)) == 100


def test_augmented_training_sample_is_consistent(tiny_dataset):
    frame = list_frames([next(p for p in sorted(tiny_dataset.iterdir()) if p.is_dir())])[0]
    opts = aug.AugmentOptions(photometric="heavy", scale_max=1.5, lidar=True, beam_dropout_p=1.0)
    s = make_sample(frame, np.random.default_rng(1), train=True, num_points=8000, augment=opts)
    assert s.image.shape == (3, OUT_H, OUT_W) and s.points.shape == (8000, 3)
    labels = g.in_frustum(s.intrinsics, g.transform(s.truth, s.points.astype(np.float64)), OUT_W, OUT_H)
    assert np.array_equal(labels, s.labels) and labels.any()
