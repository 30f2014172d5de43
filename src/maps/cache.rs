//! Prepared maps in memory, bounded by bytes with least-recently-used eviction (moka).

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use moka::notification::RemovalCause;
use moka::sync::Cache;

use super::Prepared;

pub struct MapCache {
    inner: Cache<String, Prepared>,
    budget_bytes: u64,
    /// This cache's own counters (the Prometheus ones are process-wide).
    pub evictions: Arc<AtomicU64>,
}

impl MapCache {
    pub fn new(budget_bytes: u64) -> Self {
        let evictions = Arc::new(AtomicU64::new(0));
        let counter = evictions.clone();
        // The weigher counts KiB so a single large map fits moka's u32 weights.
        let inner = Cache::builder()
            .max_capacity((budget_bytes / 1024).max(1))
            // Plain LRU: a freshly uploaded map is always admitted (TinyLFU could refuse it).
            .eviction_policy(moka::policy::EvictionPolicy::lru())
            .weigher(|_id: &String, map: &Prepared| (map.size_bytes() / 1024).clamp(1, u32::MAX as usize) as u32)
            .eviction_listener(move |_id, _map, cause| {
                if matches!(cause, RemovalCause::Size | RemovalCause::Expired) {
                    counter.fetch_add(1, Ordering::Relaxed);
                    metrics::counter!("cmr_cache_evictions_total").increment(1);
                }
            })
            .build();
        Self { inner, budget_bytes, evictions }
    }

    pub fn get(&self, id: &str) -> Option<Prepared> {
        let hit = self.inner.get(id);
        metrics::counter!(if hit.is_some() { "cmr_cache_hits_total" } else { "cmr_cache_misses_total" }).increment(1);
        hit
    }

    /// Returns the cached map or loads it once, even when many requests miss at the same time.
    pub fn get_or_load<E: Send + Sync + 'static>(
        &self,
        id: &str,
        load: impl FnOnce() -> Result<Prepared, E>,
    ) -> Result<Prepared, Arc<E>> {
        if let Some(hit) = self.get(id) {
            return Ok(hit);
        }
        let result = self.inner.try_get_with(id.to_string(), load);
        self.publish();
        result
    }

    pub fn insert(&self, id: &str, map: Prepared) {
        self.inner.insert(id.to_string(), map);
        self.publish();
    }

    pub fn invalidate(&self, id: &str) {
        self.inner.invalidate(id);
        self.publish();
    }

    /// The cached region, if any, without counting a hit or a miss (for reports).
    pub fn peek(&self, id: &str) -> Option<Prepared> {
        self.inner.get(id)
    }

    pub fn contains(&self, id: &str) -> bool {
        self.inner.contains_key(id)
    }

    /// Bytes held (approximate: KiB granularity).
    pub fn weighted_bytes(&self) -> u64 {
        self.inner.run_pending_tasks();
        self.inner.weighted_size() * 1024
    }

    pub fn budget_bytes(&self) -> u64 {
        self.budget_bytes
    }

    fn publish(&self) {
        metrics::gauge!("cmr_cache_bytes").set(self.weighted_bytes() as f64);
        metrics::gauge!("cmr_cache_entries").set(self.inner.entry_count() as f64);
    }
}
