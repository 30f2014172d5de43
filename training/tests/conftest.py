"""Shared fixtures: a tiny KITTI-layout dataset.

The dataset comes from the Rust generator (`cmr-agent synth`, binary from $CMR_AGENT_BIN or
../target/release/cmr-agent). While that binary has no `synth` subcommand (before the synth
branch is merged) a small Python-written scene in the same layout stands in, so the pipeline is
still exercised end to end on real files.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

REPO = Path(__file__).resolve().parents[2]

torch.set_num_threads(2)


def _rust_binary() -> Path | None:
    path = Path(os.environ.get("CMR_AGENT_BIN", REPO / "target" / "release" / "cmr-agent"))
    if not path.is_file():
        return None
    try:
        help_text = subprocess.run([str(path), "--help"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.TimeoutExpired):
        return None
    return path if "synth" in help_text else None


def write_python_sequence(seq: Path, frames: int, seed: int, width: int = 640, height: int = 200) -> None:
    """A street of textured walls and a ground plane; the image is the coloured points splatted
    through the same calibration the files declare."""
    rng = np.random.default_rng(seed)
    (seq / "velodyne").mkdir(parents=True)
    (seq / "image_2").mkdir()
    fx = fy = 0.55 * width
    cx, cy = width / 2 - 0.5, height / 2 - 0.5
    p2 = np.array([[fx, 0, cx, 0.06 * fx], [0, fy, cy, 0], [0, 0, 1, 0]])
    tr = np.array([[0, -1, 0, 0], [0, 0, -1, -0.08], [1, 0, 0, -0.27]], dtype=float)
    zeros = " ".join(["0"] * 12)
    (seq / "calib.txt").write_text(f"P0: {zeros}\nP1: {zeros}\nP2: {' '.join(map(str, p2.ravel()))}\nP3: {zeros}\n"
                                   f"Tr: {' '.join(map(str, tr.ravel()))}\n")
    lines = []
    for f in range(frames):
        x = rng.uniform(-40, 40, 30000)
        ground = np.stack([x, rng.uniform(-12, 12, x.size), np.full(x.size, -1.7)], 1)
        wall_x = rng.uniform(-40, 40, 30000)
        side = np.where(rng.random(wall_x.size) < 0.5, -8.0, 8.0) + rng.normal(0, 0.05, wall_x.size)
        walls = np.stack([wall_x, side, rng.uniform(-1.7, 6, wall_x.size)], 1)
        boxes = np.concatenate([np.stack([rng.uniform(b - 1, b + 1, 2000), rng.uniform(-5, 5, 1) + rng.uniform(-1, 1, 2000),
                                          rng.uniform(-1.7, 0.5, 2000)], 1) for b in rng.uniform(-30, 30, 6)])
        pts = np.concatenate([ground, walls, boxes]).astype(np.float32)
        colour = (np.stack([np.sin(pts[:, 0] * 0.7), np.cos(pts[:, 1] * 0.9 + pts[:, 2]), np.sin(pts[:, 2] * 1.3)], 1) + 1) * 110 + 20
        scan = np.concatenate([pts, np.ones((len(pts), 1), np.float32)], 1)
        scan.astype(np.float32).tofile(seq / "velodyne" / f"{f:06d}.bin")
        cam = pts.astype(float) @ tr[:, :3].T + tr[:, 3] + np.array([0.06, 0, 0])
        front = cam[:, 2] > 0.5
        u = np.round(fx * cam[front, 0] / cam[front, 2] + cx).astype(int)
        v = np.round(fy * cam[front, 1] / cam[front, 2] + cy).astype(int)
        c, z = colour[front], cam[front, 2]
        keep = (u >= 0) & (u < width) & (v >= 0) & (v < height)
        img = np.full((height, width, 3), 90, np.uint8)
        order = np.argsort(-z[keep])  # far first, near points overwrite
        for du in (0, 1):
            for dv in (0, 1):
                uu, vv = np.clip(u[keep][order] + du, 0, width - 1), np.clip(v[keep][order] + dv, 0, height - 1)
                img[vv, uu] = c[keep][order].astype(np.uint8)
        Image.fromarray(img).save(seq / "image_2" / f"{f:06d}.png")
        lines.append(" ".join(map(str, np.eye(4)[:3].ravel())))
    (seq / "poses.txt").write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth")
    binary = _rust_binary()
    if binary is not None:
        subprocess.run([str(binary), "synth", "--out", str(root), "--sequences", "1", "--frames", "4", "--seed", "7",
                        "--image-size", "640x200"], check=True, capture_output=True, timeout=600)
    else:
        write_python_sequence(root / "sequences" / "00", frames=4, seed=7)
    return root
