//! The calibrator: how likely an answer is right, from signals the search already has.
//!
//! A model set's manifest may carry a `calibrator` section: a logistic regression over a few
//! standardised [`Signals`] of one localization, fitted offline on `cmr-agent eval` outputs
//! (`python -m cmr.calibrate`, training/cmr/calibrate.py, its twin; `fixtures/calibration.json`
//! pins both), and the threshold above which an answer is called `localized`. With
//! x_i = clamp((signal_i − mean_i) / std_i, −clip, clip) (no clamp when `clip` is absent),
//!
//! ```text
//! p_registered = 1 / (1 + exp(−(bias + Σ_i weight_i · x_i)))
//! ```
//!
//! is the probability that the answered pose is registered under the paper's protocol A (rotation
//! error, Euler sum, < 10° and translation error < 5 m: `geometry::metrics::RR_MAX_*`). The server
//! (`serving::Localizer`) and `cmr-agent eval` both turn a localization into a [`Verdict`] with
//! [`Calibration::judge`]; nothing else computes it.
//!
//! A manifest without the section (every model set before issue 30) has no calibration: every
//! verdict is `p_registered: None, localized: false` ("no answer is vouched for"), never a guess.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// The signals a calibrator may read, by name (the manifest's `calibrator.features`, Python's
/// `cmr.calibrate.SIGNALS`). What each one means is on the fields of [`Signals`].
pub const SIGNAL_NAMES: [&str; 13] = [
    "alignment",
    "alignment_gain",
    "alignment_margin",
    "agreement",
    "frustum_iou",
    "policy_certainty",
    "converged",
    "steps_fraction",
    "in_view",
    "log2_starts",
    "bounded",
    "visit_share",
    "peak_margin",
];

/// The only calibrator kind this build applies.
pub const LOGISTIC: &str = "logistic";

/// What one localization says about itself, all computed by `agent::Localization::signals` from
/// the finished search (unitless; none depends on the map frame).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Signals {
    /// The answer's alignment score (`agent::state::alignment`: mean dot product of unit point and
    /// image embeddings over the points in view, in [−1, 1]; −1 with nothing in view).
    pub alignment: f64,
    /// The answer's alignment minus the mean alignment of the search's starts (the prior turned
    /// by k·360°/H, mostly wrong poses): the score over this image's own baseline, since the
    /// alignment's scale differs from image to image and rig to rig.
    pub alignment_gain: f64,
    /// The answer's alignment minus the best final alignment of the other starts (0 with one
    /// start): how clearly the answer won the search.
    pub alignment_margin: f64,
    /// Share of the other starts whose final pose is within the search's duplicate radius
    /// (`agent::search::DUPLICATE_RTE_M` / `DUPLICATE_RRE_DEG`) of the answer, in [0, 1] (0 with
    /// one start): starts a quarter turn apart that end at the same place.
    pub agreement: f64,
    /// `agent::Confidence::frustum_iou` of the answer, in [0, 1].
    pub frustum_iou: f64,
    /// `agent::Confidence::policy_certainty`: the answer's last step's mean chosen probability.
    pub policy_certainty: f64,
    /// 1 when the answer's trajectory stopped by choosing the zero step, else 0.
    pub converged: f64,
    /// The answer's steps over the request's `max_iterations`, in [0, 1].
    pub steps_fraction: f64,
    /// `agent::Confidence::in_view`: share of the M state points in the model input's frustum at
    /// the answer, in [0, 1].
    pub in_view: f64,
    /// log2 of the number of starts (0 for the paper's single trajectory, 2 for the default 4).
    pub log2_starts: f64,
    /// 1 when the request stated a bound on its prior (`prior_bound`: starts within it, the best
    /// visited pose inside it answers), else 0. Absent in records written before it: 0.
    #[serde(default)]
    pub bounded: f64,
    /// Share of every pose the search visited (each hypothesis's start and steps, both rounds)
    /// that is registered relative to the answer (`geometry::PoseError::is_registered`: within 10°
    /// and 5 m of it), in [0, 1]: where the trajectories gather. Absent in records written before
    /// it (model sets up to v11's first calibrator): 0, and `cmr.calibrate` refuses to fit on such
    /// records.
    #[serde(default)]
    pub visit_share: f64,
    /// The polished answer's alignment minus the highest peak another candidate of the polished
    /// choice reached (`agent::polish::Polish::runner_up_alignment`); 0 with one candidate or no
    /// polish. The choice compares peaks, so this, not `alignment_margin` (final poses before
    /// the polish), says how clearly the answer won. Absent in records written before it: 0, and
    /// `cmr.calibrate` refuses to fit on such records.
    #[serde(default)]
    pub peak_margin: f64,
}

impl Signals {
    /// The signal called `name` (one of [`SIGNAL_NAMES`]).
    pub fn get(&self, name: &str) -> Option<f64> {
        Some(match name {
            "alignment" => self.alignment,
            "alignment_gain" => self.alignment_gain,
            "alignment_margin" => self.alignment_margin,
            "agreement" => self.agreement,
            "frustum_iou" => self.frustum_iou,
            "policy_certainty" => self.policy_certainty,
            "converged" => self.converged,
            "steps_fraction" => self.steps_fraction,
            "in_view" => self.in_view,
            "log2_starts" => self.log2_starts,
            "bounded" => self.bounded,
            "visit_share" => self.visit_share,
            "peak_margin" => self.peak_margin,
            _ => return None,
        })
    }
}

/// The manifest's `calibrator` section (see the module doc for the formula).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibrator {
    /// [`LOGISTIC`].
    pub kind: String,
    /// What `p_registered` is the probability of, in words (for a reader of the manifest).
    pub target: String,
    /// Signal names (a subset of [`SIGNAL_NAMES`], no repeats), in the order of the vectors.
    pub features: Vec<String>,
    /// Standardisation: each signal's mean and standard deviation (> 0) on the fitting data.
    pub mean: Vec<f64>,
    pub std: Vec<f64>,
    /// One weight per standardised signal, and the intercept.
    pub weights: Vec<f64>,
    pub bias: f64,
    /// Each standardised signal is clamped to [−clip, clip] (> 0) before it is weighted, so an
    /// input far outside the fitting data (e.g. a map cropped to the camera's view, whose
    /// frustum IoU is unlike any street's) cannot push p to 0 or 1 on its own; absent: no clamp.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clip: Option<f64>,
    /// `localized` = p_registered ≥ this, in [0, 1]; chosen on the calibration data for the
    /// precision of `localized` (see `provenance`). `serve --localized-threshold` overrides it.
    pub threshold: f64,
    /// The same for a request that stated a prior bound (signal `bounded` = 1), chosen on such
    /// answers alone: they are right far more often than unbounded ones at the same p, so one
    /// threshold for both would vouch for few of them. Absent (calibrators before it): `threshold`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bounded_threshold: Option<f64>,
    /// Data, command, date and the fit's figures (free-form, written by `cmr.calibrate`).
    #[serde(default)]
    pub provenance: serde_json::Value,
}

impl Calibrator {
    /// Checks that the section can be applied: known kind and signal names, matching lengths,
    /// finite numbers, positive spreads, a threshold in [0, 1]. The error names the field.
    pub fn validate(&self) -> Result<(), String> {
        if self.kind != LOGISTIC {
            return Err(format!("calibrator.kind {:?} is unknown; this build applies {LOGISTIC:?}", self.kind));
        }
        if self.features.is_empty() {
            return Err("calibrator.features is empty".into());
        }
        for (i, name) in self.features.iter().enumerate() {
            if !SIGNAL_NAMES.contains(&name.as_str()) {
                return Err(format!("calibrator.features: unknown signal {name:?} (known: {SIGNAL_NAMES:?})"));
            }
            if self.features[..i].contains(name) {
                return Err(format!("calibrator.features: {name:?} is listed twice"));
            }
        }
        let n = self.features.len();
        for (field, v) in [("mean", &self.mean), ("std", &self.std), ("weights", &self.weights)] {
            if v.len() != n {
                return Err(format!("calibrator.{field} has {} values for {n} features", v.len()));
            }
            if v.iter().any(|x| !x.is_finite()) {
                return Err(format!("calibrator.{field} holds a number that is not finite"));
            }
        }
        if self.std.iter().any(|s| *s <= 0.0) {
            return Err("calibrator.std must be positive".into());
        }
        if !self.bias.is_finite() {
            return Err("calibrator.bias is not finite".into());
        }
        if self.clip.is_some_and(|c| !(c > 0.0 && c.is_finite())) {
            return Err("calibrator.clip must be a positive number".into());
        }
        if !(0.0..=1.0).contains(&self.threshold) {
            return Err(format!("calibrator.threshold {} is outside [0, 1]", self.threshold));
        }
        if let Some(t) = self.bounded_threshold.filter(|t| !(0.0..=1.0).contains(t)) {
            return Err(format!("calibrator.bounded_threshold {t} is outside [0, 1]"));
        }
        Ok(())
    }

    /// p_registered for `signals`, in [0, 1]; `None` when a signal it reads is not finite (no
    /// probability is made up for an answer whose own numbers are broken).
    pub fn probability(&self, signals: &Signals) -> Option<f64> {
        let clip = self.clip.unwrap_or(f64::INFINITY);
        let mut z = self.bias;
        for (i, name) in self.features.iter().enumerate() {
            let x = signals.get(name)?;
            if !x.is_finite() {
                return None;
            }
            z += self.weights[i] * ((x - self.mean[i]) / self.std[i]).clamp(-clip, clip);
        }
        Some(1.0 / (1.0 + (-z).exp()))
    }
}

/// What a caller may act on: the calibrated probability that the answer is registered and the
/// yes/no verdict `localized` (p_registered ≥ the threshold). Uncalibrated (the default):
/// `p_registered: None, localized: false`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Verdict {
    pub p_registered: Option<f64>,
    pub localized: bool,
}

/// A model set's calibrator with the thresholds in force (the manifest's, or an override).
#[derive(Debug, Clone, Default)]
pub struct Calibration {
    calibrator: Option<Calibrator>,
    threshold: f64,
    bounded_threshold: f64,
}

impl Calibration {
    /// The manifest's calibrator (none: every verdict uncalibrated) with its thresholds, or
    /// `threshold` instead of both when given (a value above 1 never calls an answer localized).
    pub fn new(calibrator: Option<&Calibrator>, threshold: Option<f64>) -> Self {
        let unbounded = threshold.or(calibrator.map(|c| c.threshold)).unwrap_or(1.0);
        let bounded = threshold.or(calibrator.and_then(|c| c.bounded_threshold)).unwrap_or(unbounded);
        Self { calibrator: calibrator.cloned(), threshold: unbounded, bounded_threshold: bounded }
    }

    /// The threshold in force for requests without a prior bound; `None` without a calibrator.
    pub fn threshold(&self) -> Option<f64> {
        self.calibrator.as_ref().map(|_| self.threshold)
    }

    /// The threshold in force for requests that state a prior bound; `None` without a calibrator.
    pub fn bounded_threshold(&self) -> Option<f64> {
        self.calibrator.as_ref().map(|_| self.bounded_threshold)
    }

    pub fn is_calibrated(&self) -> bool {
        self.calibrator.is_some()
    }

    /// The verdict on one localization's signals.
    pub fn judge(&self, signals: &Signals) -> Verdict {
        let p = self.calibrator.as_ref().and_then(|c| c.probability(signals));
        let threshold = if signals.bounded > 0.5 { self.bounded_threshold } else { self.threshold };
        Verdict { p_registered: p, localized: p.is_some_and(|p| p >= threshold) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn signals() -> Signals {
        Signals {
            alignment: 0.6,
            alignment_gain: 0.3,
            alignment_margin: 0.1,
            agreement: 1.0 / 3.0,
            frustum_iou: 0.4,
            policy_certainty: 0.8,
            converged: 1.0,
            steps_fraction: 0.5,
            in_view: 0.2,
            log2_starts: 2.0,
            bounded: 0.0,
            visit_share: 0.25,
            peak_margin: 0.02,
        }
    }

    fn calibrator() -> Calibrator {
        Calibrator {
            kind: LOGISTIC.into(),
            target: "test".into(),
            features: vec!["alignment".into(), "agreement".into()],
            mean: vec![0.5, 0.0],
            std: vec![0.1, 0.5],
            weights: vec![2.0, -1.5],
            bias: 0.25,
            clip: None,
            threshold: 0.7,
            bounded_threshold: None,
            provenance: serde_json::Value::Null,
        }
    }

    #[test]
    fn every_signal_name_reads_its_field_and_only_those() {
        let s = signals();
        let values: Vec<f64> = SIGNAL_NAMES.iter().map(|n| s.get(n).unwrap()).collect();
        let json = serde_json::to_value(s).unwrap();
        for (name, v) in SIGNAL_NAMES.iter().zip(&values) {
            assert_eq!(json[name].as_f64(), Some(*v), "{name}");
        }
        assert_eq!(json.as_object().unwrap().len(), SIGNAL_NAMES.len());
        assert!(s.get("confidence").is_none());
    }

    #[test]
    fn the_probability_is_the_logistic_of_the_standardised_sum() {
        let c = calibrator();
        let z: f64 = 0.25 + 2.0 * (0.6 - 0.5) / 0.1 - 1.5 * (1.0 / 3.0) / 0.5;
        let p = c.probability(&signals()).unwrap();
        assert!((p - 1.0 / (1.0 + (-z).exp())).abs() < 1e-15, "{p}");
        assert!(c.probability(&Signals { alignment: f64::NAN, ..signals() }).is_none());
        // Signals the calibrator does not read do not matter, even when broken.
        assert_eq!(c.probability(&Signals { in_view: f64::NAN, ..signals() }), Some(p));
        // A clamp bounds each standardised signal: alignment's z of 1 and agreement's of 2/3
        // are both cut to 0.5.
        let clipped = Calibrator { clip: Some(0.5), ..c.clone() };
        let z: f64 = 0.25 + 2.0 * 0.5 - 1.5 * 0.5;
        assert!((clipped.probability(&signals()).unwrap() - 1.0 / (1.0 + (-z).exp())).abs() < 1e-15);
    }

    #[test]
    fn the_threshold_decides_and_an_override_replaces_it() {
        let c = calibrator();
        let p = c.probability(&signals()).unwrap();
        assert!(p > 0.7 && p < 0.9, "{p}");
        assert_eq!(Calibration::new(Some(&c), None).judge(&signals()), Verdict { p_registered: Some(p), localized: true });
        assert_eq!(Calibration::new(Some(&c), Some(0.9)).judge(&signals()), Verdict { p_registered: Some(p), localized: false });
        assert_eq!(Calibration::new(Some(&c), Some(0.9)).threshold(), Some(0.9));
        assert!(!Calibration::new(Some(&c), Some(2.0)).judge(&signals()).localized, "above 1: never");
        assert_eq!(Calibration::new(Some(&c), Some(p)).judge(&signals()).localized, true, "at the threshold");
    }

    #[test]
    fn a_bounded_request_meets_its_own_threshold() {
        let c = Calibrator { bounded_threshold: Some(0.9), ..calibrator() };
        let p = c.probability(&signals()).unwrap();
        let bounded = Signals { bounded: 1.0, ..signals() };
        let p_bounded = c.probability(&bounded).unwrap();
        assert_eq!(p, p_bounded, "the test calibrator does not read `bounded`");
        let cal = Calibration::new(Some(&c), None);
        assert!(cal.judge(&signals()).localized, "unbounded: p {p} >= 0.7");
        assert!(!cal.judge(&bounded).localized, "bounded: p {p} < 0.9");
        assert_eq!((cal.threshold(), cal.bounded_threshold()), (Some(0.7), Some(0.9)));
        let easier = Calibration::new(Some(&Calibrator { bounded_threshold: Some(0.6), threshold: 0.95, ..calibrator() }), None);
        assert!(easier.judge(&bounded).localized && !easier.judge(&signals()).localized);
        // Without the field, bounded requests use `threshold`; an override replaces both.
        assert_eq!(Calibration::new(Some(&calibrator()), None).bounded_threshold(), Some(0.7));
        let overridden = Calibration::new(Some(&c), Some(0.5));
        assert_eq!((overridden.threshold(), overridden.bounded_threshold()), (Some(0.5), Some(0.5)));
        assert!(overridden.judge(&bounded).localized);
        // The field round-trips through the manifest's JSON and is left out when absent.
        let json = serde_json::to_value(&c).unwrap();
        assert_eq!(json["bounded_threshold"], 0.9);
        assert_eq!(serde_json::from_value::<Calibrator>(json).unwrap(), c);
        assert!(serde_json::to_value(calibrator()).unwrap().get("bounded_threshold").is_none());
    }

    #[test]
    fn without_a_calibrator_nothing_is_vouched_for() {
        let none = Calibration::new(None, Some(0.0));
        assert_eq!(none.judge(&signals()), Verdict { p_registered: None, localized: false });
        assert_eq!(none.threshold(), None);
        assert!(!none.is_calibrated());
    }

    #[test]
    fn malformed_sections_are_refused_with_the_field_named() {
        type Edit = Box<dyn Fn(&mut Calibrator)>;
        let cases: Vec<(Edit, &str)> = vec![
            (Box::new(|c| c.kind = "isotonic".into()), "calibrator.kind"),
            (Box::new(|c| c.features[1] = "confidence".into()), "unknown signal"),
            (Box::new(|c| c.features[1] = "alignment".into()), "listed twice"),
            (Box::new(|c| c.weights.push(1.0)), "calibrator.weights has 3"),
            (Box::new(|c| c.std[0] = 0.0), "std must be positive"),
            (Box::new(|c| c.mean[0] = f64::INFINITY), "calibrator.mean"),
            (Box::new(|c| c.threshold = 1.5), "threshold"),
            (Box::new(|c| c.bounded_threshold = Some(-0.1)), "calibrator.bounded_threshold"),
            (Box::new(|c| c.clip = Some(0.0)), "calibrator.clip"),
            (Box::new(|c| c.features.clear()), "empty"),
        ];
        assert_eq!(calibrator().validate(), Ok(()));
        for (edit, needle) in cases {
            let mut c = calibrator();
            edit(&mut c);
            let err = c.validate().unwrap_err();
            assert!(err.contains(needle), "{err} should mention {needle}");
        }
    }
}
