//! `cmr-agent serve` configuration: flags, each with an environment-variable fallback.

use std::path::PathBuf;

use crate::agent::search::{DEFAULT_HYPOTHESES, SearchTuning};
use crate::maps::{CropEmbeddings, RegionConfig};
use crate::serving::{ImageLimits, LocalizerConfig, RequestDefaults, SchedulerConfig};

/// `cmr-agent serve`'s settings: the HTTP server's own, plus the localize path's ([`EngineArgs`]).
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {

    /// Address to listen on.
    #[arg(long, env = "CMR_HOST", default_value = "0.0.0.0")]
    pub host: String,
    #[arg(long, env = "CMR_PORT", default_value_t = 8080)]
    pub port: u16,
    /// A second port, on the same address, that answers only `/health`, `/ready` and `/metrics`
    /// with connections of its own (at most 32; headers within 2 s, idle ones closed after 2 s):
    /// an orchestrator's probes get their answer however many clients hold the main port's
    /// `--max-connections`. For probes and scrapers, not clients: keep it off the public
    /// network. Default: none (probes then wait with every other connection).
    #[arg(long, env = "CMR_PROBE_PORT")]
    pub probe_port: Option<u16>,
    /// Directory of map regions (<id>.bin + <id>.json [+ <id>.emb]); created if missing.
    #[arg(long, env = "CMR_MAPS", default_value = "maps")]
    pub maps: PathBuf,
    /// Agent workers, each with its own ONNX Runtime sessions (0 = one per CPU core: measured
    /// the faster default, docs/server.md "Workers x threads").
    #[arg(long, env = "CMR_WORKERS", default_value_t = 0)]
    pub workers: usize,
    /// Requests waiting for a worker before new ones get 429.
    #[arg(long, env = "CMR_QUEUE_CAPACITY", default_value_t = 64)]
    pub queue_capacity: usize,
    /// How long a localize refused with 429 (queue full) waits before the answer, ms: a client
    /// that retries at once cannot turn overload into a flood of refusals that steals the CPU
    /// from admitted work.
    #[arg(long, env = "CMR_SHED_DELAY_MS", default_value_t = 100)]
    pub shed_delay_ms: u64,
    /// How long a client may take to send a whole request body (a map upload included), ms.
    #[arg(long, env = "CMR_BODY_TIMEOUT_MS", default_value_t = 30_000)]
    pub body_timeout_ms: u64,
    /// Largest localize request body, bytes.
    #[arg(long, env = "CMR_MAX_BODY_BYTES", default_value_t = 16 * 1024 * 1024)]
    pub max_body_bytes: usize,
    /// Largest map upload, bytes.
    #[arg(long, env = "CMR_MAX_MAP_BYTES", default_value_t = 256 * 1024 * 1024)]
    pub max_map_bytes: usize,
    /// When set, map uploads/edits/deletes need `Authorization: Bearer <token>`.
    #[arg(long, env = "CMR_ADMIN_TOKEN", hide_env_values = true)]
    pub admin_token: Option<String>,
    /// Open connections at most; more wait in the listen backlog until one closes.
    #[arg(long, env = "CMR_MAX_CONNECTIONS", default_value_t = 512)]
    pub max_connections: usize,
    /// How long a client may take to send a request's headers, and how long a kept-alive
    /// connection may sit idle before its next request, seconds.
    #[arg(long, env = "CMR_HEADER_TIMEOUT_S", default_value_t = 10)]
    pub header_timeout_s: u64,
    /// On SIGINT/SIGTERM, how long in-flight requests may take to finish, seconds.
    #[arg(long, env = "CMR_SHUTDOWN_GRACE_S", default_value_t = 10)]
    pub shutdown_grace_s: u64,
    #[command(flatten)]
    pub engine: EngineArgs,
}

/// The settings of the localize path that every command running it shares (`serve`, and
/// `localize` and `track` without HTTP): models, ONNX Runtime, image and map limits, search
/// defaults. Nothing here is about HTTP or connections.
#[derive(Debug, Clone, clap::Args)]
pub struct EngineArgs {
    /// Directory with manifest.json and the four ONNX graphs.
    #[arg(long, env = "CMR_MODELS", default_value = "models")]
    pub models: PathBuf,
    /// libonnxruntime.so (default: ORT_DYLIB_PATH, then ./runtime/, then <exe>/../../runtime/).
    #[arg(long)]
    pub ort_lib: Option<PathBuf>,
    /// ONNX Runtime intra-op threads per worker session (0 = CPU cores / workers, at least 1;
    /// the command-line tools run one worker). With several `serve` workers and fewer threads
    /// than cores, one more set of sessions with every core's threads serves whichever worker is
    /// alone with work (docs/server.md).
    #[arg(long, env = "CMR_INTRA_THREADS", default_value_t = 0)]
    pub intra_threads: usize,
    /// Most hypotheses (rows of the batched policy call) one worker steps together: a request
    /// brings one per start of its search. A search larger than this still runs, alone.
    #[arg(long, env = "CMR_MAX_BATCH", default_value_t = 8)]
    pub max_batch: usize,
    /// Per-request deadline for a localization, milliseconds.
    #[arg(long, env = "CMR_REQUEST_TIMEOUT_MS", default_value_t = 10_000)]
    pub request_timeout_ms: u64,
    /// Memory budget of the prepared-map cache, MiB.
    #[arg(long, env = "CMR_CACHE_MB", default_value_t = 1024)]
    pub cache_mb: u64,
    /// Most points an uploaded map file may hold (before any `voxel_m` downsampling); more is 413.
    #[arg(long, env = "CMR_MAX_MAP_POINTS", default_value_t = 10_000_000)]
    pub max_map_points: usize,
    /// Regions with more points than this are tiled: grouped into 20 m ground cells at upload
    /// (`<id>.emb`, memory-mapped; with `--crop-embeddings stored` also each point's float16
    /// embedding), and each localize uses the points within `radius_m` of its prior. Smaller
    /// regions are sampled whole, as one scan.
    #[arg(long, env = "CMR_TILE_ABOVE_POINTS", default_value_t = 300_000)]
    pub tile_above_points: usize,
    /// Default crop radius of a localize in a tiled region, metres: the virtual scan from the
    /// prior keeps points within this ground distance (a single scan of the training rig has 90 %
    /// of its points within 20 m and reaches 80 m).
    #[arg(long, env = "CMR_DEFAULT_RADIUS_M", default_value_t = 60.0)]
    pub default_radius_m: f64,
    /// Where a tiled region's crop gets its embeddings: `encode` (the point encoder on each
    /// request's crop; the region's file then holds no embeddings) or `stored` (per-tile float16
    /// embeddings computed at upload, or when this server first reads a region stored without).
    #[arg(long, env = "CMR_CROP_EMBEDDINGS", value_enum, default_value_t = CropEmbeddings::Encode)]
    pub crop_embeddings: CropEmbeddings,
    /// Largest accepted image width or height, pixels.
    #[arg(long, env = "CMR_MAX_IMAGE_SIDE", default_value_t = 8192)]
    pub max_image_side: u32,
    /// Largest decoded image, and largest resized image before the centre crop, in pixels
    /// (16 MP: any car camera; a 64 MP image would hold 200 MB of RGB per decode).
    #[arg(long, env = "CMR_MAX_IMAGE_PIXELS", default_value_t = 16_000_000)]
    pub max_image_pixels: u64,
    /// Images decoded at once (0 = number of CPU cores); others wait, holding their queue slot.
    #[arg(long, env = "CMR_DECODE_CONCURRENCY", default_value_t = 0)]
    pub decode_concurrency: usize,
    /// Default for requests without max_iterations.
    #[arg(long, env = "CMR_DEFAULT_ITERATIONS", default_value_t = 10)]
    pub default_max_iterations: u32,
    /// Default starts of the multi-start search for requests without `hypotheses` (1 = the
    /// paper's single trajectory; more recovers priors whose heading is far off, at the cost of
    /// that many policy rows per step).
    #[arg(long, env = "CMR_DEFAULT_HYPOTHESES", default_value_t = DEFAULT_HYPOTHESES, value_parser = clap::value_parser!(u32).range(1..=crate::agent::search::MAX_HYPOTHESES as i64))]
    pub default_hypotheses: u32,
    #[command(flatten)]
    pub search: SearchTuning,
    /// An answer is `localized` when its `confidence.p_registered` is at least this (0..=1; above
    /// 1: never). Default: the model set's `calibrator.threshold` (docs/server.md, "Is the answer
    /// right?"). Without a calibrator in the manifest no answer is localized, whatever this says.
    #[arg(long, env = "CMR_LOCALIZED_THRESHOLD", value_parser = threshold)]
    pub localized_threshold: Option<f64>,
}

impl ServeArgs {
    /// Parses flags as `serve` would (environment fallbacks included); for tests and embedding.
    pub fn from_flags<I: IntoIterator<Item = S>, S: Into<std::ffi::OsString> + Clone>(flags: I) -> Result<Self, clap::Error> {
        use clap::{FromArgMatches, Args};
        let cmd = ServeArgs::augment_args(clap::Command::new("serve").no_binary_name(true));
        let matches = cmd.try_get_matches_from(flags)?;
        ServeArgs::from_arg_matches(&matches)
    }

    /// Agent workers: `--workers`, or one per CPU core.
    pub fn workers(&self) -> usize {
        if self.workers > 0 { self.workers } else { cores() }
    }

    /// Intra-op threads of each worker's sessions: `--intra-threads`, or the cores shared out.
    pub fn intra_threads(&self) -> usize {
        self.engine.intra_threads_for(self.workers())
    }

    pub fn scheduler(&self) -> SchedulerConfig {
        self.engine.scheduler(self.workers(), self.queue_capacity)
    }
}

impl EngineArgs {
    /// Intra-op threads of each of `workers` workers' sessions: `--intra-threads`, or the cores
    /// shared out (at least 1).
    pub fn intra_threads_for(&self, workers: usize) -> usize {
        if self.intra_threads > 0 { self.intra_threads } else { (cores() / workers.max(1)).max(1) }
    }

    pub fn scheduler(&self, workers: usize, queue_capacity: usize) -> SchedulerConfig {
        SchedulerConfig { workers, max_batch: self.max_batch, queue_capacity }
    }

    pub fn localizer(&self) -> LocalizerConfig {
        LocalizerConfig {
            image: ImageLimits { max_side: self.max_image_side, max_pixels: self.max_image_pixels },
            defaults: RequestDefaults {
                max_iterations: self.default_max_iterations,
                hypotheses: self.default_hypotheses,
                search: self.search,
                radius_m: self.default_radius_m,
            },
            request_timeout: std::time::Duration::from_millis(self.request_timeout_ms),
            decode_permits: if self.decode_concurrency > 0 { self.decode_concurrency } else { cores() },
            localized_threshold: self.localized_threshold,
        }
    }

    /// How regions are stored and prepared.
    pub fn regions(&self) -> RegionConfig {
        RegionConfig { tile_above_points: self.tile_above_points, max_points: self.max_map_points, crop_embeddings: self.crop_embeddings, ..RegionConfig::default() }
    }
}

/// `--localized-threshold`: a probability, or more than 1 (never localized); not negative, not NaN.
fn threshold(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(t) if t >= 0.0 && t.is_finite() => Ok(t),
        _ => Err(format!("{text:?} is not a threshold (a number from 0; above 1 means never)")),
    }
}

pub fn cores() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}
