//! `cmr-agent eval`: flags and the entry point.

use std::path::PathBuf;

use anyhow::Result;

use super::matching::MatchStrategy;
use super::pnp::RansacOptions;
use super::run::{EvalConfig, run};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// KITTI-odometry data: a dataset root, a directory of sequences, or one sequence.
    #[arg(long)]
    pub data: PathBuf,
    /// Frozen test cases: read if the file exists, else drawn from --seed and written there.
    #[arg(long)]
    pub perturbations: PathBuf,
    /// Output directory for eval.json, cases.json, tables.md, the Fig. 5 PNGs and worst/.
    #[arg(long)]
    pub out: PathBuf,
    /// Model directory (manifest.json + four ONNX graphs): the served one by default, as for
    /// `serve`.
    #[arg(long, env = "CMR_MODELS", default_value = "models")]
    pub models: PathBuf,
    /// Run only the reference methods (greedy expert, no-op): no model is loaded.
    #[arg(long)]
    pub reference_only: bool,
    /// Path of libonnxruntime.so (otherwise the project's usual search).
    #[arg(long, env = "ORT_DYLIB_PATH")]
    pub ort_lib: Option<PathBuf>,
    /// ONNX Runtime intra-op threads.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Agent (and expert) iterations K; every iteration 1..K is reported.
    #[arg(long, default_value_t = 10)]
    pub iterations: usize,
    /// Starts of the agent's multi-start search (the server's default unless given); with more
    /// than one, the single-start agent is evaluated too.
    #[arg(long, default_value_t = crate::agent::DEFAULT_HYPOTHESES as usize)]
    pub hypotheses: usize,
    #[command(flatten)]
    pub search: crate::agent::SearchTuning,
    /// Every case's request states this bound on its prior, `ROTATION_DEG,TRANSLATION_M` (the
    /// request's `prior_bound`: starts within it, the best pose visited inside it answers); for
    /// a fleet-prior case file, `30,5` is what its priors satisfy. Default: none.
    #[arg(long, value_parser = parse_prior_bound)]
    pub prior_bound: Option<crate::agent::PriorBound>,
    /// Seed of the perturbations when the file is created.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Use every n-th frame when creating the perturbation file.
    #[arg(long, default_value_t = 1)]
    pub frame_stride: usize,
    /// At most this many frames when creating the perturbation file.
    #[arg(long)]
    pub max_cases: Option<usize>,
    /// Motions per frame when creating the perturbation file (the paper's protocol on a few real
    /// frames: 8); the cases of one frame are consecutive.
    #[arg(long, default_value_t = 1)]
    pub cases_per_frame: usize,
    /// How far the priors are drawn when creating the perturbation file: `protocol` (the paper's:
    /// any heading, ±10 m) or `fleet` (heading within ±30°, position within 5 m).
    #[arg(long, value_enum, default_value = "protocol")]
    pub priors: super::perturbations::Priors,
    /// The greedy expert's action frame: `camera_y` (yaw about camera y, translation along
    /// camera x / z) or `map_z` (yaw about the map's up axis, translation in its ground plane).
    /// Default: the model's `actions.frame`, `camera_y` with --reference-only.
    #[arg(long)]
    pub action_frame: Option<crate::geometry::ActionFrame>,
    /// RANSAC iterations of the one-shot baseline.
    #[arg(long, default_value_t = 1000)]
    pub ransac_iterations: usize,
    /// RANSAC inlier threshold in pixels of the model's 512×160 crop.
    #[arg(long, default_value_t = 8.0)]
    pub inlier_px: f64,
    /// How the one-shot baseline pairs points with image cells: `ratio` (each predicted-in-view
    /// point's nearest cell, Lowe ratio 0.9, best 4000) or `mutual` (mutual nearest neighbours).
    #[arg(long, value_enum, default_value = "ratio")]
    pub matching: MatchStrategy,
    /// Write overlays (prior, final, truth) of the K worst cases by final RTE into
    /// `<out>/worst/` (the agent's, or the expert's with --reference-only); 0: none.
    #[arg(long, default_value_t = 5)]
    pub worst: usize,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// Record every hypothesis's trajectory of the agent's search in `cases.json` (pose,
    /// alignment score and errors after each step, how it stopped): what search rules are tried
    /// on offline (`scripts/search-rules.py`).
    #[arg(long)]
    pub record_hypotheses: bool,
    /// Skip the one-shot baseline (most of a case's time): for runs that only need the agent,
    /// such as the calibrator's fitting data.
    #[arg(long)]
    pub no_baseline: bool,
}

/// `ROTATION_DEG,TRANSLATION_M`, both positive (rotation at most 180°).
fn parse_prior_bound(text: &str) -> Result<crate::agent::PriorBound, String> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let [rotation, translation] = parts[..] else { return Err(format!("expected ROTATION_DEG,TRANSLATION_M, got {text:?}")) };
    let number = |s: &str| s.parse::<f64>().map_err(|e| format!("{s:?}: {e}"));
    let (rotation_deg, translation_m) = (number(rotation)?, number(translation)?);
    if !(rotation_deg > 0.0 && rotation_deg <= 180.0) || !(translation_m > 0.0 && translation_m.is_finite()) {
        return Err(format!("the rotation must be in (0, 180] degrees and the translation positive, got {text:?}"));
    }
    Ok(crate::agent::PriorBound { rotation_deg, translation_m })
}

pub fn main(args: Args) -> Result<()> {
    if args.iterations == 0 {
        anyhow::bail!("--iterations must be at least 1");
    }
    let config = EvalConfig {
        data: args.data,
        perturbations: args.perturbations,
        out: args.out,
        models: (!args.reference_only).then_some(args.models),
        ort_lib: args.ort_lib,
        threads: args.threads.max(1),
        iterations: args.iterations,
        hypotheses: args.hypotheses.clamp(1, crate::agent::search::MAX_HYPOTHESES),
        tuning: args.search,
        prior_bound: args.prior_bound,
        seed: args.seed,
        frame_stride: args.frame_stride,
        max_cases: args.max_cases,
        cases_per_frame: args.cases_per_frame.max(1),
        priors: args.priors,
        action_frame: args.action_frame,
        num_points: 40_960,
        ransac: RansacOptions { iterations: args.ransac_iterations, inlier_px: args.inlier_px, ..RansacOptions::default() },
        matching: args.matching,
        progress: !args.quiet,
        command: std::env::args().collect::<Vec<_>>().join(" "),
        worst: args.worst,
        record_hypotheses: args.record_hypotheses,
        baseline: !args.no_baseline,
    };
    let report = run(&config)?;
    print!("{}", report.markdown());
    eprintln!("wrote {}/{{eval.json,cases.json,tables.md,fig5_rotation.png,fig5_translation.png,reliability.png,worst/}}", config.out.display());
    Ok(())
}
