//! How good the calibrated verdict is on an evaluation's cases: precision and recall of
//! `localized`, the Brier score beside the base rate's, the AUC, the expected calibration error
//! and the reliability diagram's bins. The verdict itself is `model::calibrator` (the same one
//! the server applies); these are only its scores. `training/cmr/calibrate.py` computes the same
//! figures when it fits a calibrator, and `fixtures/calibration.json` pins the two.

use serde::{Deserialize, Serialize};

use crate::geometry::metrics::{RR_MAX_ROTATION_DEG, RR_MAX_TRANSLATION_M};

use super::report::CaseRecord;

/// Equal-width probability bins of the reliability diagram and the expected calibration error.
pub const RELIABILITY_BINS: usize = 10;

/// One case as the verdict saw it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Judged {
    /// p_registered, in [0, 1].
    pub p: f64,
    /// The verdict given (p ≥ the threshold in force).
    pub localized: bool,
    /// The truth: the final pose is registered (protocol A).
    pub registered: bool,
}

/// One bin of the reliability diagram: cases whose p lies in [lower, upper) (the last bin
/// includes 1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReliabilityBin {
    pub lower: f64,
    pub upper: f64,
    pub cases: usize,
    /// Mean p over the bin's cases (0 when empty).
    pub mean_p: f64,
    /// Share of the bin's cases that are registered (0 when empty).
    pub registered_share: f64,
}

/// The verdict's figures for one method.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationReport {
    pub method: String,
    /// The threshold in force (`localized` = p ≥ it).
    pub threshold: f64,
    /// Cases with a p_registered.
    pub cases: usize,
    /// Of those, registered (protocol A); the base rate is registered / cases.
    pub registered: usize,
    pub localized: usize,
    /// Localized and registered.
    pub localized_registered: usize,
    /// localized_registered / localized; `None` when nothing is localized.
    pub precision: Option<f64>,
    /// localized_registered / registered; `None` when nothing is registered.
    pub recall: Option<f64>,
    /// Mean squared error of p against the outcome (0 or 1).
    pub brier: f64,
    /// The Brier score of always answering the base rate r: r·(1 − r). A calibrator that knows
    /// anything scores below it.
    pub brier_base_rate: f64,
    /// Probability that a registered case gets a higher p than a failed one (ties count half);
    /// `None` with only one kind of case.
    pub auc: Option<f64>,
    /// Σ over [`RELIABILITY_BINS`] bins of (cases in bin / cases) · |mean p − registered share|.
    pub ece: f64,
    pub bins: Vec<ReliabilityBin>,
}

impl CalibrationReport {
    /// The figures over `cases` (any order). Panics on no cases (there is nothing to score).
    pub fn of(method: &str, threshold: f64, cases: &[Judged]) -> Self {
        assert!(!cases.is_empty(), "no judged cases");
        let n = cases.len();
        let registered = cases.iter().filter(|c| c.registered).count();
        let localized = cases.iter().filter(|c| c.localized).count();
        let localized_registered = cases.iter().filter(|c| c.localized && c.registered).count();
        let rate = registered as f64 / n as f64;
        let p: Vec<f64> = cases.iter().map(|c| c.p).collect();
        let y: Vec<bool> = cases.iter().map(|c| c.registered).collect();
        let bins = reliability_bins(&p, &y);
        CalibrationReport {
            method: method.to_string(),
            threshold,
            cases: n,
            registered,
            localized,
            localized_registered,
            precision: (localized > 0).then(|| localized_registered as f64 / localized as f64),
            recall: (registered > 0).then(|| localized_registered as f64 / registered as f64),
            brier: brier(&p, &y),
            brier_base_rate: rate * (1.0 - rate),
            auc: auc(&p, &y),
            ece: bins.iter().map(|b| b.cases as f64 / n as f64 * (b.mean_p - b.registered_share).abs()).sum(),
            bins,
        }
    }

    /// The judged cases of `method` in `records`: those whose notes carry `p_registered`
    /// (written by `eval::learned`); the outcome is the record's final error under protocol A.
    pub fn judged(records: &[CaseRecord], method: &str) -> Vec<Judged> {
        records
            .iter()
            .filter(|r| r.method == method)
            .filter_map(|r| {
                let p = r.notes.get("p_registered")?.as_f64()?;
                let localized = r.notes.get("localized")?.as_bool()?;
                let registered = r.errors.last()?.within(RR_MAX_ROTATION_DEG, RR_MAX_TRANSLATION_M);
                Some(Judged { p, localized, registered })
            })
            .collect()
    }
}

/// Mean of (p − y)² with y ∈ {0, 1}.
pub fn brier(p: &[f64], y: &[bool]) -> f64 {
    p.iter().zip(y).map(|(p, y)| (p - if *y { 1.0 } else { 0.0 }).powi(2)).sum::<f64>() / p.len().max(1) as f64
}

/// The area under the ROC curve (Mann-Whitney: ranks of the positives, ties averaged); `None`
/// without both positives and negatives.
pub fn auc(p: &[f64], y: &[bool]) -> Option<f64> {
    let positives = y.iter().filter(|v| **v).count();
    let negatives = y.len() - positives;
    if positives == 0 || negatives == 0 {
        return None;
    }
    let mut order: Vec<usize> = (0..p.len()).collect();
    order.sort_by(|&a, &b| p[a].total_cmp(&p[b]));
    let mut rank_sum = 0.0;
    let mut i = 0;
    while i < order.len() {
        let mut j = i;
        while j + 1 < order.len() && p[order[j + 1]] == p[order[i]] {
            j += 1;
        }
        // Ranks i+1..=j+1 share their mean.
        let mean_rank = (i + j + 2) as f64 / 2.0;
        rank_sum += mean_rank * order[i..=j].iter().filter(|&&k| y[k]).count() as f64;
        i = j + 1;
    }
    let (np, nn) = (positives as f64, negatives as f64);
    Some((rank_sum - np * (np + 1.0) / 2.0) / (np * nn))
}

/// The [`RELIABILITY_BINS`] equal-width bins over [0, 1] (p = 1 goes to the last).
pub fn reliability_bins(p: &[f64], y: &[bool]) -> Vec<ReliabilityBin> {
    let k = RELIABILITY_BINS;
    let mut sums = vec![(0usize, 0.0f64, 0usize); k];
    for (p, y) in p.iter().zip(y) {
        let b = ((p * k as f64).floor() as usize).min(k - 1);
        sums[b].0 += 1;
        sums[b].1 += p;
        sums[b].2 += *y as usize;
    }
    sums.into_iter()
        .enumerate()
        .map(|(b, (cases, sum_p, positives))| ReliabilityBin {
            lower: b as f64 / k as f64,
            upper: (b + 1) as f64 / k as f64,
            cases,
            mean_p: if cases == 0 { 0.0 } else { sum_p / cases as f64 },
            registered_share: if cases == 0 { 0.0 } else { positives as f64 / cases as f64 },
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn judged(p: f64, registered: bool) -> Judged {
        Judged { p, localized: p >= 0.5, registered }
    }

    #[test]
    fn figures_on_a_hand_computed_set() {
        let cases = [judged(0.9, true), judged(0.8, false), judged(0.6, true), judged(0.3, false), judged(0.1, false), judged(0.95, true)];
        let r = CalibrationReport::of("m", 0.5, &cases);
        assert_eq!((r.cases, r.registered, r.localized, r.localized_registered), (6, 3, 4, 3));
        assert_eq!((r.precision, r.recall), (Some(0.75), Some(1.0)));
        let brier = (0.01 + 0.64 + 0.16 + 0.09 + 0.01 + 0.0025) / 6.0;
        assert!((r.brier - brier).abs() < 1e-12);
        assert_eq!(r.brier_base_rate, 0.25);
        // Pairs (positive, negative): 9 of 9 ordered right except 0.6 < 0.8.
        assert!((r.auc.unwrap() - 8.0 / 9.0).abs() < 1e-12);
        // Bins: [0.1] 0/1, [0.3] 0/1, [0.6] 1/1, [0.8] 0/1, [0.9, 0.95] 2/2.
        let ece = (0.1 + 0.3 + 0.4 + 0.8 + 2.0 * (1.0 - 0.925)) / 6.0;
        assert!((r.ece - ece).abs() < 1e-12, "{} vs {ece}", r.ece);
        assert_eq!(r.bins.len(), RELIABILITY_BINS);
        assert_eq!((r.bins[9].cases, r.bins[9].registered_share), (2, 1.0));
    }

    #[test]
    fn ties_count_half_and_one_kind_has_no_auc() {
        assert_eq!(auc(&[0.5, 0.5], &[true, false]), Some(0.5));
        assert_eq!(auc(&[0.2, 0.5, 0.5, 0.9], &[false, true, false, true]), Some(0.875));
        assert_eq!(auc(&[0.2, 0.4], &[true, true]), None);
        let bins = reliability_bins(&[1.0, 0.0], &[true, false]);
        assert_eq!((bins[0].cases, bins[9].cases), (1, 1));
        let r = CalibrationReport::of("m", 0.99, &[judged(0.2, false)]);
        assert_eq!((r.precision, r.recall, r.auc), (None, None, None));
    }
}
