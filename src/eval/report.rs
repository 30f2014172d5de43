//! The evaluation's results: per-case records, per-method summaries, and their Markdown tables
//! in the paper's layouts (Table 1, Table 2, Table 4).

use std::collections::BTreeMap;
use std::fmt::Write as _;

use serde::{Deserialize, Serialize};

use crate::geometry::PoseError;

use super::calibration::CalibrationReport;
use super::summary::{MeanStd, Summary, success_curves};

/// One method on one case.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CaseRecord {
    pub sequence: String,
    pub frame: usize,
    pub method: String,
    /// Error after each iteration (one entry for one-shot methods).
    pub errors: Vec<PoseError>,
    pub elapsed_ms: Vec<f64>,
    pub phases_ms: BTreeMap<String, f64>,
    #[serde(skip_serializing_if = "serde_json::Value::is_null", default)]
    pub notes: serde_json::Value,
}

/// One row of the per-iteration table.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IterationRow {
    pub iteration: usize,
    pub summary: Summary,
    /// Milliseconds from the method's start until this iteration's pose, over cases.
    pub elapsed_ms: MeanStd,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MethodReport {
    pub method: String,
    /// Figures at the last iteration (the only one for one-shot methods).
    pub summary: Summary,
    pub per_iteration: Vec<IterationRow>,
    pub phases_ms: BTreeMap<String, MeanStd>,
    /// Model parameters the method runs (all four graphs for the agent), when known.
    pub parameters: Option<u64>,
    /// Fig. 5 curves at the last iteration.
    pub rotation_curve: Vec<f64>,
    pub translation_curve: Vec<f64>,
}

/// Memory and model facts of the run.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Resources {
    /// Peak resident memory of the evaluating process (all methods share it), bytes.
    pub peak_rss_bytes: Option<u64>,
    /// Parameters per ONNX graph, from the manifest.
    pub graph_parameters: BTreeMap<String, u64>,
    /// Point-encoder time per map (the server computes it once per map and caches it), ms.
    pub map_prepare_ms: Option<MeanStd>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EvalReport {
    pub format: String,
    pub data: String,
    pub perturbations: String,
    pub models: Option<String>,
    pub cases: usize,
    pub iterations: usize,
    pub command: String,
    /// Method settings (baseline matching and RANSAC, model provenance).
    pub settings: serde_json::Value,
    pub created_unix_s: u64,
    pub rotation_thresholds_deg: Vec<f64>,
    pub translation_thresholds_m: Vec<f64>,
    pub methods: Vec<MethodReport>,
    pub resources: Resources,
    /// The calibrated verdict's figures per agent method (`notes.p_registered` and
    /// `notes.localized` of its records); empty when the model set has no calibrator.
    #[serde(default)]
    pub calibration: Vec<CalibrationReport>,
}

pub fn rotation_thresholds() -> Vec<f64> {
    (0..=60).map(|i| i as f64 * 0.25).collect()
}

pub fn translation_thresholds() -> Vec<f64> {
    (0..=50).map(|i| i as f64 * 0.1).collect()
}

/// Summarises records method by method, in the order methods first appear.
pub fn summarise(records: &[CaseRecord], parameters: &BTreeMap<String, u64>) -> Vec<MethodReport> {
    let mut order: Vec<&str> = Vec::new();
    for r in records {
        if !order.contains(&r.method.as_str()) {
            order.push(&r.method);
        }
    }
    let (rot_t, trans_t) = (rotation_thresholds(), translation_thresholds());
    order
        .into_iter()
        .map(|name| {
            let mine: Vec<&CaseRecord> = records.iter().filter(|r| r.method == name).collect();
            let k = mine.iter().map(|r| r.errors.len()).max().unwrap_or(0);
            let per_iteration: Vec<IterationRow> = (0..k)
                .map(|i| {
                    let errors: Vec<PoseError> = mine.iter().filter_map(|r| r.errors.get(i).or(r.errors.last()).copied()).collect();
                    let elapsed = MeanStd::of(mine.iter().filter_map(|r| r.elapsed_ms.get(i).or(r.elapsed_ms.last()).copied()));
                    IterationRow { iteration: i + 1, summary: Summary::of(&errors), elapsed_ms: elapsed }
                })
                .collect();
            let last: Vec<PoseError> = mine.iter().filter_map(|r| r.errors.last().copied()).collect();
            let mut phase_names: Vec<&String> = mine.iter().flat_map(|r| r.phases_ms.keys()).collect();
            phase_names.sort();
            phase_names.dedup();
            let phases_ms = phase_names
                .into_iter()
                .map(|p| (p.clone(), MeanStd::of(mine.iter().filter_map(|r| r.phases_ms.get(p).copied()))))
                .collect();
            let (rotation_curve, translation_curve) = success_curves(&last, &rot_t, &trans_t);
            MethodReport {
                method: name.to_string(),
                summary: Summary::of(&last),
                per_iteration,
                phases_ms,
                parameters: parameters.get(name).copied(),
                rotation_curve,
                translation_curve,
            }
        })
        .collect()
}

fn pm(s: &MeanStd, digits: usize) -> String {
    if s.n == 0 {
        return "–".into();
    }
    format!("{:.*} ± {:.*}", digits, s.mean, digits, s.std)
}

fn pct(x: f64) -> String {
    format!("{:.2}", 100.0 * x)
}

impl EvalReport {
    /// The tables as one Markdown document.
    pub fn markdown(&self) -> String {
        let mut md = String::new();
        let _ = writeln!(md, "# Evaluation: {} cases, {} iterations\n", self.cases, self.iterations);
        let _ = writeln!(md, "Data `{}`, perturbations `{}`, models `{}`.\n", self.data, self.perturbations, self.models.as_deref().unwrap_or("–"));
        let _ = writeln!(md, "Command: `{}`\n", self.command);
        let _ = writeln!(md, "Settings: `{}`\n", self.settings);

        let _ = writeln!(md, "## Table 1: registration (protocol A: RR at 10°/5 m, means ± std over registered cases)\n");
        let _ = writeln!(md, "| Method | RTE (m) | RRE (°, Euler sum) | RRE (°, geodesic) | RR (%) |");
        let _ = writeln!(md, "|---|---|---|---|---|");
        for m in &self.methods {
            let s = &m.summary;
            let _ = writeln!(
                md,
                "| {} | {} | {} | {} | {} |",
                m.method,
                pm(&s.registered.rte_m, 3),
                pm(&s.registered.rre_euler_deg, 3),
                pm(&s.registered.rre_geodesic_deg, 3),
                pct(s.registration_recall)
            );
        }

        let _ = writeln!(md, "\n## Table 1b: protocol B (accuracy at 5°/2 m, means ± std and medians over all cases)\n");
        let _ = writeln!(md, "| Method | RTE (m) | RRE (°, Euler sum) | RRE (°, geodesic) | median RTE (m) | median RRE (°, Euler) | Acc. 5°/2 m (%) |");
        let _ = writeln!(md, "|---|---|---|---|---|---|---|");
        for m in &self.methods {
            let a = &m.summary.all;
            let _ = writeln!(
                md,
                "| {} | {} | {} | {} | {:.3} | {:.3} | {} |",
                m.method,
                pm(&a.rte_m, 3),
                pm(&a.rre_euler_deg, 3),
                pm(&a.rre_geodesic_deg, 3),
                a.rte_m.median,
                a.rre_euler_deg.median,
                pct(m.summary.accuracy_5deg_2m)
            );
        }

        for m in self.methods.iter().filter(|m| m.per_iteration.len() > 1) {
            let _ = writeln!(md, "\n## Table 4: {} per iteration (protocol A errors; time = ms from the start of the method, mean)\n", m.method);
            let _ = writeln!(md, "| Iteration | RTE (m) | RRE (°, Euler sum) | RR (%) | Acc. 5°/2 m (%) | Time (ms) |");
            let _ = writeln!(md, "|---|---|---|---|---|---|");
            for row in &m.per_iteration {
                let s = &row.summary;
                let _ = writeln!(
                    md,
                    "| {} | {} | {} | {} | {} | {:.1} |",
                    row.iteration,
                    pm(&s.registered.rte_m, 3),
                    pm(&s.registered.rre_euler_deg, 3),
                    pct(s.registration_recall),
                    pct(s.accuracy_5deg_2m),
                    row.elapsed_ms.mean
                );
            }
        }

        let _ = writeln!(md, "\n## Is the answer right? The calibrated verdict (`localized` = p_registered >= threshold; outcome: protocol A)\n");
        if self.calibration.is_empty() {
            let _ = writeln!(md, "No calibrator in this model set: every answer is p_registered null, localized false.");
        } else {
            let _ = writeln!(md, "| Method | Cases | Registered | Threshold | Localized | Precision (%) | Recall (%) | Brier (base rate's) | AUC | ECE |");
            let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|");
            let opt = |x: Option<f64>| x.map_or("–".to_string(), pct);
            for c in &self.calibration {
                let _ = writeln!(
                    md,
                    "| {} | {} | {} | {:.3} | {} | {} ({}/{}) | {} | {:.4} ({:.4}) | {} | {:.4} |",
                    c.method,
                    c.cases,
                    c.registered,
                    c.threshold,
                    c.localized,
                    opt(c.precision),
                    c.localized_registered,
                    c.localized,
                    opt(c.recall),
                    c.brier,
                    c.brier_base_rate,
                    c.auc.map_or("–".to_string(), |a| format!("{a:.3}")),
                    c.ece
                );
            }
            let _ = writeln!(md, "\nReliability (mean p → registered share, cases per bin of width 0.1; `reliability.png`):\n");
            for c in &self.calibration {
                let bins: Vec<String> = c.bins.iter().filter(|b| b.cases > 0).map(|b| format!("[{:.1}, {:.1}): {:.2} → {:.2} ({})", b.lower, b.upper, b.mean_p, b.registered_share, b.cases)).collect();
                let _ = writeln!(md, "- {}: {}", c.method, bins.join("; "));
            }
        }

        let _ = writeln!(md, "\n## Table 2: computational resources (this machine's CPU)\n");
        let _ = writeln!(md, "| Method | Param. (MB, fp32) | Mem. (GB, peak RSS of the evaluator) | Time (s, mean per case) |");
        let _ = writeln!(md, "|---|---|---|---|");
        let mem = self.resources.peak_rss_bytes.map_or("–".into(), |b| format!("{:.3}", b as f64 / 1e9));
        for m in &self.methods {
            let params = m.parameters.map_or("–".into(), |p| format!("{:.3}", p as f64 * 4.0 / 1e6));
            let time = m.per_iteration.last().map_or(0.0, |r| r.elapsed_ms.mean) / 1e3;
            let _ = writeln!(md, "| {} | {} | {} | {:.4} |", m.method, params, mem, time);
        }
        if let Some(prep) = &self.resources.map_prepare_ms {
            let _ = writeln!(md, "\nMap preparation (N-point sampling + point encoder, once per map, cached by the server; not in the times above): {} ms.", pm(prep, 1));
        }

        let _ = writeln!(md, "\n## Phase times (ms, mean ± std per case)\n");
        let _ = writeln!(md, "| Method | Phase | Time (ms) |");
        let _ = writeln!(md, "|---|---|---|");
        for m in &self.methods {
            for (phase, s) in &m.phases_ms {
                let _ = writeln!(md, "| {} | {} | {} |", m.method, phase, pm(s, 2));
            }
        }
        md
    }
}
