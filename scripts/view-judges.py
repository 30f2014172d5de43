#!/usr/bin/env python3
"""Does the alignment score choose better when it also looks at zoomed views of the image? (issue 29)

Test-time augmentation for the search's choice, replayed from a recording: for every case of a
`cmr-agent eval --record-hypotheses` cases.json, the candidates are the served answer with the
hypotheses' final poses (`finals`), or those with every pose the hypotheses visited (`visited`),
and each rule answers with the candidate whose score is highest:
- `served view`: the learned alignment score (`cmr.state.alignment`, the server's twin: the mean
  over the map's points in view of dot(point feature, image cell feature)) with the image as the server prepares
  it (resize to the model's focal length, centre crop 512 x 160);
- `served + views`: the mean of that score and the same score in each extra view, a zoomed crop of
  the same image (resized `zoom` times more, then cropped at the left edge, centre or right edge)
  read through the image encoder with its own crop intrinsics; the points' features are shared;
- `views only`: the mean over the extra views alone;
- with `--mirror`: the image flipped left to right and the map reflected (`cmr.data.mirror_sample`,
  so a second point-encoder pass), the candidates conjugated alike, added to the served view.
The served answer (the server's polished choice) and the oracle (some candidate registers) are
printed beside them; registered = RTE < 5 m and RRE < 10 deg (`cmr.geometry.registered`). With
`--rigs` (rigs.json of `cmr.real_split`) also per rig. The model set's graphs are imported as
float modules (`cmr.import_onnx`).

    cd training && ../.venv/bin/python ../scripts/view-judges.py ../../shared/real-dev \\
        --perturbations ../docs/eval/real-dev-fleet-seed4404-perturbations.json \\
        --cases /tmp/rec/devf/cases.json --views 1.5:l,1.5:c,1.5:r
"""

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "training"))
from cmr import geometry as g  # noqa: E402
from cmr.data import (FOCAL_RANGE_PX, IMAGE_MEAN, IMAGE_STD, NOMINAL_SCALE, OUT_H, OUT_W, _MIRROR_CAMERA,  # noqa: E402
                      _MIRROR_MAP, _decoded, find_sequences, list_frames, make_sample, mirror_sample)
from cmr.episodes import embed  # noqa: E402
from cmr.state import alignment  # noqa: E402


def parse_views(spec: str) -> list[tuple[float, str]]:
    """"1.5:l,1.5:c" -> [(1.5, "l"), (1.5, "c")]: zoom over the served resize, crop at l / c / r."""
    views = []
    for item in filter(None, spec.split(",")):
        zoom, where = item.split(":")
        if where not in ("l", "c", "r") or float(zoom) < 1.0:
            raise SystemExit(f"--views: {item!r} is not ZOOM:l|c|r with ZOOM >= 1")
        views.append((float(zoom), where))
    return views


def zoomed_views(frame, views) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(image [3, 160, 512] normalised, crop intrinsics fx, fy, cx, cy)] of `frame`, one per view."""
    scale = g.input_scale(NOMINAL_SCALE, FOCAL_RANGE_PX, float(frame.calib.intrinsics[0]))
    served, _, (w, h) = _decoded(frame.image_path, frame.scan_path, scale)
    out = []
    for zoom, where in views:
        zw, zh = g.resized_size(w, h, scale, OUT_W, OUT_H, zoom)
        img = np.asarray(Image.fromarray(served).resize((zw, zh), Image.BILINEAR)) if zoom != 1.0 else served
        rh, rw = img.shape[:2]
        x0 = {"l": 0, "c": (rw - OUT_W) // 2, "r": rw - OUT_W}[where]
        plan = g.preprocess_plan(w, h, scale, OUT_W, OUT_H, (x0, (rh - OUT_H) // 2), zoom)
        rgb = img[plan["crop_y"]:plan["crop_y"] + OUT_H, x0:x0 + OUT_W].astype(np.float32) / 255.0
        out.append((((rgb - IMAGE_MEAN) / IMAGE_STD).transpose(2, 0, 1).astype(np.float32),
                    g.adjust_intrinsics(plan, frame.calib.intrinsics, w, h)))
    return out


@torch.no_grad()
def scores(point_features, points, image_features, k, poses) -> np.ndarray:
    """`cmr.state.alignment` [P] at each camera_from_map of `poses`, one image's features for all."""
    p = len(poses)
    return alignment(torch.as_tensor(np.stack(poses), dtype=torch.float32), points.expand(p, -1, -1),
                     torch.as_tensor(k, dtype=torch.float32)[None].expand(p, -1),
                     point_features[None].expand(p, -1, -1), image_features.expand(p, -1, -1, -1)).numpy()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path, help="the KITTI-layout root the recording was made on")
    ap.add_argument("--perturbations", type=Path, required=True, help="the recording's perturbation file")
    ap.add_argument("--cases", type=Path, required=True, help="cases.json of cmr-agent eval --record-hypotheses")
    ap.add_argument("--models", type=Path, default=Path(__file__).resolve().parent.parent / "models")
    ap.add_argument("--views", default="1.5:l,1.5:c,1.5:r", help="extra views, ZOOM:l|c|r,...")
    ap.add_argument("--mirror", action="store_true", help="also the mirrored image and map")
    ap.add_argument("--rigs", type=Path, help="rigs.json of cmr.real_split: figures per rig too")
    args = ap.parse_args()
    torch.set_num_threads(2)
    from cmr.import_onnx import import_models
    models, _ = import_models(args.models)
    views = parse_views(args.views)
    rig_of = {seq: v["rig"] for seq, v in json.loads(args.rigs.read_text()).items()} if args.rigs else {}
    frames = {(f.image_path.parent.parent.name, int(f.image_path.stem)): f for f in list_frames(find_sequences(args.root))}
    motions = json.loads(args.perturbations.read_text())["cases"]
    records = [r for r in json.loads(args.cases.read_text()) if r["method"] == "cmr-agent"]
    if len(records) != len(motions):
        raise SystemExit(f"{args.cases}: {len(records)} cases, {args.perturbations}: {len(motions)}")
    pose = lambda m: np.vstack([np.asarray(m, float).reshape(3, 4), [0, 0, 0, 1]])  # noqa: E731
    results = defaultdict(lambda: defaultdict(list))  # group -> rule -> [registered]
    view_features = {}  # frame -> [(image features, intrinsics)]: the views do not depend on the case
    for i, (rec, q) in enumerate(zip(records, motions)):
        key = (q["sequence"], q["frame"])
        frame = frames[key]
        motion = g.ground_motion(np.radians(q["yaw_deg"]), q["dx_m"], q["dy_m"])
        sample = make_sample(frame, np.random.default_rng([1234, i]), train=False, motion=motion)
        eps = embed(models, [sample], torch.device("cpu"))
        pf, points = eps.point_features[0].float(), eps.points.float()
        if key not in view_features:
            with torch.no_grad():
                view_features[key] = [(models["image_encoder"](torch.as_tensor(im)[None]), k)
                                      for im, k in zoomed_views(frame, views)]
        if args.mirror:
            mirrored = mirror_sample(sample)
            meps = embed(models, [mirrored], torch.device("cpu"))
        truth, answer = pose(rec["notes"]["truth_camera_from_map"]), pose(rec["notes"]["answer_camera_from_map"])
        hyps = rec["notes"]["hypotheses"]
        finals = [answer] + [pose((h["steps"] or [h["start"]])[-1]["camera_from_map"]) for h in hyps]
        visited = finals + [pose(s["camera_from_map"]) for h in hyps for s in [h["start"]] + h["steps"]]
        outcome = {"served answer": g.registered(answer, truth)}
        for name, cand in (("finals", finals), ("visited", visited)):
            reg = [bool(g.registered(p, truth)) for p in cand]
            served = scores(pf, points, eps.image_features, sample.intrinsics, cand)
            extra = [scores(pf, points, imf, k, cand) for imf, k in view_features[key]]
            outcome[f"{name}: oracle"] = any(reg)
            outcome[f"{name}: served view"] = reg[int(np.argmax(served))]
            if extra:
                outcome[f"{name}: served + views"] = reg[int(np.argmax(np.mean([served] + extra, axis=0)))]
                outcome[f"{name}: views only"] = reg[int(np.argmax(np.mean(extra, axis=0)))]
            if args.mirror:
                conj = [_MIRROR_CAMERA @ p @ _MIRROR_MAP for p in cand]
                mir = scores(meps.point_features[0].float(), meps.points.float(), meps.image_features,
                                mirrored.intrinsics, conj)
                outcome[f"{name}: served + mirror"] = reg[int(np.argmax(served + mir))]
        for group in ("all", rig_of.get(q["sequence"])):
            if group:
                for rule, ok in outcome.items():
                    results[group][rule].append(bool(ok))
        print(f"{i + 1}/{len(records)}", file=sys.stderr, end="\r", flush=True)
    print(file=sys.stderr)
    for group, rules in sorted(results.items(), key=lambda kv: kv[0] != "all"):
        print(f"{group}: " + ", ".join(f"{rule} {sum(v)}/{len(v)}" for rule, v in rules.items()))


if __name__ == "__main__":
    main()
