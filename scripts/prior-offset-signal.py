#!/usr/bin/env python3
"""Measures whether the answer's offset from the request's prior would help the calibrator
(issue 30): fits `cmr.calibrate.fit` on the same rows with and without one more signal,
`prior_offset` = log(1 + max(RRE / 30 deg, RTE / 5 m)) between the answer and the prior (RRE
geodesic, RTE the camera_from_map translation difference, as `cmr-agent eval` measures errors), and
prints the out-of-fold scores of both (folds by sequence, as `cmr.calibrate` makes them).

    .venv/bin/python scripts/prior-offset-signal.py EVAL_ROOT NAME=PERTURBATIONS.json [...]

Each NAME is a `cmr-agent eval --out EVAL_ROOT/NAME` folder of the served set (any eval output,
`--no-baseline` included: the no-op records are what the prior is checked against) and
PERTURBATIONS the case file it ran; e.g. EVAL_ROOT `$RUN/judge/shipped` of `scripts/train-v7.sh
judge models shipped fresh-...` with NAME `fresh-rtv-fleet-bound` and its file.
The prior is the truth moved by the case's map motion (`Perturbation::truth` inverted); each row's
prior is checked against the no-op's error. Exploratory: nothing here is served.
"""
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))
import cmr.calibrate as cal  # noqa: E402
from cmr import geometry as g  # noqa: E402


def pose(flat) -> np.ndarray:
    return np.vstack([np.asarray(flat, float).reshape(3, 4), [0, 0, 0, 1]])


def main() -> None:
    if len(sys.argv) < 3 or any("=" not in a for a in sys.argv[2:]):
        sys.exit(__doc__.split("\n\n")[1] + "\n(needs EVAL_ROOT and at least one NAME=PERTURBATIONS.json)")
    root, pairs = Path(sys.argv[1]), [a.split("=", 1) for a in sys.argv[2:]]
    extra, paths = [], []
    for name, pert in pairs:
        cases = json.loads(Path(pert).read_text())["cases"]
        records = json.loads((root / name / "cases.json").read_text())
        paths.append(root / name / "cases.json")
        noop = [r for r in records if r["method"] == "no-op"]
        kept = [r for r in records if r["method"] in cal.METHODS and "signals" in r.get("notes", {})]
        per_method = {m: iter(zip(cases, noop)) for m in cal.METHODS}
        for r in kept:
            case, n = next(per_method[r["method"]])
            assert (r["sequence"], r["frame"]) == (case["sequence"], case["frame"])
            truth, answer = pose(r["notes"]["truth_camera_from_map"]), pose(r["notes"]["answer_camera_from_map"])
            prior = truth @ g.ground_motion(math.radians(case["yaw_deg"]), case["dx_m"], case["dy_m"])
            assert abs(g.pose_error(prior, truth)["rte_m"] - n["errors"][-1]["rte_m"]) < 1e-3, "the prior does not match the no-op"
            e = g.pose_error(answer, prior)
            extra.append((e["rre_geodesic_deg"], e["rte_m"]))
    rows = cal.load_cases(paths)
    ex = np.asarray(extra)
    assert len(ex) == len(rows["y"])
    cal.SIGNALS = cal.SIGNALS + ("prior_offset",)
    rows["x"] = np.concatenate([rows["x"], np.log1p(np.maximum(ex[:, 0] / 30.0, ex[:, 1] / 5.0))[:, None]], 1)
    served = rows["method"] == "cmr-agent"
    for features in (cal.SIGNALS[:-1], cal.SIGNALS):
        c, rep = cal.fit(rows, features=features)
        p, y, s = rep["p"], rows["y"], rep["pooled"]
        print(f"{len(features)} signals{' + prior_offset' if 'prior_offset' in features else ''}: out-of-fold pooled "
              f"precision {s['precision']:.3f} recall {s['recall']:.3f} Brier {s['brier']:.3f} (base rate {s['brier_base_rate']:.3f}) "
              f"AUC {s['auc']:.3f}; served answers AUC {cal.auc(p[served], y[served]):.3f}; thresholds "
              f"{c['threshold']:.3f} / bounded {c.get('bounded_threshold', 1.0):.3f}; prior_offset weight "
              f"{c['weights'][-1] if 'prior_offset' in features else 0:.2f}")


if __name__ == "__main__":
    main()
