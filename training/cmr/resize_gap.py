"""Does the image resize explain why the training evaluator and the server disagree?

Training resizes with PIL's bilinear filter; the server (`src/agent/input.rs`) resized with the
`image` crate's Triangle filter (0.25: vertical pass kept in f32, then horizontal pass, rounded half
away from zero) until 2026-12-01, and since then with `fast_image_resize`'s bilinear convolution
(fixed point, about 10x faster; within one grey level of the Triangle filter, Rust test
`resize_is_the_triangle_filter_to_one_grey_level`, and of PIL). `server_resize` ports the Triangle
filter to numpy, and `evaluate` runs `cmr.evaluate` with it:

    python -m cmr.resize_gap compare ../data/synth-test/00/image_2/000000.png
    python -m cmr.resize_gap evaluate --checkpoint runs/v3/last.pt --data ../data/synth-test \
        --perturbations ../docs/eval/perturbations.json
"""

from __future__ import annotations

import sys
from functools import lru_cache
from pathlib import Path

import numpy as np
from PIL import Image

from . import data
from . import geometry as g


def _weights(src: int, dst: int) -> np.ndarray:
    """[dst, src] normalised triangle weights, sample positions as the `image` crate computes them."""
    ratio = np.float32(src) / np.float32(dst)
    scale = max(ratio, np.float32(1.0))
    out = np.zeros((dst, src), np.float32)
    for o in range(dst):
        centre = (np.float32(o) + np.float32(0.5)) * ratio
        left = int(np.clip(np.floor(centre - scale), 0, src - 1))
        right = int(np.clip(np.ceil(centre + scale), left + 1, src))
        x = np.abs((np.arange(left, right, dtype=np.float32) - (centre - np.float32(0.5))) / scale)
        w = np.where(x < 1, 1 - x, 0).astype(np.float32)
        out[o, left:right] = w / w.sum()
    return out


def server_resize(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """uint8 HxWx3 -> uint8 height x width x 3, as `imageops::resize(.., FilterType::Triangle)`."""
    if rgb.shape[:2] == (height, width):
        return rgb.copy()
    vertical = np.einsum("oh,hwc->owc", _weights(rgb.shape[0], height), rgb.astype(np.float32))
    both = np.einsum("ow,hwc->hoc", _weights(rgb.shape[1], width), vertical)
    return np.floor(np.clip(both, 0, 255) + 0.5).astype(np.uint8)


def _original(image_path: Path, scale: float = data.NOMINAL_SCALE) -> tuple[np.ndarray, tuple[int, int]]:
    """The decoded RGB image and the size the preprocessing plan resizes it to."""
    with Image.open(image_path) as im:
        rgb = np.asarray(im.convert("RGB"))
    plan = g.preprocess_plan(rgb.shape[1], rgb.shape[0], scale, data.OUT_W, data.OUT_H)
    return rgb, (plan["resized_width"], plan["resized_height"])


@lru_cache(maxsize=1024)
def _decoded_like_the_server(image_path: Path, scan_path: Path, scale: float):
    """`data._decoded` with the server's resize in place of PIL's."""
    rgb, size = _original(image_path, scale)
    return server_resize(rgb, *size), data.read_scan(scan_path, intensity=True), (rgb.shape[1], rgb.shape[0])


def main(argv: list[str]) -> None:
    if argv[:1] == ["compare"]:
        rgb, size = _original(Path(argv[1]))
        pil, server = np.asarray(Image.fromarray(rgb).resize(size, Image.BILINEAR)), server_resize(rgb, *size)
        diff = np.abs(pil.astype(int) - server.astype(int))
        print(f"max |difference| {diff.max()} levels, pixels differing {100 * (diff > 0).mean():.1f} %")
    elif argv[:1] == ["evaluate"]:
        from . import evaluate
        data._decoded = _decoded_like_the_server  # make_sample looks it up at call time
        evaluate.main(argv[1:])
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
