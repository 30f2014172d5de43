//! The evaluation run: cases in, every method on every case, records and report out.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};

use crate::agent::SearchConfig;
use crate::agent::SearchTuning;
use crate::geometry::{ActionFrame, ActionSet, Pose, PoseError};
use crate::model::{BackendOptions, Calibration, ModelSet};

use super::data::Dataset;
use super::calibration::CalibrationReport;
use super::learned::{AGENT, AGENT_SINGLE_START, Learned};
use super::matching::MatchStrategy;
use super::methods::{EvalCase, Expert, Method, NoOp};
use super::perturbations::{PerturbationFile, Priors};
use crate::atomic_file::write_atomic;
use super::pnp::RansacOptions;
use super::plots::{RELIABILITY_PNG, write_figure5, write_reliability};
use super::report::{CaseRecord, EvalReport, Resources, rotation_thresholds, summarise, translation_thresholds};
use super::summary::MeanStd;

/// Everything one evaluation needs (the CLI fills it from flags).
#[derive(Debug, Clone)]
pub struct EvalConfig {
    pub data: PathBuf,
    pub perturbations: PathBuf,
    pub out: PathBuf,
    /// Model directory (manifest + four graphs); without it only the reference methods run.
    pub models: Option<PathBuf>,
    pub ort_lib: Option<PathBuf>,
    pub threads: usize,
    pub iterations: usize,
    /// Starts of the agent's multi-start search; with more than one, the single-start agent
    /// (the paper's protocol) is reported too.
    pub hypotheses: usize,
    /// The rest of the search's settings, as the server takes them.
    pub tuning: SearchTuning,
    /// The bound every case's request states on its prior (`--prior-bound`).
    pub prior_bound: Option<crate::agent::PriorBound>,
    pub seed: u64,
    pub frame_stride: usize,
    pub max_cases: Option<usize>,
    /// Motions drawn per selected frame when the perturbation file is created (consecutive
    /// cases of one frame; 1 = the file format's original one-per-frame layout).
    pub cases_per_frame: usize,
    /// The regime of the priors when the perturbation file is created.
    pub priors: Priors,
    /// The expert's action frame; `None`: the model's (`camera_y` without a model).
    pub action_frame: Option<ActionFrame>,
    /// N when no model is given (the model's manifest decides otherwise).
    pub num_points: usize,
    pub ransac: RansacOptions,
    /// How the one-shot baseline pairs points with image cells.
    pub matching: MatchStrategy,
    pub progress: bool,
    /// The command line, recorded in the outputs.
    pub command: String,
    /// Overlays of this many worst cases (by final RTE) into `<out>/worst/`; 0: none.
    pub worst: usize,
    /// Every hypothesis's trajectory in the agent's case records (`Learned::run_agent`).
    pub record_hypotheses: bool,
    /// Run the one-shot baseline (with a model).
    pub baseline: bool,
}

impl EvalConfig {
    /// The agent's search as the server would run it with these settings.
    pub fn search(&self) -> SearchConfig {
        SearchConfig { prior_bound: self.prior_bound, ..self.tuning.search(self.hypotheses, self.iterations) }
    }
}

/// Where each record came from: its case's index in the perturbation file and the method's final
/// pose (for the worst-case pictures; not written to `cases.json`).
#[derive(Debug, Clone, Copy)]
pub struct RecordOrigin {
    pub case: usize,
    pub final_pose: Option<Pose>,
}

/// Runs every method on every case; one record per (case, method), and each record's origin.
pub fn evaluate(
    cases: impl Iterator<Item = Result<EvalCase>>,
    methods: &mut [Box<dyn Method>],
    progress: &ProgressBar,
) -> Result<(Vec<CaseRecord>, Vec<RecordOrigin>)> {
    let mut records = Vec::new();
    let mut origins = Vec::new();
    for (index, case) in cases.enumerate() {
        let case = case?;
        for method in methods.iter_mut() {
            let runs = method
                .run(&case)
                .with_context(|| format!("{:?} on sequence {} frame {}", method.names(), case.perturbation.sequence, case.perturbation.frame))?;
            for run in runs {
                origins.push(RecordOrigin { case: index, final_pose: run.poses.last().copied() });
                records.push(CaseRecord {
                    sequence: case.perturbation.sequence.clone(),
                    frame: case.perturbation.frame,
                    errors: run.poses.iter().map(|p| PoseError::between(p, &case.truth)).collect(),
                    method: run.method,
                    elapsed_ms: run.elapsed_ms,
                    phases_ms: run.phases_ms.into_iter().collect(),
                    notes: run.notes,
                });
            }
        }
        progress.inc(1);
    }
    progress.finish_and_clear();
    Ok((records, origins))
}

/// Peak resident set size of this process (Linux `VmHWM`).
pub fn peak_rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// The whole command: load, evaluate, write `eval.json`, `cases.json`, `tables.md` and the plots.
pub fn run(config: &EvalConfig) -> Result<EvalReport> {
    config.tuning.check(config.hypotheses as u32).map_err(|e| anyhow::anyhow!("--hypotheses and --axis-starts: {e}"))?;
    // The model set first: a run that cannot load it fails before it writes anything.
    let models = match &config.models {
        Some(dir) => Some(ModelSet::load(dir, BackendOptions { intra_threads: config.threads, ort_lib: config.ort_lib.clone() }).with_context(|| {
            format!("no usable model set at {}: pass --models DIR, or --reference-only for the expert and no-op alone", dir.display())
        })?),
        None => None,
    };
    let dataset = Dataset::open(&config.data)?;
    let frames: Vec<(String, usize)> = dataset
        .frames(config.frame_stride, config.max_cases)
        .into_iter()
        .flat_map(|f| std::iter::repeat_n(f, config.cases_per_frame.max(1)))
        .collect();
    let (file, created) = PerturbationFile::load_or_create(&config.perturbations, &frames, config.seed, config.priors)?;
    if created {
        tracing::info!(cases = file.cases.len(), path = %config.perturbations.display(), seed = config.seed, "wrote new perturbation file");
    } else {
        tracing::info!(cases = file.cases.len(), path = %config.perturbations.display(), "read perturbation file");
    }

    let mut methods: Vec<Box<dyn Method>> = Vec::new();
    let mut graph_parameters = BTreeMap::new();
    let (mut num_points, mut actions) = (config.num_points, ActionSet::default());
    let mut learned_index = None;
    let mut provenance = serde_json::Value::Null;
    let mut calibration = None;
    if let Some(set) = &models {
        calibration = set.manifest.calibrator.as_ref().map(|c| Calibration::new(Some(c), None));
        num_points = set.manifest.points.num_points;
        provenance = set.manifest.provenance.clone();
        actions = set.manifest.action_set();
        if let Some(map) = set.manifest.parameters.as_object() {
            graph_parameters = map.iter().filter_map(|(k, v)| v.as_u64().map(|n| (k.clone(), n))).collect();
        }
        learned_index = Some(methods.len());
        methods.push(Box::new(Learned::new(Box::new(set.backend()?), config.search(), config.ransac, config.matching, config.record_hypotheses, config.baseline)));
    }
    if let Some(frame) = config.action_frame {
        actions = actions.with_frame(frame);
    }
    tracing::info!(action_frame = %actions.frame, "expert's action frame");
    methods.push(Box::new(Expert { actions, iterations: config.iterations }));
    methods.push(Box::new(NoOp));

    let progress = if config.progress { ProgressBar::new(file.cases.len() as u64) } else { ProgressBar::hidden() };
    progress.set_style(ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} cases, eta {eta}").unwrap_or_else(|_| ProgressStyle::default_bar()));
    let cases = file.cases.iter().map(|p| dataset.case(p, num_points));
    let (records, origins) = evaluate(cases, &mut methods, &progress)?;

    let map_prepare_ms = learned_index.and_then(|_| {
        let times: Vec<f64> = records
            .iter()
            .filter(|r| r.method == AGENT)
            .filter_map(|r| r.notes.get("map_prepare_ms").and_then(|v| v.as_f64()))
            .collect();
        (!times.is_empty()).then(|| MeanStd::of(times))
    });
    let parameters = Learned::parameters(&graph_parameters);
    // The verdict's figures for each agent method (none without a calibrator), at the threshold
    // each met: the bounded one for the served search of a bounded run (the single start is
    // never bounded: `SearchConfig::single`).
    let bounded = config.search().prior_bound.is_some();
    let calibration = calibration
        .map(|c| {
            [(AGENT, bounded), (AGENT_SINGLE_START, false)]
                .into_iter()
                .filter_map(|(m, bounded)| {
                    let t = if bounded { c.bounded_threshold() } else { c.threshold() }?;
                    let judged = CalibrationReport::judged(&records, m);
                    (!judged.is_empty()).then(|| CalibrationReport::of(m, t, &judged))
                })
                .collect()
        })
        .unwrap_or_default();
    let report = EvalReport {
        format: "cmr-agent-eval/1".into(),
        data: config.data.display().to_string(),
        perturbations: config.perturbations.display().to_string(),
        models: config.models.as_ref().map(|p| p.display().to_string()),
        cases: file.cases.len(),
        iterations: config.iterations,
        command: config.command.clone(),
        settings: serde_json::json!({
            "baseline_matching": config.matching,
            "ransac_iterations": config.ransac.iterations,
            "ransac_inlier_px": config.ransac.inlier_px,
            "num_points": num_points,
            "hypotheses": config.hypotheses,
            "narrow_after": config.tuning.narrow_after,
            "merge_duplicates": config.tuning.merge_duplicates,
            "keep_prior": config.tuning.keep_prior,
            "refine": config.tuning.refine,
            "polish": config.tuning.polish,
            "prior_margin": config.tuning.prior_margin,
            "prior_bound": config.prior_bound.map(|b| [b.rotation_deg, b.translation_m]),
            "model_provenance": provenance,
        }),
        created_unix_s: std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs()),
        rotation_thresholds_deg: rotation_thresholds(),
        translation_thresholds_m: translation_thresholds(),
        methods: summarise(&records, &parameters),
        resources: Resources { peak_rss_bytes: peak_rss_bytes(), graph_parameters, map_prepare_ms },
        calibration,
    };
    write_outputs(&report, &records, &config.out)?;
    if config.worst > 0 {
        // The agent when a model ran, else the expert: the method whose failures matter.
        let primary = if learned_index.is_some() { AGENT } else { super::methods::EXPERT };
        let worst = worst_cases(&records, &origins, primary, config.worst);
        write_worst(&dataset, &file, &worst, num_points, &config.out.join("worst"))?;
    }
    Ok(report)
}

/// One of the worst cases of a method, by its final RTE.
#[derive(Debug, Clone)]
pub struct WorstCase {
    pub rank: usize,
    pub case: usize,
    pub method: String,
    pub final_pose: Pose,
    pub error: PoseError,
}

/// The `k` records of `method` with the largest final RTE (worst first; ties by case order).
pub fn worst_cases(records: &[CaseRecord], origins: &[RecordOrigin], method: &str, k: usize) -> Vec<WorstCase> {
    let mut of_method: Vec<(usize, &CaseRecord, Pose)> = records
        .iter()
        .zip(origins)
        .filter(|(r, _)| r.method == method)
        .filter_map(|(r, o)| Some((o.case, r, o.final_pose?)))
        .filter(|(_, r, _)| !r.errors.is_empty())
        .collect();
    let rte = |r: &CaseRecord| r.errors.last().map_or(0.0, |e| if e.rte_m.is_finite() { e.rte_m } else { f64::INFINITY });
    of_method.sort_by(|a, b| rte(b.1).total_cmp(&rte(a.1)).then(a.0.cmp(&b.0)));
    of_method
        .into_iter()
        .take(k)
        .enumerate()
        .map(|(i, (case, r, pose))| WorstCase { rank: i + 1, case, method: method.to_string(), final_pose: pose, error: *r.errors.last().expect("non-empty") })
        .collect()
}

/// Writes one overlay per worst case into `dir` (prior, final and truth panels, the case's N
/// sampled map points on its full image), and `index.json` naming them. Replaces earlier ones.
pub fn write_worst(dataset: &Dataset, file: &PerturbationFile, worst: &[WorstCase], num_points: usize, dir: &Path) -> Result<()> {
    if dir.is_dir() {
        for entry in std::fs::read_dir(dir)?.flatten() {
            let name = entry.file_name().to_string_lossy().to_string();
            if name.ends_with(".png") || name == "index.json" {
                std::fs::remove_file(entry.path())?;
            }
        }
    }
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut index = Vec::new();
    for w in worst {
        let p = &file.cases[w.case];
        let case = dataset.case(p, num_points)?;
        let prior_error = PoseError::between(&case.initial, &case.truth);
        let label = |name: &str, e: &PoseError| format!("{name}: RTE {:.2} m, RRE {:.2}°", e.rte_m, e.rre_geodesic_deg);
        let overlay = crate::render::Overlay {
            image: &case.image,
            intrinsics: case.intrinsics,
            points: &case.map_points,
            panels: vec![
                crate::render::PosePanel::new(format!("seq {} frame {} case {}  {}", p.sequence, p.frame, w.case, label("prior", &prior_error)), case.initial),
                crate::render::PosePanel::new(label(&format!("final ({})", w.method), &w.error), w.final_pose),
                crate::render::PosePanel::new("truth", case.truth),
            ],
            strip: Vec::new(),
        };
        let name = format!("{:02}_seq{}_frame{:06}_case{}.png", w.rank, p.sequence, p.frame, w.case);
        write_atomic(&dir.join(&name), &overlay.png()?)?;
        index.push(serde_json::json!({
            "rank": w.rank, "file": name, "case": w.case, "sequence": p.sequence, "frame": p.frame, "method": w.method,
            "final_rte_m": w.error.rte_m, "final_rre_geodesic_deg": w.error.rre_geodesic_deg,
            "prior_rte_m": prior_error.rte_m, "prior_rre_geodesic_deg": prior_error.rre_geodesic_deg,
        }));
    }
    write_atomic(&dir.join("index.json"), serde_json::to_string_pretty(&index)?.as_bytes())?;
    Ok(())
}

pub fn write_outputs(report: &EvalReport, records: &[CaseRecord], out: &Path) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    write_atomic(&out.join("eval.json"), serde_json::to_string_pretty(report)?.as_bytes())?;
    write_atomic(&out.join("cases.json"), serde_json::to_string(records)?.as_bytes())?;
    write_atomic(&out.join("tables.md"), report.markdown().as_bytes())?;
    if !report.calibration.is_empty() {
        write_reliability(&report.calibration, &out.join(RELIABILITY_PNG))?;
    }
    write_figure5(report, out)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::maps::formats::{PointCloud, write_kitti_bin};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A tiny KITTI-odometry sequence: random street-like scans, flat grey images, and a
    /// KITTI-like calibration with the velodyne axes exactly permuted into the camera's.
    pub(crate) fn write_tiny_sequence(root: &Path, frames: usize) {
        let seq = root.join("00");
        std::fs::create_dir_all(seq.join("velodyne")).unwrap();
        std::fs::create_dir_all(seq.join("image_2")).unwrap();
        let p = |tx: f64| format!("7.0e+02 0 6.2e+02 {tx} 0 7.0e+02 1.87e+02 0 0 0 1 0");
        let calib = format!(
            "P0: {}\nP1: {}\nP2: {}\nP3: {}\nTr: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27\n",
            p(0.0),
            p(-386.0),
            p(45.0),
            p(-337.0)
        );
        std::fs::write(seq.join("calib.txt"), calib).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for f in 0..frames {
            let xyz: Vec<[f32; 3]> = (0..3000)
                .map(|_| [rng.random_range(-40.0..40.0), rng.random_range(-40.0..40.0), rng.random_range(-1.7..4.0)])
                .collect();
            // Intensity varies from point to point (without drawing from `rng`), so a set that
            // reads it sees more than a constant.
            let cloud = PointCloud { intensity: Some((0..xyz.len()).map(|i| ((i * 37) % 100) as f32 / 100.0).collect()), xyz };
            std::fs::write(seq.join("velodyne").join(format!("{f:06}.bin")), write_kitti_bin(&cloud)).unwrap();
            image::RgbImage::from_pixel(1241, 376, image::Rgb([90, 100, 110])).save(seq.join("image_2").join(format!("{f:06}.png"))).unwrap();
        }
    }

    pub(crate) fn config(root: &Path, out: &Path) -> EvalConfig {
        EvalConfig {
            data: root.to_path_buf(),
            perturbations: out.join("perturbations.json"),
            out: out.to_path_buf(),
            models: None,
            ort_lib: None,
            threads: 1,
            iterations: 10,
            hypotheses: 1,
            tuning: SearchTuning { narrow_after: 0, merge_duplicates: false, keep_prior: false, refine: false, polish: false, prior_margin: 0.0, ..SearchTuning::default() },
            prior_bound: None,
            seed: 3,
            frame_stride: 1,
            max_cases: None,
            cases_per_frame: 1,
            priors: Priors::Protocol,
            action_frame: None,
            num_points: 2048,
            ransac: RansacOptions::default(),
            matching: MatchStrategy::Ratio,
            progress: false,
            command: "test".into(),
            worst: 2,
            record_hypotheses: false,
            baseline: true,
        }
    }

    #[test]
    fn reference_methods_on_a_generated_sequence_write_every_output_reproducibly() {
        let dir = tempfile::tempdir().unwrap();
        let (data, out) = (dir.path().join("data"), dir.path().join("out"));
        write_tiny_sequence(&data, 3);
        let config = config(&data, &out);
        let report = run(&config).unwrap();
        assert_eq!(report.cases, 3);
        for file in ["eval.json", "cases.json", "tables.md", "fig5_rotation.png", "fig5_translation.png", "perturbations.json"] {
            assert!(out.join(file).is_file(), "{file}");
        }
        let names: Vec<&str> = report.methods.iter().map(|m| m.method.as_str()).collect();
        assert_eq!(names, vec!["expert (oracle)", "no-op"]);

        // No-op: the error is the perturbation itself.
        let cases = PerturbationFile::read(&config.perturbations).unwrap().cases;
        let noop = &report.methods[1].summary.all;
        let expected_rte = cases.iter().map(|c| c.dx_m.hypot(c.dy_m)).sum::<f64>() / 3.0;
        let expected_rre = cases.iter().map(|c| c.yaw_deg.abs()).sum::<f64>() / 3.0;
        assert!((noop.rte_m.mean - expected_rte).abs() < 1e-6, "{} vs {expected_rte}", noop.rte_m.mean);
        assert!((noop.rre_geodesic_deg.mean - expected_rre).abs() < 1e-6);
        // Expert: near zero after K iterations, all registered.
        let expert = &report.methods[0];
        assert_eq!(expert.per_iteration.len(), 10);
        assert_eq!(expert.summary.registration_recall, 1.0);
        assert!(expert.summary.all.rte_m.mean < 0.06 && expert.summary.all.rre_geodesic_deg.mean < 0.06);

        // A second run reads the same perturbation file and reproduces the records.
        let first = std::fs::read_to_string(out.join("cases.json")).unwrap();
        let again = run(&EvalConfig { seed: 99, ..config }).unwrap();
        let second = std::fs::read_to_string(out.join("cases.json")).unwrap();
        let errors = |text: &str| -> Vec<Vec<PoseError>> {
            serde_json::from_str::<Vec<CaseRecord>>(text).unwrap().into_iter().map(|r| r.errors).collect()
        };
        assert_eq!(errors(&first), errors(&second));
        assert_eq!(again.methods[1].summary, report.methods[1].summary);
        // The expert's two worst cases (no model ran), worst first, as pictures.
        let index: Vec<serde_json::Value> = serde_json::from_str(&std::fs::read_to_string(out.join("worst/index.json")).unwrap()).unwrap();
        assert_eq!(index.len(), 2);
        assert!(index[0]["final_rte_m"].as_f64().unwrap() >= index[1]["final_rte_m"].as_f64().unwrap());
        for w in &index {
            let img = image::open(out.join("worst").join(w["file"].as_str().unwrap())).unwrap();
            assert_eq!(img.width(), 1241);
            assert!(img.height() > 3 * 376, "three panels");
        }
        let tables = std::fs::read_to_string(out.join("tables.md")).unwrap();
        assert!(tables.contains("## Table 1") && tables.contains("## Table 4: expert (oracle)") && tables.contains("## Table 2"));
    }

    /// `--cases-per-frame K` draws K consecutive motions per frame (one per frame draws exactly
    /// what the one-per-frame layout always drew), and `--action-frame map_z` steps the expert
    /// about the map's up axis (on this level generated rig it reaches the same floor).
    #[test]
    fn several_cases_per_frame_and_the_map_z_expert() {
        let dir = tempfile::tempdir().unwrap();
        let (data, out) = (dir.path().join("data"), dir.path().join("out"));
        write_tiny_sequence(&data, 2);
        let config = EvalConfig { cases_per_frame: 3, action_frame: Some(ActionFrame::MapZ), iterations: 10, ..config(&data, &out) };
        let report = run(&config).unwrap();
        assert_eq!(report.cases, 6);
        let cases = PerturbationFile::read(&config.perturbations).unwrap().cases;
        let frames: Vec<usize> = cases.iter().map(|c| c.frame).collect();
        assert_eq!(frames, vec![0, 0, 0, 1, 1, 1]);
        assert_eq!(cases[0], PerturbationFile::generate(&[("00".into(), 0)], config.seed, Priors::Protocol).cases[0]);
        assert!(cases[0] != cases[1]);
        let expert = &report.methods[0];
        assert_eq!(expert.summary.registration_recall, 1.0);
        assert!(expert.summary.all.rte_m.mean < 0.06 && expert.summary.all.rre_geodesic_deg.mean < 0.06);
    }

    #[test]
    fn a_perturbation_file_naming_unknown_frames_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (data, out) = (dir.path().join("data"), dir.path().join("out"));
        write_tiny_sequence(&data, 1);
        let config = config(&data, &out);
        let mut file = PerturbationFile::generate(&[("00".into(), 0), ("00".into(), 7)], 1, Priors::Protocol);
        file.cases[1].frame = 7;
        file.write(&config.perturbations).unwrap();
        let err = run(&config).unwrap_err();
        assert!(format!("{err:#}").contains("no frame 7"), "{err:#}");
    }

    /// `eval` with a set whose point encoder reads intensity: each case keeps its scan's
    /// intensity beside its points (what `prepare_map` gives the encoder), and the learned
    /// methods run with it.
    #[test]
    fn eval_gives_an_intensity_set_each_scans_intensity() {
        let dir = tempfile::tempdir().unwrap();
        let (data, out) = (dir.path().join("data"), dir.path().join("out"));
        write_tiny_sequence(&data, 1);
        let perturbation = PerturbationFile::generate(&[("00".into(), 0)], 3, Priors::Protocol).cases[0].clone();
        let case = Dataset::open(&data).unwrap().case(&perturbation, 2048).unwrap();
        let scan = crate::kitti::read_velodyne(&data.join("00/velodyne/000000.bin")).unwrap();
        assert_eq!(case.map_cloud.len(), scan.len());
        assert_eq!(case.map_intensity, Some(scan.iter().map(|p| p.intensity).collect::<Vec<_>>()));
        let models = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model-intensity");
        let config = EvalConfig { models: Some(models), iterations: 2, hypotheses: 1, ..config(&data, &out) };
        let report = run(&config).unwrap();
        assert_eq!(report.methods[0].method, AGENT);
        assert_eq!(report.methods[0].per_iteration.len(), 2);
    }

    /// The learned methods through real ONNX graphs (the committed tiny contract model): every
    /// method reports, the agent at every iteration, and each record's first agent pose is
    /// reachable from the initial pose by one action of the set.
    #[test]
    fn learned_methods_run_through_the_server_code_path() {
        let dir = tempfile::tempdir().unwrap();
        let (data, out) = (dir.path().join("data"), dir.path().join("out"));
        write_tiny_sequence(&data, 2);
        let models = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model");
        let config = EvalConfig { models: Some(models), iterations: 4, hypotheses: 2, record_hypotheses: true, ..config(&data, &out) };
        let report = run(&config).unwrap();
        let names: Vec<&str> = report.methods.iter().map(|m| m.method.as_str()).collect();
        let single = super::super::learned::AGENT_SINGLE_START;
        assert_eq!(names, vec![AGENT, single, super::super::learned::BASELINE, "expert (oracle)", "no-op"]);
        let agent = &report.methods[0];
        assert_eq!(agent.per_iteration.len(), 4);
        assert!(agent.parameters.unwrap() > report.methods[2].parameters.unwrap());
        assert!(agent.phases_ms.contains_key("agent steps") && report.methods[2].phases_ms.contains_key("matching"));
        assert!(agent.phases_ms.get("agent steps: judge's views").is_some_and(|t| t.mean > 0.0), "the search judges with its views");
        assert!(report.resources.map_prepare_ms.is_some_and(|m| m.n == 2));
        assert!(report.resources.peak_rss_bytes.is_some_and(|b| b > 0));
        assert!(report.calibration.is_empty(), "no calibrator, no verdict figures");
        let records: Vec<CaseRecord> = serde_json::from_str(&std::fs::read_to_string(out.join("cases.json")).unwrap()).unwrap();
        assert_eq!(records.len(), 2 * 5);
        for r in records.iter().filter(|r| r.method == AGENT || r.method == single) {
            assert_eq!(r.errors.len(), 4);
            assert!(r.elapsed_ms.windows(2).all(|w| w[0] <= w[1]));
            assert!(r.notes["iterations_run"].as_u64().unwrap() >= 1);
            // The tiny model has no calibrator: no probability, never localized; the signals
            // are recorded all the same (what a calibrator is fitted on).
            assert!(r.notes["p_registered"].is_null() && r.notes["localized"] == false);
            assert_eq!(r.notes["signals"]["log2_starts"], if r.method == AGENT { 1.0 } else { 0.0 });
            let starts = if r.method == AGENT { 2 } else { 1 };
            assert_eq!(r.notes["alignment"].as_array().unwrap().len(), starts);
            // `--record-hypotheses`: every start's trajectory, on the searched agent only; its
            // last step's errors are the record's when that start is the chosen one.
            let Some(hypotheses) = r.notes.get("hypotheses").and_then(|h| h.as_array()) else {
                assert_eq!(r.method, single, "the search records its hypotheses");
                continue;
            };
            assert_eq!(hypotheses.len(), 2);
            // The search (the judge's views by default) answers with a pose some start visited.
            let visited: Vec<f64> = hypotheses
                .iter()
                .flat_map(|h| std::iter::once(&h["start"]).chain(h["steps"].as_array().unwrap()))
                .map(|p| p["rte_m"].as_f64().unwrap())
                .collect();
            assert!(visited.iter().any(|e| (e - r.errors[3].rte_m).abs() < 1e-9), "{visited:?} vs {}", r.errors[3].rte_m);
            for h in hypotheses {
                assert!(h["steps"].as_array().unwrap().len() <= 4);
                assert_eq!(h["start"]["camera_from_map"].as_array().unwrap().len(), 12);
                assert!(h["start"]["frustum_iou"].as_f64().is_some_and(|iou| (0.0..=1.0).contains(&iou)));
                for step in h["steps"].as_array().unwrap() {
                    // What the policy said at the pose before the step: a softmax per DoF, the
                    // chosen index its argmax.
                    let probabilities = step["probabilities"].as_array().unwrap();
                    assert_eq!(probabilities.len(), 3);
                    for (dof, row) in probabilities.iter().enumerate() {
                        let row: Vec<f64> = row.as_array().unwrap().iter().map(|p| p.as_f64().unwrap()).collect();
                        assert!((row.iter().sum::<f64>() - 1.0).abs() < 1e-4, "{row:?}");
                        let chosen = step["action_indices"][dof].as_u64().unwrap() as usize;
                        assert!(row.iter().all(|p| *p <= row[chosen]));
                    }
                    assert!(step["value"].as_f64().is_some_and(f64::is_finite) && step["policy_certainty"].as_f64().is_some());
                }
            }
        }
        for r in records.iter().filter(|r| r.method == super::super::learned::BASELINE) {
            assert_eq!(r.errors.len(), 1);
            assert!(r.notes["matches"].as_u64().is_some() && r.notes["solved"].is_boolean());
        }
    }
}
