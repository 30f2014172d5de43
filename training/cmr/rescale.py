"""A copy of KITTI-layout sequences with every image resized by one factor and the calibration
following it: what a client sending the same camera at another resolution sends.

    python -m cmr.rescale SRC DST --factor 2

SRC holds sequence folders (`NNN/{image_2, velodyne, calib.txt, poses.txt, ...}`, as
`cmr.real_split` writes them) or is one. Each image of `image_2/` is resized by `--factor`
(PIL bilinear, sizes rounded) and `P0..P3` scaled with the pixel-centre convention the
preprocessing uses (u' = (u + 0.5) * s - 0.5, per axis: s = new size / old size); every other
file is a symbolic link to the original. Used to measure whether the model's answer depends
on the resolution an image is sent at (docs/evaluation.md, "One focal length").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image


def scaled_projection(p: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """A 3x4 projection for an image resized by (sx, sy): rows 0 and 1 become s * row + (s - 1) / 2 * row 2."""
    q = p.copy()
    for r, s in ((0, sx), (1, sy)):
        q[r] = s * p[r] + (s - 1.0) / 2.0 * p[2]
    return q


def rescale_sequence(src: Path, dst: Path, factor: float) -> None:
    (dst / "image_2").mkdir(parents=True, exist_ok=False)
    sizes = set()
    for image in sorted((src / "image_2").iterdir()):
        with Image.open(image) as im:
            w, h = im.size
            size = (round(w * factor), round(h * factor))
            im.convert("RGB").resize(size, Image.BILINEAR).save(dst / "image_2" / image.name)
        sizes.add((size[0] / w, size[1] / h))
    if len(sizes) != 1:
        raise SystemExit(f"{src}: images of several sizes")
    (sx, sy), = sizes
    lines = []
    for line in (src / "calib.txt").read_text().splitlines():
        key, _, values = line.partition(":")
        if key.strip() in ("P0", "P1", "P2", "P3"):
            p = scaled_projection(np.array(values.split(), dtype=np.float64).reshape(3, 4), sx, sy)
            line = f"{key}: " + " ".join(f"{v:.12e}" for v in p.ravel())
        lines.append(line)
    (dst / "calib.txt").write_text("\n".join(lines) + "\n")
    for entry in src.iterdir():
        if entry.name not in ("image_2", "calib.txt"):
            (dst / entry.name).symlink_to(entry.resolve())


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("dst", type=Path)
    ap.add_argument("--factor", type=float, required=True)
    args = ap.parse_args(argv)
    if not args.factor > 0:
        raise SystemExit("--factor must be positive")
    sequences = [args.src] if (args.src / "calib.txt").exists() else sorted(
        d for d in args.src.iterdir() if (d / "calib.txt").exists())
    if not sequences:
        raise SystemExit(f"{args.src}: no KITTI-layout sequence (calib.txt) found")
    for seq in sequences:
        rescale_sequence(seq, args.dst if seq == args.src else args.dst / seq.name, args.factor)
    rigs = args.src / "rigs.json"
    if rigs.exists() and not (args.dst / "rigs.json").exists():
        (args.dst / "rigs.json").symlink_to(rigs.resolve())
    print(f"{len(sequences)} sequence(s) resized by {args.factor} into {args.dst}")


if __name__ == "__main__":
    main()
