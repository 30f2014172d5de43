//! Map regions: point-cloud formats, the on-disk store, the embedding cache, and `Maps`, which
//! ties them to the point encoder.

pub mod cache;
pub mod embeddings;
pub mod formats;
pub mod prepared;
pub mod store;
pub mod upload;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use crate::model::Backend;

pub use cache::MapCache;
pub use prepared::{PreparedMap, centroid, prepare_map, sample_points};
pub use store::{MapEntry, MapMetadata, MapStore, validate_id};
pub use upload::Upload;

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
    pub store: MapStore,
    pub cache: MapCache,
    /// The point encoder used for registrations and cache misses (not the agent workers').
    encoder: Mutex<Box<dyn Backend>>,
    model_sha: String,
    /// The sha256 of the cloud each cached prepared map was made from. The store's files may be
    /// rewritten by another replica sharing the directory; a mismatch with the stored cloud's
    /// sha256 drops the cached copy, whoever noticed the change first.
    prepared_from: Mutex<std::collections::HashMap<String, String>>,
    /// Prepared maps read back from `<id>.emb`, and computed by the point encoder.
    pub loaded_from_disk: AtomicU64,
    pub computed: AtomicU64,
}

impl Maps {
    pub fn new(store: MapStore, cache: MapCache, encoder: Box<dyn Backend>) -> Self {
        let model_sha = encoder.manifest().point_encoder_sha256().to_string();
        Self {
            store,
            cache,
            encoder: Mutex::new(encoder),
            model_sha,
            prepared_from: Mutex::new(Default::default()),
            loaded_from_disk: AtomicU64::new(0),
            computed: AtomicU64::new(0),
        }
    }

    /// The prepared map of an entry the caller has just looked up (`MapStore::get`, so the files
    /// are checked once per request): from memory, else from `<id>.emb`, else computed (and
    /// persisted). Blocking.
    pub fn prepared_for(&self, entry: &MapEntry) -> Result<Arc<PreparedMap>, MapError> {
        let id = entry.id.as_str();
        let from = self.prepared_from.lock().expect("prepared_from").get(id).cloned();
        if from.as_deref() != Some(entry.source_sha256.as_str()) {
            self.cache.invalidate(id);
        }
        self.cache
            .get_or_load(id, || self.load_or_compute(id).map(Arc::new))
            .map_err(|e| (*e).clone())
    }

    fn load_or_compute(&self, id: &str) -> Result<PreparedMap, MapError> {
        let (cloud, source_sha, _) = self.store.read_cloud(id)?;
        self.prepared_from.lock().expect("prepared_from").insert(id.to_string(), source_sha.clone());
        if let Some(map) = self.store.load_embeddings(id, &self.model_sha, &source_sha) {
            self.loaded_from_disk.fetch_add(1, Ordering::Relaxed);
            metrics::counter!("cmr_embeddings_loaded_total").increment(1);
            return Ok(map);
        }
        let map = self.encode(&cloud)?;
        self.computed.fetch_add(1, Ordering::Relaxed);
        metrics::counter!("cmr_embeddings_computed_total").increment(1);
        if let Err(e) = self.store.save_embeddings(id, &map, &self.model_sha, &source_sha) {
            tracing::warn!("could not persist embeddings of {id:?}: {e}");
        }
        Ok(map)
    }

    fn encode(&self, cloud: &[[f32; 3]]) -> Result<PreparedMap, MapError> {
        let mut encoder = self.encoder.lock().map_err(|_| MapError::Inference("encoder poisoned".into()))?;
        prepare_map(encoder.as_mut(), cloud).map_err(|e| MapError::Inference(format!("{e:#}")))
    }

    /// Parses (see [`upload::read_upload`]), encodes and stores an uploaded cloud, replacing any
    /// region with the same id only once everything succeeded. Blocking.
    pub fn register(&self, id: &str, upload: Upload, metadata: Option<MapMetadata>) -> Result<(MapEntry, RegisterTimings), MapError> {
        validate_id(id)?;
        if let Some(m) = &metadata {
            m.validate()?;
        }
        let t = Instant::now();
        let parsed = upload::read_upload(upload, formats::Limits::default())?;
        if parsed.dropped_non_finite > 0 {
            tracing::info!(map = id, dropped = parsed.dropped_non_finite, kept = parsed.cloud.len(), "dropped points with non-finite coordinates");
        }
        let cloud = parsed.cloud;
        let parse_ms = ms(t);
        let t = Instant::now();
        let prepared = self.encode(&cloud.xyz)?;
        let encode_ms = ms(t);
        let t = Instant::now();
        let entry = self.store.put(id, &cloud, metadata, &prepared, &self.model_sha)?;
        self.prepared_from.lock().expect("prepared_from").insert(id.to_string(), entry.source_sha256.clone());
        self.cache.insert(id, Arc::new(prepared));
        let store_ms = ms(t);
        Ok((entry, RegisterTimings { parse_ms, encode_ms, store_ms }))
    }

    pub fn delete(&self, id: &str) -> Result<(), MapError> {
        self.store.delete(id)?;
        self.cache.invalidate(id);
        Ok(())
    }
}

fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1000.0
}
