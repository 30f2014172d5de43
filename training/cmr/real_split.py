"""The training / validation split of `../shared/real-train`, by drive or scene, never by frame.

Frames of one drive are 0.5-1 s apart and nuScenes / DDAD cameras share scans, so a frame-level
split would validate on near-copies of training frames. Validation holds whole drives of five of
the seven rigs (the aiMotive rig has one drive: its last four keyframes, 1.5 s after the rest):

    python -m cmr.real_split --src ../../shared/real-train --out ~/.cache/cmr-agent/data/real-split

writes `OUT/train/NNN` and `OUT/val/NNN` (symbolic links to the sequence folders; no frame is
copied) and `OUT/rigs.json` (sequence -> rig, drive). `OUT/train` and `OUT/val` are KITTI-layout
roots for `cmr.train --data/--val-data`, `cmr.diagnose` and `cmr-agent eval`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

# (rig, drive, first sequence, last sequence) -- ../shared/real-train/README.md and FRAMES.md
DRIVES = [
    ("kitti-object", "training/000008", 0, 0),
    ("kitti-object", "training/000010", 1, 1),
    ("kitti-object", "training/000134", 2, 2),
    ("kitti-raw", "2011_09_26_drive_0048", 3, 4),
    ("kitti-raw", "2011_09_26_drive_0009", 5, 15),
    ("kitti-odometry", "sequence 04", 16, 21),
    ("nuscenes", "scene-0523", 22, 48),
    ("nuscenes", "scene-0916", 49, 76),
    ("nuscenes", "log n015-2018-08-02", 77, 78),
    ("ddad", "scene_01", 79, 81),
    ("ddad", "scene_02", 82, 90),
    ("aimotive", "20210901-194123 keyframes 33643-33679", 91, 103),
    ("aimotive", "20210901-194123 keyframes 33682-33691", 104, 107),
    ("opencalib", "manual_calib/0", 108, 108),
]
VALIDATION = {"training/000010", "2011_09_26_drive_0048", "log n015-2018-08-02", "scene_01",
              "20210901-194123 keyframes 33682-33691"}


def rigs() -> dict[str, dict]:
    """sequence name ('NNN') -> {rig, drive, split}."""
    return {f"{n:03d}": dict(rig=rig, drive=drive, split="val" if drive in VALIDATION else "train")
            for rig, drive, a, b in DRIVES for n in range(a, b + 1)}


def write(src: Path, out: Path) -> dict[str, int]:
    """Links every sequence of `src` (a real-train copy) into `out/train` or `out/val`; returns counts.
    Raises FileNotFoundError when `src` lacks a sequence the split names."""
    table = rigs()
    counts = {"train": 0, "val": 0}
    for split in counts:
        (out / split).mkdir(parents=True, exist_ok=True)
    for name, row in table.items():
        seq = (src / "sequences" / name).resolve()
        if not (seq / "calib.txt").is_file():
            raise FileNotFoundError(f"{seq}: no calib.txt; is {src} ../shared/real-train?")
        link = out / row["split"] / name
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(seq)
        counts[row["split"]] += 1
    (out / "rigs.json").write_text(json.dumps(table, indent=1) + "\n")
    return counts


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--src", type=Path, default=Path("../../shared/real-train"))
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    print(json.dumps(write(args.src, args.out)))


if __name__ == "__main__":
    main()
