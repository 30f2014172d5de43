//! `cmr-agent localize`: one localization from files, no HTTP, through the server's own
//! [`Localizer`] (same validation, limits, decode and search as `POST /v1/maps/{id}/localize`),
//! printing the same response JSON. The map file is registered in a temporary map store first.
//! [`OfflineLocalizer`] is that path for any command-line tool (`cmr-agent track` uses it too).

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result, anyhow};

use crate::maps::formats::CloudFormat;
use crate::maps::{MapCache, MapMetadata, MapStore, Maps, Upload};
use crate::model::{BackendOptions, ModelSet};
use crate::serving::{ImagePayload, Lifecycle, LocalizeError, LocalizeRequest, Localized, Localizer, Scheduler};

use super::config::ServeArgs;
use super::types::{LocalizeResponse, TimingsMs};

#[derive(Debug, Clone, clap::Args)]
pub struct LocalizeArgs {
    /// Point cloud of the map region (KITTI .bin, PCD or PLY); `<stem>.json` next to it is read
    /// as the region's metadata when present.
    #[arg(long)]
    pub map: PathBuf,
    /// A localize request body (JSON, as for the HTTP API), e.g. examples/localize-demo.json.
    #[arg(long)]
    pub request: PathBuf,
    /// Replaces the request's max_iterations (checked like the request's own value).
    #[arg(long)]
    pub max_iterations: Option<u32>,
    /// Replaces the request's hypotheses (checked like the request's own value).
    #[arg(long)]
    pub hypotheses: Option<u32>,
    /// Every `serve` setting (models, limits, search defaults) applies here too.
    #[command(flatten)]
    pub serve: ServeArgs,
}

pub fn run(args: LocalizeArgs) -> Result<()> {
    let started = std::time::Instant::now();
    let bytes = std::fs::read(&args.map).with_context(|| format!("cannot read {}", args.map.display()))?;
    let format = args.map.extension().and_then(|e| e.to_str()).and_then(CloudFormat::from_extension);
    let sidecar = args.map.with_extension("json");
    let metadata: Option<MapMetadata> = match std::fs::read(&sidecar) {
        Ok(text) => Some(serde_json::from_slice(&text).with_context(|| format!("{}", sidecar.display()))?),
        Err(_) => None,
    };
    let mut request: LocalizeRequest = serde_json::from_slice(&std::fs::read(&args.request)?)
        .with_context(|| format!("{} is not a localize request", args.request.display()))?;
    request.max_iterations = args.max_iterations.or(request.max_iterations);
    request.hypotheses = args.hypotheses.or(request.hypotheses);
    let image = ImagePayload::Base64(std::mem::take(&mut request.image));

    let dir = tempfile::tempdir()?;
    let (store, _) = MapStore::open(dir.path()).map_err(|e| anyhow!("{e}"))?;
    let offline = OfflineLocalizer::new(&args.serve, store)?;
    let id = "map";
    offline.localizer.maps.register(id, Upload { bytes: &bytes, format, gzip: false, max_bytes: usize::MAX }, Default::default(), metadata).map_err(|e| anyhow!("{}: {e}", args.map.display()))?;
    let done = offline.localize(id, &request, image).map_err(|e| anyhow!("{e}"))?;
    drop(offline);
    let loc = &done.localization;
    let timings = TimingsMs::new(done.queue_ms, done.decode_ms, &loc.timings, started.elapsed().as_secs_f64() * 1000.0);
    let name = args.map.file_stem().and_then(|s| s.to_str()).unwrap_or(id);
    println!("{}", serde_json::to_string_pretty(&LocalizeResponse::new(name, loc, done.prior_source, timings))?);
    Ok(())
}

/// The server's localize path without HTTP, for the command-line tools (`localize`, `track`):
/// the models, a map store, one worker's scheduler and a ready [`Localizer`], driven from
/// synchronous code. Dropping it stops the worker.
pub struct OfflineLocalizer {
    pub localizer: Localizer,
    scheduler: Arc<Scheduler>,
    runtime: tokio::runtime::Runtime,
}

impl OfflineLocalizer {
    /// Loads `config.models` and serves from `store` with `config`'s limits and search defaults
    /// (one worker). Errors: the models or ONNX Runtime cannot be loaded.
    pub fn new(config: &ServeArgs, store: MapStore) -> Result<Self> {
        // One request at a time: one worker, with the cores its threads (unless given).
        let one = ServeArgs { workers: 1, ..config.clone() };
        let models = ModelSet::load(&config.models, BackendOptions { intra_threads: one.intra_threads(), ort_lib: config.ort_lib.clone() })?;
        let maps = Arc::new(Maps::new(store, MapCache::new(config.cache_mb.saturating_mul(1024 * 1024)), Box::new(models.backend()?), config.regions()));
        let scheduler = Arc::new(Scheduler::start(&models.factory(), one.scheduler())?);
        let lifecycle = Arc::new(Lifecycle::default());
        lifecycle.set_ready();
        let localizer = Localizer::new(maps, scheduler.clone(), lifecycle, models.manifest.clone(), config.localizer());
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        Ok(Self { localizer, scheduler, runtime })
    }

    /// One localization of map `id`, exactly as `POST /v1/maps/{id}/localize` runs it
    /// (admission, validation, decode, search, deadline); `request.image` is ignored.
    pub fn localize(&self, id: &str, request: &LocalizeRequest, image: ImagePayload) -> Result<Localized, LocalizeError> {
        self.runtime.block_on(async {
            let admission = self.localizer.admit()?;
            self.localizer.localize(admission, id, request, image).await
        })
    }
}

impl Drop for OfflineLocalizer {
    fn drop(&mut self) {
        self.scheduler.shutdown(std::time::Duration::from_secs(2));
    }
}
