//! Pins the calibrator across languages: Python fits it (`training/cmr/calibrate.py`), Rust applies
//! it (`model::calibrator`), and both score it (`eval::calibration`).
//!
//! `fixtures/calibration.json` holds a calibrator, signals and the p_registered this crate
//! computes for them, and a scored set with the figures this crate gives it;
//! `training/tests/test_calibrate.py` checks the Python twins against the same file. Regenerate
//! (after a deliberate change) with `REGENERATE_FIXTURES=1 cargo test --test calibration_fixture`.

use cmr_agent::eval::calibration::{CalibrationReport, Judged};
use cmr_agent::model::calibrator::{Calibration, Calibrator, LOGISTIC, SIGNAL_NAMES, Signals};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};

mod common;

const FIXTURE: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/calibration.json");

fn calibrator() -> Calibrator {
    Calibrator {
        kind: LOGISTIC.into(),
        target: "fixture".into(),
        // Not every signal, and not in SIGNAL_NAMES order: the names pick the columns.
        features: ["in_view", "alignment", "agreement", "alignment_margin", "policy_certainty", "converged", "log2_starts", "alignment_gain", "bounded", "visit_share", "peak_margin"].map(String::from).to_vec(),
        mean: vec![0.2, 0.45, 0.3, 0.05, 0.6, 0.4, 1.0, 0.1, 0.3, 0.3, 0.02],
        std: vec![0.1, 0.15, 0.35, 0.08, 0.2, 0.49, 1.0, 0.15, 0.46, 0.2, 0.03],
        weights: vec![-0.15, 0.9, 0.4, 0.3, 0.2, -0.1, 0.25, 0.3, 0.5, 0.6, 0.7],
        bias: -0.3,
        // Tight enough that some of the random signals below are cut.
        clip: Some(1.5),
        threshold: 0.7,
        // Below `threshold`, so some bounded cases are localized that an unbounded one would not be.
        bounded_threshold: Some(0.45),
        provenance: json!({"command": "tests/calibration_fixture.rs"}),
    }
}

fn random_signals(rng: &mut ChaCha8Rng) -> Signals {
    Signals {
        alignment: rng.random_range(-0.2..0.9),
        alignment_gain: rng.random_range(-0.2..0.5),
        alignment_margin: rng.random_range(-0.1..0.4),
        agreement: [0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0][rng.random_range(0..4)],
        frustum_iou: rng.random_range(0.0..0.7),
        policy_certainty: rng.random_range(0.2..1.0),
        converged: if rng.random_bool(0.5) { 1.0 } else { 0.0 },
        steps_fraction: rng.random_range(0..=10) as f64 / 10.0,
        in_view: rng.random_range(0.0..0.5),
        log2_starts: if rng.random_bool(0.5) { 0.0 } else { 2.0 },
        bounded: if rng.random_bool(0.3) { 1.0 } else { 0.0 },
        visit_share: rng.random_range(0..=40) as f64 / 40.0,
        peak_margin: rng.random_range(-0.02..0.1),
    }
}

fn compute() -> Value {
    let mut rng = ChaCha8Rng::seed_from_u64(30);
    let c = calibrator();
    let verdicts = Calibration::new(Some(&c), None);
    let cases: Vec<Value> = (0..24)
        .map(|_| {
            let s = random_signals(&mut rng);
            let v = verdicts.judge(&s);
            json!({"signals": s, "p_registered": c.probability(&s).unwrap(), "localized": v.localized})
        })
        .collect();
    // A scored set: p with ties and both outcomes.
    let threshold = 0.6;
    let judged: Vec<Judged> = (0..40)
        .map(|_| {
            let p = (rng.random_range(0.0f64..1.0) * 20.0).round() / 20.0;
            Judged { p, localized: p >= threshold, registered: rng.random_bool(p.clamp(0.05, 0.95)) }
        })
        .collect();
    let report = CalibrationReport::of("fixture", threshold, &judged);
    json!({
        "signal_names": SIGNAL_NAMES,
        "calibrator": c,
        "cases": cases,
        "scored": {
            "p": judged.iter().map(|j| j.p).collect::<Vec<_>>(),
            "registered": judged.iter().map(|j| j.registered).collect::<Vec<_>>(),
            "threshold": threshold,
            "report": report,
        },
    })
}

#[test]
fn calibrator_matches_the_shared_fixture() {
    let computed = compute();
    let stored = common::stored_fixture(FIXTURE, &computed, |v| serde_json::to_string_pretty(v).unwrap());
    common::assert_json_close(&stored, &computed, 1e-12, "fixture");
    // The stored calibrator is one this build accepts.
    let c: Calibrator = serde_json::from_value(stored["calibrator"].clone()).unwrap();
    assert_eq!(c.validate(), Ok(()));
}
