//! Map regions: point-cloud formats, the on-disk store, the embedding cache, and `Maps`, which
//! ties them to the point encoder.

pub mod build;
pub mod cache;
pub mod embeddings;
pub mod formats;
pub mod persist;
pub mod prepared;
pub mod store;
pub mod tiles;
pub mod upload;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use crate::geometry::LocalFrame;
use crate::geometry::voxel::{validate_voxel, voxel_downsample};
use crate::model::{Backend, Points};

pub use cache::MapCache;
pub use prepared::{PreparedMap, centroid, intensity_rank, prepare_map, sample_indices, sample_points};
pub use store::{Extent, MapEntry, MapMetadata, MapStore, validate_id};
pub use tiles::{SparseCrop, TileConfig, TiledMap};
pub use upload::Upload;

/// How regions are stored and prepared (from `serve`'s flags).
#[derive(Debug, Clone, Copy)]
pub struct RegionConfig {
    /// Regions with more points than this are tiled (encoded once tile by tile, cropped around
    /// the prior per request); smaller ones are sampled whole, as one scan (`--tile-above-points`).
    pub tile_above_points: usize,
    pub tiles: TileConfig,
    /// The most points an uploaded file may hold, before any voxel downsampling (`--max-map-points`).
    pub max_points: usize,
    /// Where a tiled region's crop gets its embeddings (`--crop-embeddings`).
    pub crop_embeddings: CropEmbeddings,
}

/// Where the embeddings of a tiled region's crop come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CropEmbeddings {
    /// The point encoder runs on each request's crop (one call, about 0.15 s on 2 cores): what
    /// the shipped model needs (its embeddings depend on where the input's centre is).
    #[default]
    Encode,
    /// The per-tile embeddings stored at upload (float16, memory-mapped), no encoder call.
    Stored,
}

impl Default for RegionConfig {
    /// Tiles above 300,000 points (two HDL-64E sweeps; every single scan of the rigs we know is
    /// below), 20 m cells with 40 m context, uploads up to 10 M points.
    fn default() -> Self {
        RegionConfig { tile_above_points: 300_000, tiles: TileConfig::default(), max_points: 10_000_000, crop_embeddings: CropEmbeddings::Encode }
    }
}

/// Upload options besides the bytes.
#[derive(Debug, Clone, Copy, Default)]
pub struct UploadOptions {
    /// The local frame's origin, map frame (metres); default: the cloud's box centre rounded to 1 km.
    pub origin: Option<[f64; 3]>,
    /// Voxel downsampling (one centroid per cube of this side, metres) before storing.
    pub voxel_m: Option<f64>,
}

/// A region ready for requests: a whole region's prepared sample, or a tiled region's mapped
/// embeddings.
#[derive(Clone)]
pub enum Prepared {
    Whole(Arc<PreparedMap>),
    Tiled(Arc<TiledMap>),
}

impl Prepared {
    /// Heap memory held, for the cache's byte budget (a tiled region's mapped file is not heap).
    pub fn size_bytes(&self) -> usize {
        match self {
            Prepared::Whole(m) => m.size_bytes(),
            Prepared::Tiled(t) => t.heap_bytes(),
        }
    }

    /// Cells of a tiled region (1 for a whole one).
    pub fn tiles(&self) -> usize {
        match self {
            Prepared::Whole(_) => 1,
            Prepared::Tiled(t) => t.cells(),
        }
    }

    /// Up to `max` of the region's points (local frame) for drawing, and how many points the
    /// stored cloud has: a whole region's first points of its sample (a seeded random
    /// permutation, so any prefix is a uniform subsample), a tiled region's [`TiledMap::spread`].
    pub fn drawing_sample(&self, max: usize) -> (Vec<[f32; 3]>, usize) {
        match self {
            Prepared::Whole(m) => (m.points[..m.points.len().min(max)].to_vec(), m.source_points),
            Prepared::Tiled(t) => (t.spread(max), t.points),
        }
    }

    /// What one localize uses: the whole region's sample, or the model's N points of a virtual
    /// scan from `sensor` (local frame) within `radius_m` with their stored embeddings
    /// ([`TiledMap::around`]; empty features without `stored_features`, for the caller to
    /// encode). Errors: a crop with fewer than `min_points` points.
    pub fn around(&self, sensor: [f64; 3], radius_m: f64, min_points: usize, stored_features: bool) -> Result<Arc<PreparedMap>, SparseCrop> {
        match self {
            Prepared::Whole(m) => Ok(m.clone()),
            Prepared::Tiled(t) => t.around(sensor, radius_m, min_points, stored_features).map(Arc::new),
        }
    }
}

#[derive(Debug, Clone, thiserror::Error)]
pub enum MapError {
    #[error("invalid map id {0:?}: use 1-64 characters of a-z, 0-9, '_' or '-', starting with a letter or digit")]
    InvalidId(String),
    #[error("no map named {0:?}")]
    NotFound(String),
    #[error("cannot read the point cloud: {0}")]
    BadCloud(String),
    /// The body is not a point cloud in a format we read (an image, an archive, LAZ, ...).
    #[error("{0}")]
    Unsupported(String),
    /// The cloud file (inflated, for gzip) is larger than the map byte limit.
    #[error("{0}")]
    TooLarge(String),
    #[error("invalid map metadata: {0}")]
    BadMetadata(String),
    #[error("storage error: {0}")]
    Io(String),
    #[error("point encoder failed: {0}")]
    Inference(String),
    /// An upload option out of range (origin, voxel_m).
    #[error("{0}")]
    BadOption(String),
}

/// Phase times of one registration.
#[derive(Debug, Clone, Copy, Default)]
pub struct RegisterTimings {
    pub parse_ms: f64,
    pub encode_ms: f64,
    pub store_ms: f64,
}

/// Stored regions plus their prepared embeddings.
pub struct Maps {
    pub store: Arc<MapStore>,
    pub cache: MapCache,
    pub config: RegionConfig,
    /// The point encoder used for registrations and cache misses (not the agent workers').
    encoder: Mutex<Box<dyn Backend>>,
    model_sha: String,
    /// Whether the point encoder reads intensity (`Manifest::reads_intensity`): then a tiled
    /// region's file keeps each point's intensity for its crops.
    reads_intensity: bool,
    /// The sha256 of the cloud each cached prepared map was made from. The store's files may be
    /// rewritten by another replica sharing the directory; a mismatch with the stored cloud's
    /// sha256 drops the cached copy, whoever noticed the change first.
    prepared_from: Mutex<std::collections::HashMap<String, String>>,
    /// Prepared maps read back from `<id>.emb`, and computed by the point encoder.
    pub loaded_from_disk: AtomicU64,
    pub computed: AtomicU64,
    /// Writes whole regions' `<id>.emb` after the answer ([`persist`]).
    writer: persist::EmbeddingWriter,
}

impl Maps {
    pub fn new(store: MapStore, cache: MapCache, encoder: Box<dyn Backend>, config: RegionConfig) -> Self {
        let model_sha = encoder.manifest().point_encoder_sha256().to_string();
        let reads_intensity = encoder.manifest().reads_intensity();
        let store = Arc::new(store);
        Self {
            writer: persist::EmbeddingWriter::start(store.clone()),
            store,
            cache,
            config,
            encoder: Mutex::new(encoder),
            model_sha,
            reads_intensity,
            prepared_from: Mutex::new(Default::default()),
            loaded_from_disk: AtomicU64::new(0),
            computed: AtomicU64::new(0),
        }
    }

    /// Whether a tiled region's file must hold embeddings: only when crops read them
    /// (`CropEmbeddings::Stored`); a server that encodes every crop needs the cell table and the
    /// points alone.
    fn needs_tile_embeddings(&self) -> bool {
        self.config.crop_embeddings == CropEmbeddings::Stored
    }

    /// Whether a region of `num_points` points is tiled.
    pub fn is_tiled(&self, num_points: usize) -> bool {
        num_points > self.config.tile_above_points
    }

    /// The prepared region of an entry the caller has just looked up (`MapStore::get`, so the
    /// files are checked once per request): from memory, else from `<id>.emb`, else computed
    /// (and persisted). Blocking.
    pub fn prepared_for(&self, entry: &MapEntry) -> Result<Prepared, MapError> {
        let id = entry.id.as_str();
        let from = self.prepared_from.lock().expect("prepared_from").get(id).cloned();
        if from.as_deref() != Some(entry.source_sha256.as_str()) {
            self.cache.invalidate(id);
        }
        self.cache.get_or_load(id, || self.load_or_compute(id)).map_err(|e| (*e).clone())
    }

    fn load_or_compute(&self, id: &str) -> Result<Prepared, MapError> {
        let (mut cloud, source_sha, _) = self.store.read_cloud(id)?;
        self.drop_unread_intensity(&mut cloud);
        self.prepared_from.lock().expect("prepared_from").insert(id.to_string(), source_sha.clone());
        if self.is_tiled(cloud.len()) {
            if let Some(tiled) = self.store.load_tiles(id, &self.model_sha, &source_sha, self.config.tiles, self.needs_tile_embeddings(), self.reads_intensity) {
                self.loaded_from_disk.fetch_add(1, Ordering::Relaxed);
                metrics::counter!("cmr_embeddings_loaded_total").increment(1);
                return Ok(Prepared::Tiled(Arc::new(tiled)));
            }
            let mut emb = self.store.stage_embeddings(id)?;
            self.encode_tiles(cloud.points(), &source_sha, &mut emb)?;
            emb.commit().map_err(|e| MapError::Io(e.to_string()))?;
            self.computed.fetch_add(1, Ordering::Relaxed);
            metrics::counter!("cmr_embeddings_computed_total").increment(1);
            let tiled = self.store.load_tiles(id, &self.model_sha, &source_sha, self.config.tiles, self.needs_tile_embeddings(), self.reads_intensity).ok_or_else(|| MapError::Io(format!("{id}.emb: cannot read back the tiles just written")))?;
            return Ok(Prepared::Tiled(Arc::new(tiled)));
        }
        // A registration's own file may still be queued (evicted right after it was made).
        self.writer.flush();
        if let Some(map) = self.store.load_embeddings(id, &self.model_sha, &source_sha) {
            self.loaded_from_disk.fetch_add(1, Ordering::Relaxed);
            metrics::counter!("cmr_embeddings_loaded_total").increment(1);
            return Ok(Prepared::Whole(Arc::new(map)));
        }
        let map = Arc::new(self.encode(cloud.points())?);
        self.computed.fetch_add(1, Ordering::Relaxed);
        metrics::counter!("cmr_embeddings_computed_total").increment(1);
        self.writer.submit(id, map.clone(), &self.model_sha, &source_sha);
        Ok(Prepared::Whole(map))
    }

    /// Returns once every `<id>.emb` write queued before the call is on disk.
    pub fn flush_writes(&self) {
        self.writer.flush();
    }

    /// Writes the queued `<id>.emb` files and stops the writer (at shutdown).
    pub fn finish_writes(&self) {
        self.writer.finish();
    }

    /// Runs the point encoder twice on a cloud of the model's N points, as a registration does:
    /// ONNX Runtime plans its memory for a new input shape over the first runs (on the shipped
    /// model, 2 cores: about 39, 40, then 22-26 ms), which the first uploads would pay otherwise.
    pub fn warm_up_encoder(&self) -> Result<(), MapError> {
        let mut encoder = self.encoder.lock().map_err(|_| MapError::Inference("encoder poisoned".into()))?;
        let cloud = crate::model::synthetic_cloud(encoder.manifest().points.num_points, 80.0, 3.0);
        for _ in 0..2 {
            encoder.encode_points(Points::xyz(&cloud)).map_err(|e| MapError::Inference(format!("{e:#}")))?;
        }
        Ok(())
    }

    /// A crop with its embeddings computed now, by the point encoder on the crop's own points
    /// and their intensity ([`PreparedMap::input`]; `CropEmbeddings::Encode`), instead of the
    /// stored per-tile ones.
    pub fn reencode(&self, crop: &PreparedMap) -> Result<PreparedMap, MapError> {
        let mut encoder = self.encoder.lock().map_err(|_| MapError::Inference("encoder poisoned".into()))?;
        let features = encoder.encode_points(crop.input()).map_err(|e| MapError::Inference(format!("{e:#}")))?;
        Ok(PreparedMap { features, ..crop.clone() })
    }

    /// Frees a cloud's intensity unless the point encoder reads it, before an encode that holds
    /// the whole region (a tiled one: tens of millions of points).
    fn drop_unread_intensity(&self, cloud: &mut formats::PointCloud) {
        if !self.reads_intensity {
            cloud.intensity = None;
        }
    }

    fn encode(&self, cloud: Points<'_>) -> Result<PreparedMap, MapError> {
        let mut encoder = self.encoder.lock().map_err(|_| MapError::Inference("encoder poisoned".into()))?;
        prepare_map(encoder.as_mut(), cloud).map_err(|e| MapError::Inference(format!("{e:#}")))
    }

    fn encode_tiles(&self, cloud: Points<'_>, source_sha: &str, out: &mut dyn std::io::Write) -> Result<tiles::BuildStats, MapError> {
        let mut encoder = self.encoder.lock().map_err(|_| MapError::Inference("encoder poisoned".into()))?;
        let t = Instant::now();
        let stats = tiles::build(encoder.as_mut(), cloud, self.config.tiles, self.needs_tile_embeddings(), &self.model_sha, source_sha, out).map_err(|e| MapError::Inference(format!("{e:#}")))?;
        tracing::info!(points = stats.points, cells = stats.cells, encoder_passes = stats.passes, ms = ms(t), "tiled a region");
        Ok(stats)
    }

    /// Parses (see [`upload::read_upload`]) an uploaded cloud, moves it into its local frame,
    /// downsamples it when asked, encodes and stores it, replacing any region with the same id
    /// only once everything succeeded. Blocking. Returns once the cloud and its metadata are
    /// durable; a whole region's `<id>.emb` follows on the writer thread ([`persist`]).
    /// Errors: `TooLarge` for more points than `config.max_points`, `BadOption` for an origin or
    /// voxel size out of range, and [`upload::read_upload`]'s.
    pub fn register(&self, id: &str, upload: Upload, options: UploadOptions, metadata: Option<MapMetadata>) -> Result<(MapEntry, RegisterTimings), MapError> {
        validate_id(id)?;
        if let Some(m) = &metadata {
            m.validate()?;
        }
        let t = Instant::now();
        let (mut cloud, frame) = ingest(id, upload, options, self.config.max_points)?;
        let staged = self.store.stage(id, &cloud, frame)?;
        let parse_ms = ms(t);
        let t = Instant::now();
        // A tiled region's embeddings are streamed to their file as the tiles are encoded and
        // committed with the cloud; a whole region's are written after the answer.
        self.drop_unread_intensity(&mut cloud);
        let (whole, tiles) = if self.is_tiled(cloud.len()) {
            let mut emb = self.store.stage_embeddings(id)?;
            self.encode_tiles(cloud.points(), staged.sha256(), &mut emb)?;
            (None, Some(emb))
        } else {
            (Some(Arc::new(self.encode(cloud.points())?)), None)
        };
        drop(cloud);
        let encode_ms = ms(t);
        let t = Instant::now();
        let entry = self.store.commit(id, staged, tiles, metadata)?;
        self.prepared_from.lock().expect("prepared_from").insert(id.to_string(), entry.source_sha256.clone());
        match whole {
            Some(prepared) => {
                self.cache.insert(id, Prepared::Whole(prepared.clone()));
                self.writer.submit(id, prepared, &self.model_sha, &entry.source_sha256);
            }
            None => match self.store.load_tiles(id, &self.model_sha, &entry.source_sha256, self.config.tiles, self.needs_tile_embeddings(), self.reads_intensity) {
                Some(tiled) => self.cache.insert(id, Prepared::Tiled(Arc::new(tiled))),
                None => self.cache.invalidate(id),
            },
        }
        let store_ms = ms(t);
        Ok((entry, RegisterTimings { parse_ms, encode_ms, store_ms }))
    }

    pub fn delete(&self, id: &str) -> Result<(), MapError> {
        self.store.delete(id)?;
        self.cache.invalidate(id);
        Ok(())
    }
}

/// An upload's cloud as region `id` stores it, and its local frame: parsed within `max_points`
/// ([`upload::read_upload`]; points with a non-finite coordinate dropped), moved into
/// `options.origin`'s local frame (default: the box centre rounded to 1 km,
/// [`LocalFrame::centred_on`]), voxel-downsampled when `options.voxel_m` is set. What
/// `PUT /v1/maps/{id}` and `cmr-agent map build --store` both store ([`MapStore::stage`] next).
/// Errors: `BadOption` for an origin or voxel size out of range, and [`upload::read_upload`]'s.
pub fn ingest(id: &str, upload: Upload, options: UploadOptions, max_points: usize) -> Result<(formats::PointCloud, LocalFrame), MapError> {
    let given_frame = options.origin.map(LocalFrame::new).transpose().map_err(|e| MapError::BadOption(format!("origin: {e}")))?;
    if let Some(v) = options.voxel_m {
        validate_voxel(v).map_err(MapError::BadOption)?;
    }
    let limits = formats::Limits { max_points, frame: given_frame, ..formats::Limits::default() };
    let mut parsed = upload::read_upload(upload, limits)?;
    if parsed.dropped_non_finite > 0 {
        tracing::info!(map = id, dropped = parsed.dropped_non_finite, kept = parsed.cloud.len(), "dropped points with non-finite coordinates");
    }
    let frame = given_frame.unwrap_or_else(|| LocalFrame::centred_on(parsed.min, parsed.max));
    parsed.rebase(frame);
    let mut cloud = parsed.cloud;
    if let Some(v) = options.voxel_m {
        let (xyz, intensity) = voxel_downsample(&cloud.xyz, cloud.intensity.as_deref(), v);
        tracing::info!(map = id, voxel_m = v, before = cloud.xyz.len(), after = xyz.len(), "voxel downsampling");
        cloud = formats::PointCloud { xyz, intensity };
    }
    Ok((cloud, frame))
}

fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1000.0
}
