//! `cmr-agent localize`: one localization from files, no HTTP, same request/response JSON as
//! `POST /v1/maps/{id}/localize` (handy for debugging a map or a model).

use std::path::PathBuf;

use anyhow::{Context, Result, anyhow};

use crate::agent;
use crate::geometry::pose::PoseMatrix;
use crate::geometry::{Intrinsics, Pose};
use crate::maps::MapMetadata;
use crate::maps::formats::{CloudFormat, parse};
use crate::model::{BackendOptions, ModelSet};

use super::decode::decode_base64_image;
use super::types::{LocalizeRequest, LocalizeResponse, TimingsMs};

#[derive(Debug, Clone, clap::Args)]
pub struct LocalizeArgs {
    /// Point cloud of the map region (KITTI .bin, PCD or PLY); `<stem>.json` next to it is read
    /// as the region's metadata when present.
    #[arg(long)]
    pub map: PathBuf,
    /// A localize request body (JSON, as for the HTTP API), e.g. examples/localize-demo.json.
    #[arg(long)]
    pub request: PathBuf,
    #[arg(long, env = "CMR_MODELS", default_value = "models")]
    pub models: PathBuf,
    #[arg(long)]
    pub ort_lib: Option<PathBuf>,
    /// Overrides the request's max_iterations.
    #[arg(long)]
    pub max_iterations: Option<u32>,
    /// Overrides the request's hypotheses (starts of the multi-start search).
    #[arg(long)]
    pub hypotheses: Option<u32>,
    #[command(flatten)]
    pub search: super::config::SearchTuning,
}

pub fn run(args: LocalizeArgs) -> Result<()> {
    let started = std::time::Instant::now();
    let models = ModelSet::load(&args.models, BackendOptions { intra_threads: num_cpus(), ort_lib: args.ort_lib.clone() })?;
    let mut backend = models.backend()?;
    let bytes = std::fs::read(&args.map).with_context(|| format!("cannot read {}", args.map.display()))?;
    let format = args
        .map
        .extension()
        .and_then(|e| e.to_str())
        .and_then(CloudFormat::from_extension)
        .or_else(|| CloudFormat::sniff(&bytes))
        .ok_or_else(|| anyhow!("{}: unknown point-cloud format", args.map.display()))?;
    let cloud = parse(&bytes, format).map_err(|e| anyhow!("{}: {e}", args.map.display()))?;
    let sidecar = args.map.with_extension("json");
    let metadata: MapMetadata = match std::fs::read(&sidecar) {
        Ok(text) => serde_json::from_slice(&text).with_context(|| format!("{}", sidecar.display()))?,
        Err(_) => MapMetadata::default(),
    };
    let request: LocalizeRequest = serde_json::from_slice(&std::fs::read(&args.request)?)
        .with_context(|| format!("{} is not a localize request", args.request.display()))?;

    let map = agent::prepare_map(&mut backend, &cloud.xyz)?;
    let k = request.intrinsics;
    let intrinsics = Intrinsics { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy };
    let t = std::time::Instant::now();
    let image = decode_base64_image(&request.image, 16384).map_err(|e| anyhow!("{e}"))?;
    let (tensor, crop_k) = agent::prepare_image(&image, &intrinsics, &models.manifest)?;
    let decode_ms = agent::ms(t);
    let prior = match request.prior_camera_from_map {
        Some(m) => Pose::try_from(PoseMatrix(m)).map_err(|e| anyhow!("prior_camera_from_map: {e}"))?,
        None => metadata.initial_pose().unwrap_or_else(Pose::identity),
    };
    let iterations = args.max_iterations.or(request.max_iterations).unwrap_or(10).clamp(1, super::config::MAX_ITERATIONS);
    let hypotheses = args.hypotheses.or(request.hypotheses).unwrap_or(super::config::DEFAULT_HYPOTHESES);
    let hypotheses = hypotheses.clamp(1, agent::search::MAX_HYPOTHESES as u32) as usize;
    let search = args.search.search(hypotheses, iterations as usize);
    let loc = agent::localize(&mut backend, &map, &tensor, crop_k, prior, search)?;
    let timings = TimingsMs::new(0.0, decode_ms, &loc.timings, agent::ms(started));
    let id = args.map.file_stem().and_then(|s| s.to_str()).unwrap_or("map");
    println!("{}", serde_json::to_string_pretty(&LocalizeResponse::new(id, &loc, timings))?);
    Ok(())
}

fn num_cpus() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}
