//! `cmr-agent localize`: one localization from files, no HTTP, through the server's own
//! [`Localizer`] (same validation, limits, decode and search as `POST /v1/maps/{id}/localize`),
//! printing the same response JSON. The map file is registered in a temporary map store first.
//! [`OfflineLocalizer`] is that path for any command-line tool (`cmr-agent track` uses it too).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result, anyhow};

use crate::maps::formats::CloudFormat;
use crate::maps::{MapCache, MapMetadata, MapStore, Maps, Upload};
use crate::model::{BackendOptions, ModelSet};
use crate::serving::{ImagePayload, Lifecycle, LocalizeError, LocalizeRequest, Localized, Localizer, Scheduler};

use super::config::EngineArgs;
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
    /// The localize path's settings (models, limits, search defaults), as `serve` takes them.
    #[command(flatten)]
    pub engine: EngineArgs,
}

pub fn run(args: LocalizeArgs) -> Result<()> {
    let started = std::time::Instant::now();
    let mut request: LocalizeRequest = serde_json::from_slice(&std::fs::read(&args.request).with_context(|| format!("cannot read {}", args.request.display()))?)
        .with_context(|| format!("{} is not a localize request", args.request.display()))?;
    request.max_iterations = args.max_iterations.or(request.max_iterations);
    request.hypotheses = args.hypotheses.or(request.hypotheses);
    let image = ImagePayload::Base64(std::mem::take(&mut request.image));

    let offline = OfflineLocalizer::with_map_file(&args.engine, &args.map)?;
    let done = offline.localize(FILE_REGION_ID, &request, image).map_err(|e| anyhow!("{e}"))?;
    drop(offline);
    let loc = &done.localization;
    let timings = TimingsMs::new(done.queue_ms, done.decode_ms, &loc.timings, started.elapsed().as_secs_f64() * 1000.0);
    println!("{}", serde_json::to_string_pretty(&LocalizeResponse::new(&map_file_name(&args.map), loc, done.prior_source, timings))?);
    Ok(())
}

/// The id under which [`OfflineLocalizer::with_map_file`] registers its map file.
pub const FILE_REGION_ID: &str = "map";

/// What the command-line tools call a region given as a file: its file stem.
pub fn map_file_name(map: &Path) -> String {
    map.file_stem().and_then(|s| s.to_str()).unwrap_or(FILE_REGION_ID).to_string()
}

/// The server's localize path without HTTP, for the command-line tools (`localize`, `track`):
/// the models, a map store, one worker's scheduler and a ready [`Localizer`], driven from
/// synchronous code. Dropping it stops the worker.
pub struct OfflineLocalizer {
    pub localizer: Localizer,
    scheduler: Arc<Scheduler>,
    runtime: tokio::runtime::Runtime,
    /// The temporary store of [`OfflineLocalizer::with_map_file`], removed on drop.
    _scratch: Option<tempfile::TempDir>,
}

impl OfflineLocalizer {
    /// Loads `engine.models` and serves from `store` with `engine`'s limits and search defaults
    /// (one worker). Errors: the models or ONNX Runtime cannot be loaded.
    pub fn new(engine: &EngineArgs, store: MapStore) -> Result<Self> {
        // One request at a time: one worker, with the cores its threads (unless given); a queue
        // as roomy as serve's default, which one request at a time never fills (a finished
        // job's slot is released by the worker a moment after its answer).
        engine.search.check(engine.default_hypotheses).map_err(|e| anyhow::anyhow!("--default-hypotheses and --axis-starts: {e}"))?;
        let models = ModelSet::load(&engine.models, BackendOptions { intra_threads: engine.intra_threads_for(1), ort_lib: engine.ort_lib.clone() })?;
        let maps = Arc::new(Maps::new(store, MapCache::new(engine.cache_mb.saturating_mul(1024 * 1024)), Box::new(models.backend()?), engine.regions()));
        let scheduler = Arc::new(Scheduler::start(&models.factory(), engine.scheduler(1, 64))?);
        let lifecycle = Arc::new(Lifecycle::default());
        lifecycle.set_ready();
        let localizer = Localizer::new(maps, scheduler.clone(), lifecycle, models.manifest.clone(), engine.localizer());
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        Ok(Self { localizer, scheduler, runtime, _scratch: None })
    }

    /// [`OfflineLocalizer::new`] on a temporary store holding one region, id
    /// [`FILE_REGION_ID`]: the point-cloud file `map` (KITTI .bin, PCD, PLY, LAS/LAZ; format
    /// from the extension, else sniffed) registered as `PUT /v1/maps/{id}` registers it, with
    /// `<stem>.json` beside it as its metadata when present.
    /// Errors: the file cannot be read, its sidecar is not metadata, the cloud is refused as an
    /// upload would be (the message names the file), or the models cannot be loaded.
    pub fn with_map_file(engine: &EngineArgs, map: &Path) -> Result<Self> {
        let bytes = std::fs::read(map).with_context(|| format!("cannot read {}", map.display()))?;
        let format = map.extension().and_then(|e| e.to_str()).and_then(CloudFormat::from_extension);
        let sidecar = map.with_extension("json");
        let metadata = match std::fs::read(&sidecar) {
            Ok(text) => Some(MapMetadata::from_json(serde_json::from_slice(&text).with_context(|| format!("{} is not JSON", sidecar.display()))?).with_context(|| sidecar.display().to_string())?),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => return Err(anyhow!("cannot read {}: {e}", sidecar.display())),
        };
        let dir = tempfile::tempdir()?;
        let (store, _) = MapStore::open(dir.path()).map_err(|e| anyhow!("{e}"))?;
        let mut offline = OfflineLocalizer::new(engine, store)?;
        offline._scratch = Some(dir);
        let upload = Upload { bytes: &bytes, format, gzip: false, max_bytes: usize::MAX };
        offline.localizer.maps.register(FILE_REGION_ID, upload, Default::default(), metadata).map_err(|e| anyhow!("{}: {e}", map.display()))?;
        Ok(offline)
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
