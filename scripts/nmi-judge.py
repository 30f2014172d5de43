#!/usr/bin/env python3
"""A rig-independent judge beside the learned alignment score (issue 29): normalised mutual
information between the LiDAR intensity projected at a pose and the image's grey levels under it
(the classic score of targetless camera-LiDAR calibration and of camera-in-LiDAR-map
localisation: at the right pose, reflectance and brightness co-vary; at a wrong one they are
independent).

For every pose the search visited (the start and every step of every hypothesis of
`cmr-agent eval --record-hypotheses`), the case's map (Q . scan, with intensity, Q from the
perturbation file) is moved into the camera by that camera_from_map, projected with the frame's
full-size intrinsics (`training/cmr/data.py`'s calibration, the same as the server's), and
NMI = (H(I) + H(G)) / H(I, G) is computed over the points in view from a joint histogram
(`--bins`, intensity and grey each in equal-count bins per case), in [1, 2], 1 = independent.

Prints per file, like scripts/pose-judges.py: RR when the answer is the candidate that maximises
each judge, its mean within-case AUC (registered vs not), and what answering with the prior
(no-op) when it beats the search's answer would do (`keep prior`).

    cd training && ../.venv/bin/python ../scripts/nmi-judge.py --data ../../shared/real-dev \
        --perturbations ../docs/eval/real-dev-perturbations.json /tmp/rec/rd/cases.json
"""

import argparse
import importlib.util
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "training"))
from cmr import geometry as g  # noqa: E402
from cmr.data import find_sequences, parse_calib  # noqa: E402

# protocol A's test, from scripts/pose-judges.py (the one copy among the scripts)
_spec = importlib.util.spec_from_file_location("pose_judges", Path(__file__).resolve().parent / "pose-judges.py")
_pj = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_pj)
registered = _pj.registered


class Frame:
    """One frame's grey image, intrinsics and scan (xyz + intensity, LiDAR frame)."""

    def __init__(self, seq: Path, index: int):
        calib = parse_calib(seq / "calib.txt")
        self.k = calib.intrinsics  # fx, fy, cx, cy of the full-size image
        with Image.open(seq / "image_2" / f"{index:06d}.png") as im:
            self.grey = np.asarray(im.convert("L"), dtype=np.float32)
        raw = np.fromfile(seq / "velodyne" / f"{index:06d}.bin", dtype=np.float32).reshape(-1, 4)
        self.xyz, self.intensity = raw[:, :3].astype(np.float64), raw[:, 3]


def ranks_to_bins(x: np.ndarray, bins: int) -> np.ndarray:
    """Equal-count bins (robust to each rig's intensity scale and the image's exposure)."""
    order = np.argsort(x, kind="stable")
    out = np.empty(len(x), dtype=np.int64)
    out[order] = np.arange(len(x)) * bins // max(len(x), 1)
    return out


def nmi(frame: Frame, map_xyz: np.ndarray, camera_from_map: np.ndarray, bins: int) -> float:
    cam = g.transform(camera_from_map, map_xyz)
    fx, fy, cx, cy = frame.k
    h, w = frame.grey.shape
    z = cam[:, 2]
    ok = z > 0.5
    u = np.full(len(z), -1.0)
    v = np.full(len(z), -1.0)
    u[ok] = fx * cam[ok, 0] / z[ok] + cx
    v[ok] = fy * cam[ok, 1] / z[ok] + cy
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    if ok.sum() < 50:
        return 1.0
    a = ranks_to_bins(frame.intensity[ok], bins)
    b = ranks_to_bins(frame.grey[v[ok].astype(int), u[ok].astype(int)], bins)
    joint = np.bincount(a * bins + b, minlength=bins * bins).astype(np.float64)
    p = joint / joint.sum()
    pa, pb = p.reshape(bins, bins).sum(1), p.reshape(bins, bins).sum(0)
    ent = lambda q: -np.sum(q[q > 0] * np.log(q[q > 0]))  # noqa: E731
    return float((ent(pa) + ent(pb)) / max(ent(p), 1e-12))


def auc(pos, neg) -> float:
    if not pos or not neg:
        return float("nan")
    return sum((p > n) + 0.5 * (p == n) for p in pos for n in neg) / (len(pos) * len(neg))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="+")
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--perturbations", required=True, type=Path)
    ap.add_argument("--bins", type=int, default=16)
    ap.add_argument("--weights", default="0.5,1,2,4", help="w in alignment + w * (NMI - 1)")
    ap.add_argument("--no-nmi", action="store_true", help="only the answer rules (fast)")
    args = ap.parse_args()
    seqs = {p.name: p for p in find_sequences(args.data)}
    cases_q = json.load(open(args.perturbations))["cases"]
    weights = [float(w) for w in args.weights.split(",")]
    frames = {}
    for path in args.cases:
        agent = [r for r in json.load(open(path)) if r["method"] == "cmr-agent"]
        noop = [r for r in json.load(open(path)) if r["method"] == "no-op"]
        assert len(agent) == len(cases_q), f"{path}: {len(agent)} cases, the perturbation file {len(cases_q)}"
        judges = defaultdict(lambda: [0, []])  # name -> [wins, aucs]
        answer_ok = oracle = 0
        margins = [-0.01, 0.0, 0.005, 0.01, 0.02, 0.04]
        keep_prior_ok = dict.fromkeys(margins, 0)
        for i, (rec, q) in enumerate(zip(agent, cases_q)):
            key = (q["sequence"], q["frame"])
            hyps = rec["notes"]["hypotheses"]
            cands = [p for h in hyps for p in [h["start"]] + h["steps"]]
            reg = [registered(c) for c in cands]
            oracle += any(reg)
            scores = {"alignment": [c["alignment"] for c in cands]}
            if not args.no_nmi:
                if key not in frames:
                    frames[key] = Frame(seqs[q["sequence"]], q["frame"])
                fr = frames[key]
                motion = g.ground_motion(np.radians(q["yaw_deg"]), q["dx_m"], q["dy_m"])
                map_xyz = g.transform(motion, fr.xyz)
                for c in cands:
                    m = np.eye(4)
                    m[:3, :] = np.asarray(c["camera_from_map"]).reshape(3, 4)
                    c["nmi"] = nmi(fr, map_xyz, m, args.bins)
                scores["nmi"] = [c["nmi"] for c in cands]
                for w in weights:
                    scores[f"alignment + {w} (nmi-1)"] = [c["alignment"] + w * (c["nmi"] - 1) for c in cands]
            for name, s in scores.items():
                best = int(np.argmax(s))
                judges[name][0] += reg[best]
                judges[name][1].append(auc([x for x, r in zip(s, reg) if r], [x for x, r in zip(s, reg) if not r]))
            # keep prior: hypothesis 0's start is the prior; the search's answer is the recorded one
            answer_ok += registered(rec["errors"][-1])
            prior = hyps[0]["start"]
            finals = [(h["steps"] or [h["start"]])[-1] for h in hyps]
            best_final = max(finals, key=lambda c: c["alignment"])
            for d in margins:
                kept = prior["alignment"] > best_final["alignment"] + d
                keep_prior_ok[d] += registered(prior if kept else rec["errors"][-1])
        n = len(agent)
        noop_ok = sum(registered(r["errors"][-1]) for r in noop)
        print(f"{path}: {n} cases; search answer {answer_ok / n:.1%}, no-op {noop_ok / n:.1%}; "
              f"some visited pose registered {oracle / n:.1%}")
        print("  keep prior when its alignment beats the answer's by more than d: " +
              ", ".join(f"d={d:+}: {ok / n:.1%}" for d, ok in keep_prior_ok.items()))
        for name, (wins, aucs) in judges.items():
            a = [x for x in aucs if x == x]
            print(f"  argmax {name:28s} RR {wins / n:6.1%}   within-case AUC {np.mean(a) if a else float('nan'):.3f} ({len(a)} cases)")


if __name__ == "__main__":
    main()
