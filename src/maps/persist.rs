//! Whole regions' `<id>.emb` files, written off the request path.
//!
//! A whole region's embeddings are a cache of what the point encoder computes from `<id>.bin`:
//! a registration answers once the cloud and its metadata are durable, and the embeddings (11 MB
//! for the shipped model's 40,960 points: about 20 ms of writing, fsync and rename on our disk)
//! reach the disk here, on one thread, in the order they were submitted. A write whose region
//! was replaced or deleted meanwhile is dropped ([`MapStore::save_embeddings`]); one lost to a
//! crash costs one encoder call when the region is next prepared: every file is fsynced before
//! its rename and names the model and the cloud it was made from, so no stale or partial file is
//! ever used. At most [`QUEUE`] writes wait; a submission beyond that waits for room.

use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use super::{MapStore, PreparedMap};

/// Writes that may wait for the writer thread (each holds its map by `Arc`: no copy).
pub const QUEUE: usize = 2;

enum Job {
    Write { id: String, map: Arc<PreparedMap>, model_sha: String, source_sha: String },
    /// Answered once every job before it is done.
    Barrier(SyncSender<()>),
}

/// The writer thread and its queue. Stopped by [`EmbeddingWriter::finish`] (or on drop), which
/// writes what is queued first.
pub struct EmbeddingWriter {
    store: Arc<MapStore>,
    queue: Mutex<Option<SyncSender<Job>>>,
    thread: Mutex<Option<JoinHandle<()>>>,
}

impl EmbeddingWriter {
    pub fn start(store: Arc<MapStore>) -> Self {
        let (tx, rx) = sync_channel(QUEUE);
        let thread_store = store.clone();
        let thread = std::thread::Builder::new()
            .name("embedding-writer".into())
            .spawn(move || run(&thread_store, rx))
            .expect("spawning the embedding writer");
        Self { store, queue: Mutex::new(Some(tx)), thread: Mutex::new(Some(thread)) }
    }

    /// Queues `map` to be written as `<id>.emb`, naming `model_sha` and `source_sha`. Blocks
    /// while [`QUEUE`] writes wait; after [`EmbeddingWriter::finish`], writes it now.
    pub fn submit(&self, id: &str, map: Arc<PreparedMap>, model_sha: &str, source_sha: &str) {
        let job = Job::Write { id: id.to_string(), map, model_sha: model_sha.to_string(), source_sha: source_sha.to_string() };
        let sender = self.queue.lock().expect("queue").clone();
        let job = match sender {
            Some(tx) => match tx.send(job) {
                Ok(()) => return,
                Err(returned) => returned.0,
            },
            None => job,
        };
        write(&self.store, job);
    }

    /// Returns once every write submitted before the call is done.
    pub fn flush(&self) {
        let sender = self.queue.lock().expect("queue").clone();
        if let Some(tx) = sender {
            let (done_tx, done_rx) = sync_channel(1);
            if tx.send(Job::Barrier(done_tx)).is_ok() {
                let _ = done_rx.recv();
            }
        }
    }

    /// Writes what is queued and stops the thread; later submissions are written by the caller.
    pub fn finish(&self) {
        drop(self.queue.lock().expect("queue").take());
        if let Some(thread) = self.thread.lock().expect("thread").take() {
            let _ = thread.join();
        }
    }
}

impl Drop for EmbeddingWriter {
    fn drop(&mut self) {
        self.finish();
    }
}

fn run(store: &MapStore, jobs: Receiver<Job>) {
    for job in jobs {
        write(store, job);
    }
}

fn write(store: &MapStore, job: Job) {
    match job {
        Job::Write { id, map, model_sha, source_sha } => match store.save_embeddings(&id, &map, &model_sha, &source_sha) {
            Ok(true) => metrics::counter!("cmr_embeddings_written_total").increment(1),
            Ok(false) => tracing::debug!(map = id, "embeddings not written: the region changed meanwhile"),
            Err(e) => tracing::warn!(map = id, "could not persist embeddings: {e}"),
        },
        Job::Barrier(done) => {
            let _ = done.send(());
        }
    }
}
