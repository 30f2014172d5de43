r"""Fit the calibrator of a model set: how likely an answer is right, from the search's own signals.

Reads `cmr-agent eval` outputs (each `cases.json` record of the agent carries `notes.signals`,
the calibrator's inputs, and its final errors), fits a logistic regression of "registered under
protocol A" (RRE Euler sum < 10 deg and RTE < 5 m, `geometry.RR_MAX_*`) on the standardised
signals, chooses the `localized` threshold for a precision of at least 95 % on out-of-fold
predictions, and writes both into the model set's manifest (`calibrator`; every other key is left
as it was, so the graphs' sha256 checks still pass). numpy only.

    cd training
    ../.venv/bin/python -m cmr.calibrate --models ../models --drives /tmp/cal/real-split/rigs.json \
        --cases /tmp/cal/rt-train-paper/cases.json,/tmp/cal/rt-train-fleet/cases.json,...

The model (`model::calibrator` in Rust applies it; `fixtures/calibration.json` pins the two):
x_i = clip((signal_i - mean_i) / std_i, -clip, clip), p = 1 / (1 + exp(-(bias + sum_i weight_i x_i))).
The clamp (default 3 standard deviations) keeps an input unlike any in the fitting data (the
frustum-cropped KITTI-object scans of real-train give a frustum IoU far above any street's) from
pushing p to 0 or 1 by extrapolation; measured on the out-of-fold predictions of the shipped fit,
without it no threshold reached 95 % precision (docs/evaluation.md).

Data rules: fit on frames the model set never trained on and never on the frames kept for checking
it (`../shared/real-dev`): synthetic frames of a fresh seed and `../shared/real-train` (for a model
trained on `real_split`'s train half, its val half only). Both agent methods of an eval (the
served search and the single start) are used, so a request with one start gets a calibrated
probability too.

Threshold: the smallest t such that, on every cases file separately, the out-of-fold precision of
"p >= t" is at least the target at t and at every higher threshold (a file with nothing localized
counts as meeting it); 1.0 (hardly ever localized) when no such t exists. Two thresholds, each
chosen that way on its own answers: `threshold` on those of requests without a prior bound, and
`bounded_threshold` on those of requests that stated one (signal `bounded`), which are right far
more often at the same p (docs/evaluation.md, "A threshold for bounded requests"). Folds (5) never split a
group: a drive (`--drives`, e.g. `real_split`'s rigs.json, for real frames whose drives share
scenes) or a synthetic sequence, across all the files of one data folder.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import sys
from pathlib import Path

import numpy as np

from . import geometry as g
from .files import atomic_write_bytes, git_commit

# model::calibrator::SIGNAL_NAMES, in its order.
SIGNALS = ("alignment", "alignment_gain", "alignment_margin", "agreement", "frustum_iou", "policy_certainty", "converged",
           "steps_fraction", "in_view", "log2_starts", "bounded", "visit_share", "peak_margin")
# Signals that records written before them lack, with the value they stood for then (Rust's
# `#[serde(default)]` on the same fields): no bound was stated before `bounded` existed.
SIGNAL_DEFAULTS = {"bounded": 0.0}
# The eval methods whose records are fitted (eval::learned::AGENT, AGENT_SINGLE_START).
METHODS = ("cmr-agent", "cmr-agent, single start")
TARGET = "registered: the answer's rotation error (sum of absolute Euler angles) < 10 deg and translation error < 5 m (protocol A)"
RELIABILITY_BINS = 10  # eval::calibration::RELIABILITY_BINS


def registered(error: dict) -> bool:
    """Protocol A on one eval error record ({rte_m, rre_euler_deg, ...}): geometry.registered's test."""
    return error["rte_m"] < g.RR_MAX_TRANSLATION_M and error["rre_euler_deg"] < g.RR_MAX_ROTATION_DEG


def load_cases(paths: list[Path], drives: dict[str, str] | None = None) -> dict:
    """The fitting rows of `paths` (cases.json files of `cmr-agent eval`).

    Returns {"x": [n, len(SIGNALS)] float64, "y": [n] bool, "file": [n] int (index into paths),
    "group": [n] str (data folder + drive or sequence), "method": [n] str}.
    Raises ValueError when a file has no agent record with signals (an eval older than the
    calibrator, or a run with --reference-only) or records lacking one of SIGNALS that has no
    historical default (an eval older than that signal)."""
    rows = {"x": [], "y": [], "file": [], "group": [], "method": []}
    for i, path in enumerate(paths):
        records = json.loads(Path(path).read_text())
        report = Path(path).with_name("eval.json")
        data = json.loads(report.read_text())["data"] if report.is_file() else str(Path(path).parent)
        kept = [r for r in records if r["method"] in METHODS and "signals" in r.get("notes", {})]
        if not kept:
            raise ValueError(f"{path}: no agent records with notes.signals")
        sequences = {r["sequence"] for r in kept}
        by_drive = drives is not None and sequences <= set(drives)
        for r in kept:
            signals = {**SIGNAL_DEFAULTS, **r["notes"]["signals"]}
            missing = [name for name in SIGNALS if name not in signals]
            if missing:
                raise ValueError(f"{path}: records without the signals {missing} (an eval older than them: run it again)")
            rows["x"].append([float(signals[name]) for name in SIGNALS])
            rows["y"].append(registered(r["errors"][-1]))
            rows["file"].append(i)
            rows["group"].append(f"{data}:{drives[r['sequence']] if by_drive else r['sequence']}")
            rows["method"].append(r["method"])
    out = {k: np.asarray(v) for k, v in rows.items()}
    out["x"] = out["x"].astype(np.float64).reshape(-1, len(SIGNALS))
    out["y"] = out["y"].astype(bool)
    return out


def standardisation(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column mean and standard deviation of x [n, d]; a constant column gets std 1."""
    mean = x.mean(axis=0)
    std = x.std(axis=0)
    return mean, np.where(std > 1e-12, std, 1.0)


def fit_logistic(z: np.ndarray, y: np.ndarray, l2: float = 1.0, iterations: int = 100) -> tuple[np.ndarray, float]:
    """Maximum a posteriori logistic regression by Newton's method.

    z [n, d] standardised inputs, y [n] bool. Minimises the mean log loss plus l2 / (2 n) |w|^2
    (the intercept is not penalised), so l2 is a prior worth l2 cases. Returns (w [d], bias)."""
    n, d = z.shape
    a = np.hstack([z, np.ones((n, 1))])
    t = y.astype(np.float64)
    beta = np.zeros(d + 1)
    penalty = np.full(d + 1, l2 / n)
    penalty[-1] = 0.0
    for _ in range(iterations):
        p = 1.0 / (1.0 + np.exp(-(a @ beta)))
        grad = a.T @ (p - t) / n + penalty * beta
        hess = (a * (p * (1 - p))[:, None]).T @ a / n + np.diag(penalty) + 1e-9 * np.eye(d + 1)
        step = np.linalg.solve(hess, grad)
        beta -= step
        if np.max(np.abs(step)) < 1e-10:
            break
    return beta[:-1], float(beta[-1])


def probability(calibrator: dict, signals: np.ndarray) -> np.ndarray:
    """p_registered of rows of signals [n, len(SIGNALS)] (columns in SIGNALS order) under a manifest
    `calibrator` section: the twin of Rust's `Calibrator::probability`."""
    cols = [SIGNALS.index(name) for name in calibrator["features"]]
    clip = calibrator.get("clip") or np.inf
    z = np.clip((signals[:, cols] - np.asarray(calibrator["mean"])) / np.asarray(calibrator["std"]), -clip, clip)
    return 1.0 / (1.0 + np.exp(-(calibrator["bias"] + z @ np.asarray(calibrator["weights"]))))


def thresholds(calibrator: dict, signals: np.ndarray) -> np.ndarray:
    """The threshold each row of signals [n, len(SIGNALS)] must meet to be `localized`: the twin of
    Rust's `Calibration::judge` (`bounded_threshold` for a bounded request when the section has
    one, else `threshold`)."""
    bounded = signals[:, SIGNALS.index("bounded")] > 0.5
    return np.where(bounded, calibrator.get("bounded_threshold", calibrator["threshold"]), calibrator["threshold"])


def brier(p: np.ndarray, y: np.ndarray) -> float:
    """Mean (p - y)^2: eval::calibration::brier."""
    return float(np.mean((p - y.astype(np.float64)) ** 2))


def auc(p: np.ndarray, y: np.ndarray) -> float | None:
    """Area under the ROC curve, ties counted half (Mann-Whitney); None with one kind of case."""
    pos, neg = int(y.sum()), int((~y).sum())
    if pos == 0 or neg == 0:
        return None
    order = np.argsort(p, kind="stable")
    ranks = np.empty(len(p))
    sorted_p = p[order]
    i = 0
    while i < len(p):
        j = i
        while j + 1 < len(p) and sorted_p[j + 1] == sorted_p[i]:
            j += 1
        ranks[order[i:j + 1]] = (i + j + 2) / 2.0
        i = j + 1
    return float((ranks[y].sum() - pos * (pos + 1) / 2.0) / (pos * neg))


def reliability_bins(p: np.ndarray, y: np.ndarray) -> list[dict]:
    """The equal-width bins of eval::calibration::reliability_bins: [{lower, upper, cases, mean_p, registered_share}]."""
    k = RELIABILITY_BINS
    index = np.minimum(np.floor(p * k).astype(int), k - 1)
    bins = []
    for b in range(k):
        m = index == b
        n = int(m.sum())
        bins.append(dict(lower=b / k, upper=(b + 1) / k, cases=n, mean_p=float(p[m].mean()) if n else 0.0,
                         registered_share=float(y[m].mean()) if n else 0.0))
    return bins


def scores(p: np.ndarray, y: np.ndarray, threshold: float | np.ndarray) -> dict:
    """The figures of eval::calibration::CalibrationReport (without method and bins) for p [n], y [n]
    bool, at one threshold or one per row (`thresholds`; reported as the sorted distinct values)."""
    n = len(p)
    localized = p >= threshold
    rate = float(y.mean()) if n else 0.0
    bins = reliability_bins(p, y)
    distinct = sorted({float(t) for t in np.broadcast_to(threshold, p.shape)})
    return dict(
        threshold=distinct[0] if len(distinct) == 1 else distinct, cases=n, registered=int(y.sum()), localized=int(localized.sum()),
        localized_registered=int((localized & y).sum()),
        precision=float((localized & y).sum() / localized.sum()) if localized.any() else None,
        recall=float((localized & y).sum() / y.sum()) if y.any() else None,
        brier=brier(p, y), brier_base_rate=rate * (1 - rate), auc=auc(p, y),
        ece=float(sum(b["cases"] / n * abs(b["mean_p"] - b["registered_share"]) for b in bins)) if n else 0.0)


def smallest_safe_threshold(p: np.ndarray, y: np.ndarray, candidates: np.ndarray, target: float) -> float:
    """The smallest candidate t with precision(p >= t') >= target for every candidate t' >= t
    (no case localized counts as meeting it); the candidates are sorted ascending and end with 1.0."""
    safe = 1.0
    for t in candidates[::-1]:
        localized = p >= t
        if localized.any() and (localized & y).sum() / localized.sum() < target:
            break
        safe = float(t)
    return safe


def recall_ceiling(p: np.ndarray, y: np.ndarray, target: float) -> float | None:
    """The highest recall that any one threshold on p [n] reaches with precision(p >= t) >= target
    on these same rows (y [n] bool; tied p count together); None when no row is registered.

    The threshold is chosen on the rows it is scored on, so this is a ceiling, not a result: what
    the signals behind p could give at best. When it is below a recall bar, no threshold rule
    meets that bar with these signals; better signals (a better model) are needed."""
    if not y.any():
        return None
    order = np.argsort(-p, kind="stable")
    ps, hits = p[order], np.cumsum(y[order])
    last_of_tie = np.r_[ps[1:] != ps[:-1], True]
    safe = last_of_tie & (hits / np.arange(1, len(ps) + 1) >= target)  # as smallest_safe_threshold
    return float(hits[safe].max() / y.sum()) if safe.any() else 0.0


def folds_of(groups: np.ndarray, k: int, seed: int) -> np.ndarray:
    """Fold index [n] per row: whole groups, shuffled with `seed`, dealt round-robin into k folds."""
    names = sorted(set(groups.tolist()))
    rng = np.random.default_rng(seed)
    rng.shuffle(names)
    fold = {name: i % k for i, name in enumerate(names)}
    return np.array([fold[gname] for gname in groups])


def fit(rows: dict, features: tuple[str, ...] = SIGNALS, l2: float = 1.0, k: int = 5, seed: int = 0,
        target_precision: float = 0.95, clip: float | None = 3.0) -> tuple[dict, dict]:
    """Fits on `rows` (load_cases): returns (calibrator section without provenance, out-of-fold report).

    The report holds the out-of-fold p [n] ("p"), the threshold, per cases file and pooled the
    `scores` at that threshold, and per cases file the `recall_ceiling` of the out-of-fold p at the
    target precision."""
    cols = [SIGNALS.index(name) for name in features]
    x, y = rows["x"][:, cols], rows["y"]

    def train(mask):
        mean, std = standardisation(x[mask])
        z = (x[mask] - mean) / std
        if clip is not None:
            z = np.clip(z, -clip, clip)
        w, b = fit_logistic(z, y[mask], l2)
        section = dict(kind="logistic", target=TARGET, features=list(features), mean=mean.tolist(), std=std.tolist(),
                       weights=w.tolist(), bias=b)
        if clip is not None:
            section["clip"] = clip
        return section

    folds = folds_of(rows["group"], k, seed)
    oof = np.empty(len(y))
    for f in range(k):
        held = folds == f
        if held.any():
            oof[held] = probability(train(~held), rows["x"][held])
    candidates = np.unique(np.concatenate([oof, [1.0]]))
    in_file = {int(i): rows["file"] == i for i in sorted(set(rows["file"].tolist()))}
    bounded = rows["x"][:, SIGNALS.index("bounded")] > 0.5

    def safe(kind: np.ndarray) -> float:
        """The threshold every file's answers of this kind meet."""
        masks = [m for m in (f & kind for f in in_file.values()) if m.any()]
        return max((smallest_safe_threshold(oof[m], y[m], candidates, target_precision) for m in masks), default=1.0)

    calibrator = train(np.ones(len(y), bool))
    calibrator["threshold"] = safe(~bounded)
    if bounded.any():
        calibrator["bounded_threshold"] = safe(bounded)
    t = thresholds(calibrator, rows["x"])
    report = dict(p=oof, threshold=calibrator["threshold"], bounded_threshold=calibrator.get("bounded_threshold"),
                  pooled=scores(oof, y, t),
                  per_file={i: scores(oof[f], y[f], t[f]) for i, f in in_file.items()},
                  recall_ceiling={i: recall_ceiling(oof[f], y[f], target_precision) for i, f in in_file.items()})
    return calibrator, report


def eval_run(cases: Path) -> dict:
    """What made a cases.json: its eval.json's data, perturbations, models and command ({} without one)."""
    report = Path(cases).with_name("eval.json")
    if not report.is_file():
        return {}
    doc = json.loads(report.read_text())
    return {key: doc.get(key) for key in ("data", "perturbations", "models", "command")}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", required=True, help="comma-separated cases.json files of cmr-agent eval")
    ap.add_argument("--models", type=Path, required=True, help="model set whose manifest.json gets the calibrator")
    ap.add_argument("--drives", type=Path, help="sequence -> {drive} JSON (cmr.real_split's rigs.json): folds by drive")
    ap.add_argument("--features", default=",".join(SIGNALS), help="signals to use (default: all)")
    ap.add_argument("--l2", type=float, default=1.0, help="ridge prior on the standardised weights, in cases")
    ap.add_argument("--clip", type=float, default=3.0, help="clamp of each standardised signal (0: none)")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--target-precision", type=float, default=0.95)
    ap.add_argument("--dry-run", action="store_true", help="print the calibrator, do not write the manifest")
    args = ap.parse_args(argv)
    paths = [Path(p) for p in args.cases.split(",") if p]
    drives = None
    if args.drives:
        drives = {seq: row["drive"] for seq, row in json.loads(args.drives.read_text()).items()}
    features = tuple(f for f in args.features.split(",") if f)
    unknown = set(features) - set(SIGNALS)
    if unknown:
        sys.exit(f"unknown signals {sorted(unknown)}; known: {SIGNALS}")
    rows = load_cases(paths, drives)
    calibrator, report = fit(rows, features, args.l2, args.folds, args.seed, args.target_precision, args.clip or None)
    calibrator["provenance"] = dict(
        data=[dict(cases=str(p), **eval_run(p), records=int((rows["file"] == i).sum()),
                   registered=int(rows["y"][rows["file"] == i].sum())) for i, p in enumerate(paths)],
        methods=list(METHODS),
        command="python -m cmr.calibrate " + " ".join(argv if argv is not None else sys.argv[1:]),
        created=_dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
        git_commit=git_commit(),
        fit=dict(l2=args.l2, clip=args.clip or None, folds=args.folds, seed=args.seed, target_precision=args.target_precision,
                 groups=len(set(rows["group"].tolist()))),
        out_of_fold=dict(pooled=report["pooled"], per_file={str(paths[i]): s for i, s in report["per_file"].items()},
                         recall_ceiling={str(paths[i]): r for i, r in report["recall_ceiling"].items()}),
    )
    text = json.dumps(calibrator, indent=2)
    print(text)
    if args.dry_run:
        return
    path = args.models / "manifest.json"
    doc = json.loads(path.read_text())
    doc["calibrator"] = calibrator
    atomic_write_bytes(path, (json.dumps(doc, indent=2) + "\n").encode())
    print(f"wrote the calibrator into {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
