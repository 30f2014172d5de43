"""The training-time state matches the contract, checked against a literal per-point reference."""

import numpy as np
import torch

from cmr import geometry as g
from cmr.state import build_state


def reference_state(pose, points, k, pf, imf, prob):
    grid = np.zeros((64, 40, 128))
    count = np.zeros((40, 128))
    p_cam = g.transform(pose, points)
    inside = g.in_frustum(k, p_cam, 512, 160)
    uv, _ = g.project(k, p_cam)
    for i in np.flatnonzero(inside):
        row, col = int(np.floor((uv[i, 1] + 0.5) / 4)), int(np.floor((uv[i, 0] + 0.5) / 4))
        grid[:, row, col] += pf[i]
        count[row, col] += 1
    grid /= np.maximum(count, 1)
    m = len(prob)
    s3 = np.concatenate([p_cam[:m] / 10.0, prob[:, None], inside[:m, None].astype(float)], axis=1)
    return np.concatenate([imf, grid]), s3


def test_state_matches_reference():
    rng = np.random.default_rng(3)
    n, m = 3000, 256
    points = rng.uniform([-30, -30, -2], [30, 30, 3], (n, 3))
    pose = g.apply_action(np.array([[0, -1, 0, 0], [0, 0, -1, 0.1], [1, 0, 0, -0.3], [0, 0, 0, 1.0]]),
                          points.mean(0), 20.0, 0.5, -1.0)
    k = np.array([360.0, 360.0, 255.5, 79.5])
    pf = rng.normal(size=(n, 64))
    imf = rng.normal(size=(64, 40, 128))
    prob = rng.uniform(size=m)
    want2, want3 = reference_state(pose, points, k, pf, imf, prob)
    t = lambda a: torch.as_tensor(a, dtype=torch.float32)[None]  # noqa: E731
    got2, got3 = build_state(t(pose), t(points), t(k), t(pf), t(imf), t(prob))
    assert got2.shape == (1, 128, 40, 128) and got3.shape == (1, m, 5)
    assert want3[:, 4].sum() > 10  # the pose sees part of the cloud
    assert np.allclose(got2[0].numpy(), want2, atol=1e-4)
    assert np.allclose(got3[0].numpy(), want3, atol=1e-4)


def test_alignment_matches_reference():
    """Batched alignment = per-point mean of dot(point feature, image feature of its cell); a row
    whose pose sees no point scores -1."""
    from cmr.state import alignment
    rng = np.random.default_rng(5)
    n = 2000
    points = rng.uniform([-30, -30, -2], [30, 30, 3], (n, 3))
    pose = g.apply_action(np.array([[0, -1, 0, 0], [0, 0, -1, 0.1], [1, 0, 0, -0.3], [0, 0, 0, 1.0]]),
                          points.mean(0), -35.0, 0.2, 1.0)
    blind = np.eye(4)
    blind[2, 3] = -100.0  # every point behind the camera
    k = np.array([360.0, 360.0, 255.5, 79.5])
    pf = rng.normal(size=(n, 64))
    imf = rng.normal(size=(64, 40, 128))
    p_cam = g.transform(pose, points)
    inside = g.in_frustum(k, p_cam, 512, 160)
    uv, _ = g.project(k, p_cam)
    want = np.mean([pf[i] @ imf[:, int(np.floor((uv[i, 1] + 0.5) / 4)), int(np.floor((uv[i, 0] + 0.5) / 4))]
                    for i in np.flatnonzero(inside)])
    t = lambda *a: torch.as_tensor(np.stack(a), dtype=torch.float32)  # noqa: E731
    got = alignment(t(pose, blind), t(points, points), t(k, k), t(pf, pf), t(imf, imf))
    assert inside.sum() > 10 and got.shape == (2,)
    assert abs(float(got[0]) - want) < 1e-4 and float(got[1]) == -1.0
