"""The sample protocol: crop sizes, intrinsics, map-frame motion and labels agree with projection."""

import math

import numpy as np
import pytest

from cmr import geometry as g
from cmr.data import DataError, find_sequences, list_frames, make_sample, parse_calib


def test_sample_protocol(tiny_dataset):
    frames = list_frames(find_sequences(tiny_dataset))
    assert len(frames) == 4
    s = make_sample(frames[0], np.random.default_rng(0), train=True, num_points=4096)
    assert s.image.shape == (3, 160, 512) and s.image.dtype == np.float32
    assert s.points.shape == (4096, 3)
    # Truth = camera_from_lidar * Q^-1, and Q is a yaw about z plus a ground shift within 10 m.
    assert np.allclose(s.truth @ s.motion, frames[0].calib.camera_from_lidar, atol=1e-9)
    assert abs(s.motion[2, 3]) < 1e-12 and np.all(np.abs(s.motion[:2, 3]) <= 10.0)
    assert np.allclose(s.motion[2, :3], [0, 0, 1])
    # Labels are exactly "in the crop's frustum under the true pose".
    p_cam = g.transform(s.truth, s.points.astype(np.float64))
    uv, front = g.project(s.intrinsics, p_cam)
    expect = front & (uv[:, 0] >= -0.5) & (uv[:, 0] < 511.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < 159.5)
    assert np.array_equal(expect, s.labels)
    assert 0 < s.labels.sum() < len(s.labels)


def test_centre_crop_is_deterministic_and_matches_plan(tiny_dataset):
    frame = list_frames(find_sequences(tiny_dataset))[1]
    a = make_sample(frame, np.random.default_rng(5), train=False, num_points=2048)
    b = make_sample(frame, np.random.default_rng(5), train=False, num_points=2048)
    assert np.array_equal(a.image, b.image) and np.array_equal(a.points, b.points)
    from PIL import Image
    w, h = Image.open(frame.image_path).size
    plan = g.preprocess_plan(w, h, 0.5, 512, 160)
    assert np.allclose(a.intrinsics, g.adjust_intrinsics(plan, frame.calib.intrinsics, w, h))


def test_short_scan_is_refilled(tiny_dataset):
    frame = list_frames(find_sequences(tiny_dataset))[0]
    s = make_sample(frame, np.random.default_rng(1), train=False, num_points=500_000)
    assert s.points.shape == (500_000, 3)


def test_bad_calib_is_a_clear_error(tmp_path):
    (tmp_path / "calib.txt").write_text("P2: 1 2 3\n")
    with pytest.raises(DataError, match="P2"):
        parse_calib(tmp_path / "calib.txt")
    with pytest.raises(DataError):
        find_sequences(tmp_path / "nothing")


def test_the_servers_resize_port_stays_within_one_level_of_pil():
    """cmr.resize_gap ports the server's Triangle resize; on a downscale it agrees with PIL's
    bilinear to one grey level (the two differ only in rounding), and a same-size resize copies."""
    from PIL import Image
    from cmr.resize_gap import server_resize
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (94, 310, 3), dtype=np.uint8)
    ours = server_resize(rgb, 133, 40)
    pil = np.asarray(Image.fromarray(rgb).resize((133, 40), Image.BILINEAR))
    assert ours.shape == pil.shape
    assert np.abs(ours.astype(int) - pil.astype(int)).max() <= 1
    assert np.array_equal(server_resize(rgb, 310, 94), rgb)
