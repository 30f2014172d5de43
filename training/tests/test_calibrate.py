"""The calibrator: fitting recovers a known relation, the Python twins agree with Rust on the shared
fixture, the threshold rule holds, and the command rewrites only the manifest's calibrator."""

import json
from pathlib import Path

import numpy as np
import pytest

from cmr import calibrate as c

FIXTURE = json.loads((Path(__file__).resolve().parents[2] / "fixtures" / "calibration.json").read_text())
REPO = Path(__file__).resolve().parents[2]


def test_signal_names_are_rusts():
    assert tuple(FIXTURE["signal_names"]) == c.SIGNALS


def test_probability_matches_rust():
    cal = FIXTURE["calibrator"]
    signals = np.array([[case["signals"][name] for name in c.SIGNALS] for case in FIXTURE["cases"]])
    expected = np.array([case["p_registered"] for case in FIXTURE["cases"]])
    assert np.allclose(c.probability(cal, signals), expected, rtol=1e-12, atol=1e-15)
    assert np.mean((expected > 0.05) & (expected < 0.95)) > 0.75  # the cases span the curve, not its flat ends


def test_localized_matches_rust():
    """Each case meets its own threshold: `bounded_threshold` for a bounded request."""
    cal = FIXTURE["calibrator"]
    signals = np.array([[case["signals"][name] for name in c.SIGNALS] for case in FIXTURE["cases"]])
    localized = c.probability(cal, signals) >= c.thresholds(cal, signals)
    assert localized.tolist() == [case["localized"] for case in FIXTURE["cases"]]
    p, bounded = c.probability(cal, signals), signals[:, c.SIGNALS.index("bounded")] > 0.5
    assert (bounded & (p >= cal["bounded_threshold"]) & (p < cal["threshold"])).any(), "the fixture exercises the bounded threshold"


def test_scores_match_rust():
    s = FIXTURE["scored"]
    p, y = np.array(s["p"]), np.array(s["registered"], dtype=bool)
    got = c.scores(p, y, s["threshold"])
    want = s["report"]
    for key, value in got.items():
        if value is None or want[key] is None:
            assert value is None and want[key] is None, key
        else:
            assert value == pytest.approx(want[key], abs=1e-12), key
    assert c.reliability_bins(p, y) == pytest.approx(want["bins"], abs=1e-12)


def test_fit_recovers_a_known_relation():
    """Standardised signals with a known logistic relation: the fit finds its weights and bias,
    and the probabilities it gives are calibrated."""
    rng = np.random.default_rng(3)
    n = 40_000
    x = np.column_stack([rng.normal(0.5, 0.2, n), rng.uniform(0, 1, n), rng.integers(0, 2, n).astype(float)])
    mean, std = c.standardisation(x)
    w_true, b_true = np.array([1.5, -0.8, 0.0]), -0.4
    p_true = 1 / (1 + np.exp(-(b_true + ((x - mean) / std) @ w_true)))
    y = rng.uniform(size=n) < p_true
    w, b = c.fit_logistic((x - mean) / std, y, l2=1.0)
    assert np.allclose(w, w_true, atol=0.05) and abs(b - b_true) < 0.05, (w, b)
    cal = dict(features=["alignment", "agreement", "converged"], mean=mean.tolist(), std=std.tolist(), weights=w.tolist(), bias=b)
    signals = np.zeros((n, len(c.SIGNALS)))
    signals[:, [c.SIGNALS.index(f) for f in cal["features"]]] = x
    p = c.probability(cal, signals)
    assert c.scores(p, y, 0.5)["ece"] < 0.02
    assert c.brier(p, y) < c.scores(p, y, 0.5)["brier_base_rate"]


def test_the_threshold_holds_the_precision_at_and_above_it():
    p = np.array([0.95, 0.9, 0.85, 0.8, 0.7, 0.6, 0.5, 0.3])
    y = np.array([True, True, False, True, True, True, False, False])
    candidates = np.unique(np.concatenate([p, [1.0]]))
    # Precision of p >= t from the top: 1, 1, 2/3, 3/4, 4/5, 5/6, 5/7, 5/8.
    assert c.smallest_safe_threshold(p, y, candidates, 0.75) == 0.9  # 2/3 at 0.85: nothing below 0.9 is safe
    assert c.smallest_safe_threshold(p, y, candidates, 0.66) == 0.5  # 5/8 at 0.3
    assert c.smallest_safe_threshold(p, y, candidates, 0.6) == 0.3
    assert c.smallest_safe_threshold(p, np.zeros_like(y), candidates, 0.95) == 1.0  # nothing is ever right


def test_the_recall_ceiling_is_the_best_any_threshold_reaches():
    p = np.array([0.95, 0.9, 0.85, 0.8, 0.7, 0.6, 0.5, 0.3])
    y = np.array([True, True, False, True, True, True, False, False])
    # Precision of p >= t from the top: 1, 1, 2/3, 3/4, 4/5, 5/6, 5/7, 5/8; recall k/5.
    assert c.recall_ceiling(p, y, 0.8) == 1.0  # 5/6 at 0.6
    assert c.recall_ceiling(p, y, 0.9) == 0.4  # only the top two
    assert c.recall_ceiling(p, y, 1.0) == 0.4
    # Tied scores go in or out together: the top three tie, one of them wrong.
    assert c.recall_ceiling(np.array([0.9, 0.9, 0.9, 0.1]), np.array([True, True, False, True]), 0.9) == 0.0
    assert c.recall_ceiling(p, np.zeros_like(y), 0.95) is None
    # Whatever the threshold rule picks, its recall on the same rows is never above the ceiling.
    rng = np.random.default_rng(3)
    p, y = rng.uniform(size=200), rng.uniform(size=200) < 0.5
    candidates = np.unique(np.concatenate([p, [1.0]]))
    t = c.smallest_safe_threshold(p, y, candidates, 0.6)
    assert (c.scores(p, y, t)["recall"] or 0.0) <= c.recall_ceiling(p, y, 0.6)


def _cases_json(path: Path, rng, n: int, data: str) -> Path:
    """A cases.json (and eval.json) as cmr-agent eval writes them, with signals that predict the outcome."""
    records = []
    for i in range(n):
        good = rng.uniform() < 0.4
        signals = {name: float(rng.uniform()) for name in c.SIGNALS}
        signals["alignment"] = float(rng.normal(0.6 if good else 0.35, 0.08))
        err = dict(rte_m=0.5 if good else 12.0, rre_euler_deg=2.0 if good else 90.0, rre_geodesic_deg=2.0)
        for method in c.METHODS:
            records.append(dict(sequence=f"{i % 7:02d}", frame=i, method=method, errors=[err], elapsed_ms=[1.0],
                                phases_ms={}, notes=dict(signals=signals, p_registered=None, localized=False)))
        records.append(dict(sequence="00", frame=i, method="no-op", errors=[err], elapsed_ms=[0.0], phases_ms={}))
    path.mkdir(parents=True)
    (path / "cases.json").write_text(json.dumps(records))
    (path / "eval.json").write_text(json.dumps(dict(data=data)))
    return path / "cases.json"


def test_the_command_writes_only_the_calibrator(tmp_path):
    rng = np.random.default_rng(5)
    files = [_cases_json(tmp_path / name, rng, 150, data) for name, data in (("a", "synth"), ("b", "synth"), ("c", "real"))]
    models = tmp_path / "models"
    models.mkdir()
    original = (REPO / "tests" / "fixtures" / "tiny-model" / "manifest.json").read_text()
    (models / "manifest.json").write_text(original)
    c.main(["--cases", ",".join(map(str, files)), "--models", str(models), "--features", "alignment,agreement"])
    doc = json.loads((models / "manifest.json").read_text())
    cal = doc.pop("calibrator")
    assert doc == json.loads(original)
    assert cal["features"] == ["alignment", "agreement"] and cal["kind"] == "logistic"
    assert cal["weights"][0] > 1.0  # alignment carries the outcome
    assert 0.5 < cal["threshold"] <= 1.0
    oof = cal["provenance"]["out_of_fold"]
    assert oof["pooled"]["cases"] == 900 and oof["pooled"]["auc"] > 0.9
    for scores in oof["per_file"].values():
        assert scores["precision"] is None or scores["precision"] >= 0.95
    assert [d["records"] for d in cal["provenance"]["data"]] == [300, 300, 300]


def test_bounded_requests_get_their_own_threshold():
    """Answers of bounded requests are right more often at the same p: their threshold is chosen on
    them alone, each kind keeps the target precision out of fold in every file, and `thresholds`
    (the twin of Rust's `Calibration::judge`) gives each row its own."""
    rng = np.random.default_rng(11)
    n = 1200
    bounded = rng.uniform(size=n) < 0.5
    good = rng.uniform(size=n) < np.where(bounded, 0.7, 0.3)
    x = rng.uniform(size=(n, len(c.SIGNALS)))
    x[:, c.SIGNALS.index("bounded")] = bounded
    # unbounded answers: a noisy score; bounded ones: the same score, cleanly separated
    x[:, c.SIGNALS.index("alignment")] = np.where(good, 0.6, 0.4) + rng.normal(0, np.where(bounded, 0.05, 0.12))
    rows = dict(x=x, y=good, file=np.arange(n) % 2, group=np.array([f"g{i % 40}" for i in range(n)]),
                method=np.array(["cmr-agent"] * n))
    cal, report = c.fit(rows, features=("alignment", "bounded"))
    assert 0.0 < cal["bounded_threshold"] < cal["threshold"] <= 1.0, cal
    t = c.thresholds(cal, x)
    assert np.array_equal(t, np.where(bounded, cal["bounded_threshold"], cal["threshold"]))
    localized = report["p"] >= t
    for f in (0, 1):
        for kind in (bounded, ~bounded):
            m = (rows["file"] == f) & kind & localized
            assert m.sum() > 0 and good[m].mean() >= 0.95
    # bounded answers localized at their own threshold that the single one would not vouch for
    assert (localized & bounded & (report["p"] < cal["threshold"])).sum() > 20
    assert report["pooled"]["threshold"] == sorted([cal["bounded_threshold"], cal["threshold"]])
    # a section without the field: every row meets `threshold`
    plain = {k: v for k, v in cal.items() if k != "bounded_threshold"}
    assert np.all(c.thresholds(plain, x) == cal["threshold"])


def test_folds_keep_groups_whole():
    groups = np.array(["a", "b", "a", "c", "d", "b", "e", "a"])
    folds = c.folds_of(groups, 3, 0)
    for name in set(groups):
        assert len(set(folds[groups == name])) == 1
    assert set(folds) == {0, 1, 2}


def test_records_older_than_a_signal_are_refused_not_filled_in(tmp_path):
    """A cases.json written before `visit_share` or `peak_margin` existed cannot be fitted on (0
    would be a guess); one written before `bounded` can (no bound could be stated then)."""
    path = _cases_json(tmp_path / "a", np.random.default_rng(6), 10, "synth")
    records = json.loads(path.read_text())
    for r in records:
        r.get("notes", {}).get("signals", {}).pop("bounded", None)
    path.write_text(json.dumps(records))
    assert c.load_cases([path])["x"][:, c.SIGNALS.index("bounded")].tolist() == [0.0] * 20
    for r in records:
        r.get("notes", {}).get("signals", {}).pop("visit_share", None)
    path.write_text(json.dumps(records))
    with pytest.raises(ValueError, match="visit_share"):
        c.load_cases([path])
    for r in records:
        r.get("notes", {}).get("signals", {}).pop("peak_margin", None)
    path.write_text(json.dumps(records))
    with pytest.raises(ValueError, match="peak_margin"):
        c.load_cases([path])
