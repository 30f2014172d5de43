//! The serving path: a pool of agent workers behind one bounded queue, with iteration-level
//! batching.
//!
//! Each worker owns one set of ONNX Runtime sessions. Between two policy steps it admits waiting
//! requests (running their image encoder and frustum head), then makes ONE batched `agent` call
//! for every running hypothesis of every request it holds, applies the actions, and answers the
//! requests that are done. So requests join and leave the running batch at step boundaries, the
//! way LLM routers batch decode steps, and a short request never waits for a long one to finish.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tokio::sync::oneshot;

use crate::geometry::{Intrinsics, Pose};
use crate::model::{Backend, ModelSet};

use super::search::Search;
use super::state::{ScatterScratch, StateLayout};
use super::{Localization, PreparedMap, SearchConfig, Timings, ms, start_search};

/// One localize request, ready for inference.
pub struct Job {
    pub map: Arc<PreparedMap>,
    pub image_tensor: Vec<f32>,
    pub intrinsics: Intrinsics,
    pub prior: Pose,
    pub search: SearchConfig,
    pub deadline: Instant,
    pub reply: oneshot::Sender<Result<Finished, JobError>>,
}

/// A finished localization and how long it waited for a worker.
pub struct Finished {
    pub localization: Localization,
    pub queue_ms: f64,
}

#[derive(Debug, Clone, thiserror::Error)]
pub enum JobError {
    #[error("the request's deadline passed before the agent finished")]
    DeadlineExceeded,
    #[error("inference failed: {0}")]
    Inference(String),
}

#[derive(Debug, Clone, thiserror::Error)]
pub enum SubmitError {
    #[error("the localization queue is full; retry later")]
    QueueFull,
    #[error("the server is shutting down")]
    Draining,
}

#[derive(Debug, Clone)]
pub struct SchedulerConfig {
    pub workers: usize,
    /// Most hypotheses (rows of the policy call) a worker steps at once; a request whose search
    /// alone is larger still runs, by itself.
    pub max_batch: usize,
    pub queue_capacity: usize,
}

struct Queue {
    jobs: Mutex<VecDeque<(Job, Instant)>>,
    ready: Condvar,
    capacity: usize,
    closed: AtomicBool,
    /// Requests admitted into some worker's running batch.
    active: AtomicUsize,
    /// Batched policy calls made, and the hypotheses they stepped (mean batch = ratio).
    steps: AtomicUsize,
    stepped_rows: AtomicUsize,
    largest_batch: AtomicUsize,
}

/// Counters of the batching behaviour since start.
#[derive(Debug, Clone, Copy)]
pub struct BatchStats {
    pub policy_calls: usize,
    /// Hypotheses stepped, summed over calls (one request contributes one per running start).
    pub stepped_rows: usize,
    pub largest_batch: usize,
}

/// Handle to the worker pool; cheap to share.
pub struct Scheduler {
    queue: Arc<Queue>,
    workers: Mutex<Vec<JoinHandle<()>>>,
}

impl Scheduler {
    /// Starts `config.workers` threads, each with its own backend. Fails if any backend fails.
    pub fn start(models: &ModelSet, config: SchedulerConfig) -> anyhow::Result<Self> {
        let queue = Arc::new(Queue {
            jobs: Mutex::new(VecDeque::new()),
            ready: Condvar::new(),
            capacity: config.queue_capacity.max(1),
            closed: AtomicBool::new(false),
            active: AtomicUsize::new(0),
            steps: AtomicUsize::new(0),
            stepped_rows: AtomicUsize::new(0),
            largest_batch: AtomicUsize::new(0),
        });
        let mut workers = Vec::new();
        for index in 0..config.workers.max(1) {
            let mut backend = models.backend()?;
            backend.warm_up()?;
            let queue = queue.clone();
            let max_batch = config.max_batch.max(1);
            let handle = std::thread::Builder::new()
                .name(format!("agent-worker-{index}"))
                .spawn(move || Worker::new(backend, queue, max_batch).run())?;
            workers.push(handle);
        }
        Ok(Self { queue, workers: Mutex::new(workers) })
    }

    /// Queues a job, or refuses at once when the queue is full or closed.
    pub fn submit(&self, job: Job) -> Result<(), SubmitError> {
        if self.queue.closed.load(Ordering::SeqCst) {
            return Err(SubmitError::Draining);
        }
        let mut jobs = self.queue.jobs.lock().expect("queue lock");
        if jobs.len() >= self.queue.capacity {
            metrics::counter!("cmr_queue_rejections_total").increment(1);
            return Err(SubmitError::QueueFull);
        }
        jobs.push_back((job, Instant::now()));
        metrics::gauge!("cmr_queue_depth").set(jobs.len() as f64);
        drop(jobs);
        self.queue.ready.notify_one();
        Ok(())
    }

    pub fn queue_depth(&self) -> usize {
        self.queue.jobs.lock().map(|j| j.len()).unwrap_or(0)
    }

    pub fn active(&self) -> usize {
        self.queue.active.load(Ordering::SeqCst)
    }

    pub fn batch_stats(&self) -> BatchStats {
        BatchStats {
            policy_calls: self.queue.steps.load(Ordering::SeqCst),
            stepped_rows: self.queue.stepped_rows.load(Ordering::SeqCst),
            largest_batch: self.queue.largest_batch.load(Ordering::SeqCst),
        }
    }

    /// Stops accepting jobs; workers finish what is queued and running, then exit.
    pub fn close(&self) {
        self.queue.closed.store(true, Ordering::SeqCst);
        self.queue.ready.notify_all();
    }

    /// Closes and waits for the workers, at most `timeout`. Returns whether they all exited.
    pub fn shutdown(&self, timeout: Duration) -> bool {
        self.close();
        let start = Instant::now();
        let handles: Vec<JoinHandle<()>> = std::mem::take(&mut *self.workers.lock().expect("workers lock"));
        for h in handles {
            while !h.is_finished() && start.elapsed() < timeout {
                std::thread::sleep(Duration::from_millis(5));
            }
            if h.is_finished() {
                let _ = h.join();
            } else {
                return false;
            }
        }
        true
    }
}

impl Drop for Scheduler {
    fn drop(&mut self) {
        self.close();
    }
}

/// A request in a worker's running batch.
struct Active {
    job: Job,
    search: Search,
    timings: Timings,
    queue_ms: f64,
    steps_started: Instant,
    /// Set when a batched policy call failed: the request is answered with this error.
    failed: Option<String>,
}

struct Worker {
    backend: Backend,
    queue: Arc<Queue>,
    max_batch: usize,
    layout: StateLayout,
    actions: crate::geometry::ActionSet,
    scratch: ScatterScratch,
    state_2d: Vec<f32>,
    state_3d: Vec<f32>,
}

impl Worker {
    fn new(backend: Backend, queue: Arc<Queue>, max_batch: usize) -> Self {
        let layout = StateLayout::from_manifest(backend.manifest());
        let actions = backend.manifest().action_set();
        Self { backend, queue, max_batch, layout, actions, scratch: Default::default(), state_2d: vec![], state_3d: vec![] }
    }

    fn run(mut self) {
        let mut batch: Vec<Active> = Vec::new();
        loop {
            let rows: usize = batch.iter().map(|a| a.search.running().count()).sum();
            let Some(admitted) = self.take_jobs(batch.is_empty(), self.max_batch.saturating_sub(rows)) else {
                return; // closed, nothing queued, nothing running
            };
            for (job, enqueued) in admitted {
                // On a panic the job is dropped, so its client gets an internal error at once.
                let admitted = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.admit(job, enqueued)));
                if let Ok(Some(active)) = admitted {
                    self.queue.active.fetch_add(1, Ordering::SeqCst);
                    batch.push(active);
                }
            }
            if batch.is_empty() {
                continue;
            }
            // A bug in one step must not take the worker (and every later request) down: the
            // requests in the batch get an error and the worker goes on.
            let stepped = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.step(&mut batch)));
            if stepped.is_err() {
                tracing::error!("agent step panicked; failing the {} requests in the batch", batch.len());
                for a in batch.iter_mut() {
                    a.failed = Some("internal error in the agent step".into());
                }
            }
            self.retire(&mut batch);
        }
    }

    /// Takes queued jobs, in order, while their hypotheses fit in `room` rows (an empty batch
    /// takes the first job whatever its size); blocks for one when `wait` (the batch is empty).
    /// `None` means: shut down.
    fn take_jobs(&self, wait: bool, mut room: usize) -> Option<Vec<(Job, Instant)>> {
        let mut jobs = self.queue.jobs.lock().expect("queue lock");
        if wait {
            while jobs.is_empty() {
                if self.queue.closed.load(Ordering::SeqCst) {
                    return None;
                }
                jobs = self.queue.ready.wait_timeout(jobs, Duration::from_millis(200)).expect("queue lock").0;
            }
        }
        let mut taken = Vec::new();
        while let Some((job, _)) = jobs.front() {
            let rows = job.search.hypotheses;
            if rows > room && !(wait && taken.is_empty()) {
                break;
            }
            room = room.saturating_sub(rows);
            taken.extend(jobs.pop_front());
        }
        metrics::gauge!("cmr_queue_depth").set(jobs.len() as f64);
        Some(taken)
    }

    /// Runs the per-request models (image encoder, frustum head) so the request can join the batch.
    fn admit(&mut self, job: Job, enqueued: Instant) -> Option<Active> {
        let queue_ms = ms(enqueued);
        metrics::histogram!("cmr_phase_seconds", "phase" => "queue").record(queue_ms / 1000.0);
        if job.reply.is_closed() {
            return None; // the client went away while queued
        }
        if Instant::now() >= job.deadline {
            let _ = job.reply.send(Err(JobError::DeadlineExceeded));
            return None;
        }
        match start_search(&mut self.backend, &job.map, &job.image_tensor, job.intrinsics, job.prior, job.search) {
            Ok((search, timings)) => {
                metrics::histogram!("cmr_phase_seconds", "phase" => "image_encoder").record(timings.image_encoder_ms / 1000.0);
                metrics::histogram!("cmr_phase_seconds", "phase" => "frustum_head").record(timings.frustum_head_ms / 1000.0);
                Some(Active { job, search, timings, queue_ms, steps_started: Instant::now(), failed: None })
            }
            Err(e) => {
                let _ = job.reply.send(Err(JobError::Inference(format!("{e:#}"))));
                None
            }
        }
    }

    /// One batched policy call for every hypothesis in the batch that still has steps to take.
    fn step(&mut self, batch: &mut [Active]) {
        let running: Vec<(usize, usize)> =
            batch.iter().enumerate().flat_map(|(i, a)| a.search.running().map(move |h| (i, h))).collect();
        if running.is_empty() {
            return;
        }
        let b = running.len();
        let (l2, l3) = (self.layout.state_2d_len(), self.layout.state_3d_len());
        self.state_2d.resize(b * l2, 0.0);
        self.state_3d.resize(b * l3, 0.0);
        for (slot, &(i, h)) in running.iter().enumerate() {
            let ts = Instant::now();
            let a = &mut batch[i];
            a.search.episodes[h].write_state(
                &a.job.map,
                &self.layout,
                &mut self.scratch,
                &mut self.state_2d[slot * l2..(slot + 1) * l2],
                &mut self.state_3d[slot * l3..(slot + 1) * l3],
            );
            a.timings.state_build_ms += ms(ts);
        }
        metrics::histogram!("cmr_batch_size").record(b as f64);
        self.queue.steps.fetch_add(1, Ordering::SeqCst);
        self.queue.stepped_rows.fetch_add(b, Ordering::SeqCst);
        self.queue.largest_batch.fetch_max(b, Ordering::SeqCst);
        match self.backend.agent_step(&self.state_2d, &self.state_3d, b) {
            Ok(out) => {
                let per = 3 * self.actions.num_actions();
                for (slot, &(i, h)) in running.iter().enumerate() {
                    let a = &mut batch[i];
                    a.search.episodes[h].advance(&a.job.map, &self.actions, &out.policy_logits[slot * per..(slot + 1) * per], out.value[slot]);
                }
                for a in batch.iter_mut() {
                    a.search.after_step(&a.job.map, &self.layout, &mut self.scratch);
                }
            }
            Err(e) => {
                let message = format!("{e:#}");
                tracing::error!("agent step failed: {message}");
                for &(i, _) in &running {
                    batch[i].failed = Some(message.clone());
                }
            }
        }
    }

    /// Answers and removes every request that is done, expired or abandoned.
    fn retire(&mut self, batch: &mut Vec<Active>) {
        let now = Instant::now();
        let mut i = 0;
        while i < batch.len() {
            let a = &batch[i];
            let expired = now >= a.job.deadline && !a.search.is_done();
            if !(a.search.is_done() || expired || a.failed.is_some() || a.job.reply.is_closed()) {
                i += 1;
                continue;
            }
            let mut a = batch.swap_remove(i);
            self.queue.active.fetch_sub(1, Ordering::SeqCst);
            let result = if let Some(message) = a.failed.take() {
                Err(JobError::Inference(message))
            } else if expired {
                Err(JobError::DeadlineExceeded)
            } else {
                a.timings.agent_steps_ms = ms(a.steps_started);
                metrics::histogram!("cmr_phase_seconds", "phase" => "agent_steps").record(a.timings.agent_steps_ms / 1000.0);
                let localization = a.search.finish(&a.job.map, &self.layout, &mut self.scratch, a.timings);
                Ok(Finished { localization, queue_ms: a.queue_ms })
            };
            let _ = a.job.reply.send(result);
        }
    }
}
