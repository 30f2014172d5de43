//! Aggregating per-case pose errors into the figures of the paper's tables.
//!
//! Protocol A (the paper's): registration recall RR = share of cases with RRE_euler < 10° and
//! RTE < 5 m; the means ± standard deviations are over the *registered* cases only.
//! Protocol B (newer papers): accuracy = share with RRE_euler < 5° and RTE < 2 m; the means are
//! over *all* cases (a failure counts with its full error).

use serde::{Deserialize, Serialize};

use crate::geometry::PoseError;
use crate::geometry::metrics::{RR_MAX_ROTATION_DEG, RR_MAX_TRANSLATION_M};

pub const STRICT_MAX_ROTATION_DEG: f64 = 5.0;
pub const STRICT_MAX_TRANSLATION_M: f64 = 2.0;

/// Mean and population standard deviation; both NaN-free (0 for an empty set, with n = 0).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MeanStd {
    pub mean: f64,
    pub std: f64,
    pub median: f64,
    pub n: usize,
}

impl MeanStd {
    pub fn of(values: impl IntoIterator<Item = f64>) -> Self {
        let mut v: Vec<f64> = values.into_iter().collect();
        if v.is_empty() {
            return MeanStd { mean: 0.0, std: 0.0, median: 0.0, n: 0 };
        }
        let n = v.len() as f64;
        let mean = v.iter().sum::<f64>() / n;
        let std = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
        v.sort_by(f64::total_cmp);
        let median = if v.len() % 2 == 1 { v[v.len() / 2] } else { 0.5 * (v[v.len() / 2 - 1] + v[v.len() / 2]) };
        MeanStd { mean, std, median, n: v.len() }
    }
}

/// RTE and both RRE conventions over one set of cases.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ErrorStats {
    pub rte_m: MeanStd,
    pub rre_euler_deg: MeanStd,
    pub rre_geodesic_deg: MeanStd,
}

impl ErrorStats {
    pub fn of<'a>(errors: impl Iterator<Item = &'a PoseError> + Clone) -> Self {
        ErrorStats {
            rte_m: MeanStd::of(errors.clone().map(|e| e.rte_m)),
            rre_euler_deg: MeanStd::of(errors.clone().map(|e| e.rre_euler_deg)),
            rre_geodesic_deg: MeanStd::of(errors.map(|e| e.rre_geodesic_deg)),
        }
    }
}

/// Everything the tables show for one method (at one iteration).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub cases: usize,
    /// Protocol A: share registered at 10°/5 m (0..1) and the errors of the registered cases.
    pub registration_recall: f64,
    pub registered: ErrorStats,
    /// Protocol B: share within 5°/2 m (0..1) and the errors of all cases.
    pub accuracy_5deg_2m: f64,
    pub all: ErrorStats,
}

impl Summary {
    pub fn of(errors: &[PoseError]) -> Self {
        let share = |pass: usize| if errors.is_empty() { 0.0 } else { pass as f64 / errors.len() as f64 };
        let registered = errors.iter().filter(|e| e.within(RR_MAX_ROTATION_DEG, RR_MAX_TRANSLATION_M));
        let strict = errors.iter().filter(|e| e.within(STRICT_MAX_ROTATION_DEG, STRICT_MAX_TRANSLATION_M)).count();
        Summary {
            cases: errors.len(),
            registration_recall: share(registered.clone().count()),
            registered: ErrorStats::of(registered),
            accuracy_5deg_2m: share(strict),
            all: ErrorStats::of(errors.iter()),
        }
    }
}

/// Share of cases whose RRE_euler is below each rotation threshold (any RTE), and whose RTE is
/// below each translation threshold (any RRE): the two panels of the paper's Fig. 5.
pub fn success_curves(errors: &[PoseError], rotation_deg: &[f64], translation_m: &[f64]) -> (Vec<f64>, Vec<f64>) {
    let share = |pass: usize| if errors.is_empty() { 0.0 } else { pass as f64 / errors.len() as f64 };
    let rot = rotation_deg.iter().map(|&t| share(errors.iter().filter(|e| e.rre_euler_deg < t).count())).collect();
    let trans = translation_m.iter().map(|&t| share(errors.iter().filter(|e| e.rte_m < t).count())).collect();
    (rot, trans)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn e(rte: f64, rre: f64) -> PoseError {
        PoseError { rte_m: rte, rre_euler_deg: rre, rre_geodesic_deg: rre * 0.9 }
    }

    #[test]
    fn mean_std_median_on_known_values() {
        let s = MeanStd::of([1.0, 2.0, 3.0, 4.0]);
        assert_eq!((s.mean, s.median, s.n), (2.5, 2.5, 4));
        assert!((s.std - 1.25f64.sqrt()).abs() < 1e-12);
        assert_eq!(MeanStd::of([]).n, 0);
    }

    #[test]
    fn protocols_a_and_b_average_over_different_sets() {
        // Registered at 10°/5 m: the first three; within 5°/2 m: the first two.
        let errors = [e(1.0, 2.0), e(1.5, 4.0), e(4.0, 9.0), e(20.0, 120.0)];
        let s = Summary::of(&errors);
        assert_eq!(s.cases, 4);
        assert_eq!(s.registration_recall, 0.75);
        assert_eq!(s.accuracy_5deg_2m, 0.5);
        assert!((s.registered.rte_m.mean - 6.5 / 3.0).abs() < 1e-12);
        assert!((s.registered.rre_euler_deg.mean - 5.0).abs() < 1e-12);
        assert!((s.registered.rre_geodesic_deg.mean - 4.5).abs() < 1e-12);
        assert!((s.all.rte_m.mean - 26.5 / 4.0).abs() < 1e-12);
        assert_eq!(s.all.rre_euler_deg.median, 6.5);
        // Thresholds are strict: exactly 10° is not registered.
        assert_eq!(Summary::of(&[e(1.0, 10.0)]).registration_recall, 0.0);
    }

    #[test]
    fn curves_count_each_threshold_separately() {
        let errors = [e(0.5, 1.0), e(3.0, 0.5), e(6.0, 12.0)];
        let (rot, trans) = success_curves(&errors, &[0.0, 1.0, 1.5, 15.0], &[1.0, 5.0]);
        assert_eq!(rot, vec![0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0]);
        assert_eq!(trans, vec![1.0 / 3.0, 2.0 / 3.0]);
    }
}
