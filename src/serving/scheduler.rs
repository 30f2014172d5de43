//! A pool of agent workers behind one bounded queue, with iteration-level batching.
//!
//! Each worker owns one [`Backend`] and one [`Batch`]. Between two policy steps it admits
//! waiting requests into the batch (running their image encoder and frustum head), makes ONE
//! batched policy call for every running hypothesis of every request it holds, and answers the
//! requests that are done. So requests join and leave the running batch at step boundaries, the
//! way LLM routers batch decode steps, and a short request never waits for a long one.
//!
//! Capacity is reserved before a request does any work ([`Scheduler::reserve`]): a [`Slot`] counts
//! against `queue_capacity` from admission until a worker takes the job, so a request refused with
//! 429 has cost nothing, and decoding requests count as waiting ones.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tokio::sync::oneshot;

use crate::agent::{Batch, Localization, Start, StepError, ms};
use crate::model::{Backend, BackendFactory};

/// One localize request, ready for inference.
pub struct Job {
    pub start: Start,
    pub deadline: Instant,
    /// The request's span: the worker's work for this job is recorded inside it.
    pub span: tracing::Span,
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
    #[error(transparent)]
    Step(#[from] StepError),
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
    /// Requests admitted but not yet taken by a worker (decoding or queued) before new ones are
    /// refused.
    pub queue_capacity: usize,
}

struct Queued {
    job: Job,
    enqueued: Instant,
    _slot: Slot,
}

struct Queue {
    jobs: Mutex<VecDeque<Queued>>,
    ready: Condvar,
    capacity: usize,
    /// Slots held: requests between `reserve` and a worker taking them.
    reserved: AtomicUsize,
    closed: AtomicBool,
    /// Requests in some worker's running batch.
    active: AtomicUsize,
    /// Batched policy calls made, and the hypotheses they stepped (mean batch = ratio).
    steps: AtomicUsize,
    stepped_rows: AtomicUsize,
    largest_batch: AtomicUsize,
}

/// A reserved place in the queue; released when dropped (the request failed before it was
/// queued) or when a worker takes the queued job.
pub struct Slot {
    queue: Arc<Queue>,
}

impl Drop for Slot {
    fn drop(&mut self) {
        self.queue.reserved.fetch_sub(1, Ordering::SeqCst);
    }
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
    /// Starts `config.workers` threads, each with its own backend from `factory` (warmed up).
    /// Fails if any backend fails.
    pub fn start(factory: &BackendFactory, config: SchedulerConfig) -> anyhow::Result<Self> {
        let queue = Arc::new(Queue {
            jobs: Mutex::new(VecDeque::new()),
            ready: Condvar::new(),
            capacity: config.queue_capacity.max(1),
            reserved: AtomicUsize::new(0),
            closed: AtomicBool::new(false),
            active: AtomicUsize::new(0),
            steps: AtomicUsize::new(0),
            stepped_rows: AtomicUsize::new(0),
            largest_batch: AtomicUsize::new(0),
        });
        let mut workers = Vec::new();
        for index in 0..config.workers.max(1) {
            let mut backend = factory()?;
            backend.warm_up()?;
            let worker = Worker { batch: Batch::new(backend.manifest()), backend, queue: queue.clone(), max_batch: config.max_batch.max(1) };
            workers.push(std::thread::Builder::new().name(format!("agent-worker-{index}")).spawn(move || worker.run())?);
        }
        Ok(Self { queue, workers: Mutex::new(workers) })
    }

    /// Reserves a place for one request, or refuses at once when the queue is full or closed.
    /// Call it before any work on the request (body, decode).
    pub fn reserve(&self) -> Result<Slot, SubmitError> {
        if self.queue.closed.load(Ordering::SeqCst) {
            return Err(SubmitError::Draining);
        }
        let capacity = self.queue.capacity;
        self.queue
            .reserved
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| (n < capacity).then_some(n + 1))
            .map_err(|_| {
                metrics::counter!("cmr_queue_rejections_total").increment(1);
                SubmitError::QueueFull
            })?;
        Ok(Slot { queue: self.queue.clone() })
    }

    /// Queues a job in its reserved slot.
    pub fn submit(&self, job: Job, slot: Slot) -> Result<(), SubmitError> {
        if self.queue.closed.load(Ordering::SeqCst) {
            return Err(SubmitError::Draining);
        }
        let mut jobs = self.queue.jobs.lock().expect("queue lock");
        jobs.push_back(Queued { job, enqueued: Instant::now(), _slot: slot });
        metrics::gauge!("cmr_queue_depth").set(jobs.len() as f64);
        drop(jobs);
        self.queue.ready.notify_one();
        Ok(())
    }

    /// Requests admitted and not yet taken by a worker (decoding or queued).
    pub fn queue_depth(&self) -> usize {
        self.queue.reserved.load(Ordering::SeqCst)
    }

    /// Requests in the workers' running batches.
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
        let deadline = Instant::now() + timeout;
        let handles: Vec<JoinHandle<()>> = std::mem::take(&mut *self.workers.lock().expect("workers lock"));
        for h in handles {
            while !h.is_finished() && Instant::now() < deadline {
                std::thread::sleep(Duration::from_millis(5));
            }
            if !h.is_finished() {
                return false;
            }
            let _ = h.join();
        }
        true
    }
}

impl Drop for Scheduler {
    fn drop(&mut self) {
        self.close();
    }
}

/// What the batch carries for each request besides its search.
struct Tag {
    reply: oneshot::Sender<Result<Finished, JobError>>,
    deadline: Instant,
    span: tracing::Span,
    queue_ms: f64,
}

struct Worker {
    backend: Box<dyn Backend>,
    batch: Batch<Tag>,
    queue: Arc<Queue>,
    max_batch: usize,
}

impl Worker {
    fn run(mut self) {
        loop {
            let room = self.max_batch.saturating_sub(self.batch.rows());
            let Some(taken) = self.take_jobs(self.batch.is_empty(), room) else {
                return; // closed, nothing queued, nothing running
            };
            for queued in taken {
                self.admit(queued);
            }
            if self.batch.is_empty() {
                continue;
            }
            // A bug in one step must not take the worker (and every later request) down: the
            // requests in the batch get an error and the worker goes on.
            let stepped = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.batch.step(self.backend.as_mut())));
            match stepped {
                Ok(rows) if rows > 0 => {
                    metrics::histogram!("cmr_batch_size").record(rows as f64);
                    self.queue.steps.fetch_add(1, Ordering::SeqCst);
                    self.queue.stepped_rows.fetch_add(rows, Ordering::SeqCst);
                    self.queue.largest_batch.fetch_max(rows, Ordering::SeqCst);
                }
                Ok(_) => {}
                Err(_) => {
                    tracing::error!("agent step panicked; failing the {} requests in the batch", self.batch.len());
                    self.batch.fail_all(StepError::Inference("internal error in the agent step".into()));
                }
            }
            self.retire();
        }
    }

    /// Takes queued jobs, in order, while their hypotheses fit in `room` rows (an empty batch
    /// takes the first job whatever its size); blocks for one when `wait` (the batch is empty).
    /// `None` means: shut down.
    fn take_jobs(&self, wait: bool, mut room: usize) -> Option<Vec<Queued>> {
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
        while let Some(q) = jobs.front() {
            let rows = q.job.start.search.hypotheses;
            if rows > room && !(wait && taken.is_empty()) {
                break;
            }
            room = room.saturating_sub(rows);
            taken.extend(jobs.pop_front());
        }
        metrics::gauge!("cmr_queue_depth").set(jobs.len() as f64);
        Some(taken)
    }

    /// Runs the per-request models (image encoder, frustum head) so the request joins the batch.
    fn admit(&mut self, queued: Queued) {
        let Queued { job, enqueued, _slot } = queued;
        drop(_slot);
        let queue_ms = ms(enqueued);
        metrics::histogram!("cmr_phase_seconds", "phase" => "queue").record(queue_ms / 1000.0);
        if job.reply.is_closed() {
            return; // the client went away while queued
        }
        if Instant::now() >= job.deadline {
            let _ = job.reply.send(Err(JobError::DeadlineExceeded));
            return;
        }
        let span = job.span.clone();
        let _entered = span.enter();
        let tag = Tag { reply: job.reply, deadline: job.deadline, span: job.span.clone(), queue_ms };
        let backend = self.backend.as_mut();
        let batch = &mut self.batch;
        // On a panic the job is dropped, so its client gets an internal error at once.
        let admitted = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| batch.admit(backend, job.start, tag)));
        match admitted {
            Ok(Ok(())) => {
                self.queue.active.fetch_add(1, Ordering::SeqCst);
                tracing::debug!(queue_ms, "admitted into the running batch");
            }
            Ok(Err((tag, e))) => {
                let _ = tag.reply.send(Err(e.into()));
            }
            Err(_) => tracing::error!("admitting a request panicked"),
        }
    }

    /// Answers and removes every request that is done, failed, expired or abandoned.
    fn retire(&mut self) {
        for (tag, result) in self.batch.retire() {
            self.queue.active.fetch_sub(1, Ordering::SeqCst);
            let _entered = tag.span.enter();
            let result = result.map(|localization| {
                let t = localization.timings;
                metrics::histogram!("cmr_phase_seconds", "phase" => "image_encoder").record(t.image_encoder_ms / 1000.0);
                metrics::histogram!("cmr_phase_seconds", "phase" => "frustum_head").record(t.frustum_head_ms / 1000.0);
                metrics::histogram!("cmr_phase_seconds", "phase" => "agent_steps").record(t.agent_steps_ms / 1000.0);
                tracing::debug!(agent_steps_ms = t.agent_steps_ms, "localization finished");
                Finished { localization, queue_ms: tag.queue_ms }
            });
            if let Err(e) = &result {
                tracing::warn!("request failed in the step loop: {e}");
            }
            let _ = tag.reply.send(result.map_err(JobError::from));
        }
        let now = Instant::now();
        for tag in self.batch.cancel(|t| t.reply.is_closed() || now >= t.deadline) {
            self.queue.active.fetch_sub(1, Ordering::SeqCst);
            let _ = tag.reply.send(Err(JobError::DeadlineExceeded));
        }
    }
}
