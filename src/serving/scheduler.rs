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
    /// One message per worker that has exited (sent on drop, so a panic counts too).
    exited: Mutex<std::sync::mpsc::Receiver<()>>,
}

/// Tells the scheduler a worker thread has ended, however it ended.
struct ExitSignal(std::sync::mpsc::Sender<()>);

impl Drop for ExitSignal {
    fn drop(&mut self) {
        let _ = self.0.send(());
    }
}

impl Scheduler {
    /// Starts `config.workers` threads, each with its own backend from `factory` (warmed up).
    /// Fails if any backend fails.
    pub fn start(factory: &BackendFactory, config: SchedulerConfig) -> anyhow::Result<Self> {
        Self::start_with_lone(factory, None, config)
    }

    /// [`Scheduler::start`], plus one backend from `lone` (sessions with every core's threads)
    /// that a worker uses while it is the only one with work: no request in another worker's
    /// batch and none decoding or queued. A lone request then has the idle cores for its ONNX
    /// Runtime calls; under load every worker runs its own one-thread sessions side by side,
    /// the faster way to share the cores (docs/server.md, "Workers x threads"). One set serves
    /// all workers, since only one can be alone at a time (a worker that finds it taken uses
    /// its own).
    pub fn start_with_lone(factory: &BackendFactory, lone: Option<&BackendFactory>, config: SchedulerConfig) -> anyhow::Result<Self> {
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
        let lone = match lone {
            Some(make) => {
                let mut backend = make()?;
                backend.warm_up()?;
                Some(Arc::new(Mutex::new(backend)))
            }
            None => None,
        };
        let mut workers = Vec::new();
        let (exit_tx, exited) = std::sync::mpsc::channel();
        for index in 0..config.workers.max(1) {
            let mut backend = factory()?;
            backend.warm_up()?;
            let worker = Worker { batch: Batch::new(backend.manifest()), backend, lone: lone.clone(), queue: queue.clone(), max_batch: config.max_batch.max(1) };
            let signal = ExitSignal(exit_tx.clone());
            workers.push(std::thread::Builder::new().name(format!("agent-worker-{index}")).spawn(move || {
                let _signal = signal;
                worker.run()
            })?);
        }
        Ok(Self { queue, workers: Mutex::new(workers), exited: Mutex::new(exited) })
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

    /// Closes and waits for the workers' exit signals, at most `timeout`. Returns whether they
    /// all exited.
    pub fn shutdown(&self, timeout: Duration) -> bool {
        self.close();
        let deadline = Instant::now() + timeout;
        let handles: Vec<JoinHandle<()>> = std::mem::take(&mut *self.workers.lock().expect("workers lock"));
        let exited = self.exited.lock().expect("exit channel");
        for _ in 0..handles.len() {
            if exited.recv_timeout(deadline.saturating_duration_since(Instant::now())).is_err() {
                return false;
            }
        }
        for h in handles {
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
    /// Sessions with every core's threads, shared by the workers, for whichever is alone with work.
    lone: Option<Arc<Mutex<Box<dyn Backend>>>>,
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
            let stepped = self.with_backend(|batch, backend| std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| batch.step(backend))));
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

    /// Runs `f` (one model call's worth of work on the batch) with the lone backend while no
    /// other request is in another worker's batch, decoding or queued (read just before the
    /// call: a request that arrives during it runs beside it for that one call), else with
    /// this worker's own. `f` must not unwind (callers catch panics inside it).
    fn with_backend<R>(&mut self, f: impl FnOnce(&mut Batch<Tag>, &mut dyn Backend) -> R) -> R {
        let alone = self.queue.active.load(Ordering::SeqCst) <= self.batch.len() && self.queue.reserved.load(Ordering::SeqCst) == 0;
        let Worker { backend, lone, batch, .. } = self;
        match lone.as_ref().filter(|_| alone).and_then(|lone| lone.try_lock().ok()) {
            Some(mut shared) => f(batch, shared.as_mut()),
            None => f(batch, backend.as_mut()),
        }
    }

    /// Takes queued jobs, in order, while their peak rows (`SearchConfig::peak_rows`) fit in `room` rows (an empty batch
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
            let rows = q.job.start.search.peak_rows();
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
        // On a panic the job is dropped, so its client gets an internal error at once.
        let admitted = self.with_backend(|batch, backend| std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| batch.admit(backend, job.start, tag))));
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
        // Finishing may encode a search's judge's views (`Search::finish`).
        let retired = self.with_backend(|batch, backend| batch.retire(backend));
        for (tag, result) in retired {
            self.queue.active.fetch_sub(1, Ordering::SeqCst);
            let _entered = tag.span.enter();
            let result = result.map(|localization| {
                let t = localization.timings;
                metrics::histogram!("cmr_phase_seconds", "phase" => "image_encoder").record(t.image_encoder_ms / 1000.0);
                metrics::histogram!("cmr_phase_seconds", "phase" => "frustum_head").record(t.frustum_head_ms / 1000.0);
                metrics::histogram!("cmr_phase_seconds", "phase" => "agent_steps").record(t.agent_steps_ms / 1000.0);
                if let Some(judge) = localization.judge {
                    metrics::counter!("cmr_judged_requests_total").increment(1);
                    metrics::counter!("cmr_judge_views_read_total").increment(judge.read_views as u64);
                }
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

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::agent::{Localization, SearchConfig, localize};
    use crate::geometry::{Intrinsics, Pose};
    use crate::maps::{PreparedMap, prepare_map};
    use crate::model::{BackendFactory, FakeBackend, Manifest};

    fn manifest() -> Arc<Manifest> {
        Arc::new(Manifest::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tiny-model")).unwrap())
    }

    fn fake_factory(manifest: &Arc<Manifest>) -> BackendFactory {
        let m = manifest.clone();
        Arc::new(move || Ok(Box::new(FakeBackend::new(m.clone())) as Box<dyn Backend>))
    }

    fn map(manifest: &Arc<Manifest>) -> Arc<PreparedMap> {
        let cloud: Vec<[f32; 3]> = (0..5000).map(|i| [(i % 100) as f32 * 0.3 - 15.0, (i / 100) as f32 * 0.4 - 10.0, ((i * 7) % 13) as f32 * 0.2 - 1.7]).collect();
        Arc::new(prepare_map(&mut FakeBackend::new(manifest.clone()), crate::model::Points::xyz(&cloud)).unwrap())
    }

    fn start(manifest: &Arc<Manifest>, map: &Arc<PreparedMap>, i: usize, poisoned: bool) -> Start {
        let n = 3 * manifest.image.width as usize * manifest.image.height as usize;
        let mut image_tensor: Vec<f32> = (0..n).map(|p| ((p * (i + 1)) % 97) as f32 / 97.0).collect();
        if poisoned {
            image_tensor[0] = FakeBackend::POISON * 10.0;
        }
        let intrinsics = Intrinsics { fx: 250.0, fy: 250.0, cx: 255.5, cy: 79.5 };
        let rig = Pose::from_rt(nalgebra::Matrix3::new(0.0, -1.0, 0.0, 0.0, 0.0, -1.0, 1.0, 0.0, 0.0), nalgebra::Vector3::zeros());
        let prior = rig.compose(&Pose::ground_motion(0.2 * i as f64, i as f64 * 0.5, -1.0));
        Start { maps: vec![map.clone()], image_tensor, intrinsics, prior, views: Vec::new(), search: SearchConfig { hypotheses: 1 + i % 3, max_iterations: 6, narrow_after: None, merge_duplicates: i % 2 == 0, keep_prior: i % 3 == 0, prior_bound: (i % 4 == 3).then_some(crate::agent::PriorBound { rotation_deg: 30.0, translation_m: 5.0 }), refine: i % 4 == 1, polish: i % 3 == 2, prior_margin: if i % 5 == 0 { 0.03 } else { 0.0 }, axis: if i % 6 == 4 { crate::agent::search::AxisStarts { each_way: 1, step_m: 1.25, margin: 0.005 } } else { crate::agent::search::AxisStarts::NONE }, judge_zoom: 0.0, judge_gate: 1.0 } }
    }

    fn submit(scheduler: &Scheduler, start: Start) -> oneshot::Receiver<Result<Finished, JobError>> {
        let (reply, answer) = oneshot::channel();
        let job = Job { start, deadline: Instant::now() + Duration::from_secs(30), span: tracing::Span::none(), reply };
        scheduler.submit(job, scheduler.reserve().ok().expect("room")).ok().expect("queued");
        answer
    }

    fn same(a: &Localization, b: &Localization) -> bool {
        a.chosen == b.chosen
            && a.answer_steps == b.answer_steps
            && a.kept_prior == b.kept_prior
            && a.polish == b.polish
            && a.hypotheses.len() == b.hypotheses.len()
            && a.hypotheses.iter().zip(&b.hypotheses).all(|(x, y)| x.steps.len() == y.steps.len() && x.camera_from_map() == y.camera_from_map())
    }

    /// One request whose policy rows turn NaN fails alone, with a numerical error; the requests
    /// stepped in the same batched calls get exactly the answers they get alone.
    #[test]
    fn a_failing_row_fails_only_its_own_request() {
        let manifest = manifest();
        let map = map(&manifest);
        let expected: Vec<Localization> = (0..5)
            .map(|i| {
                let s = start(&manifest, &map, i, false);
                localize(&mut FakeBackend::new(manifest.clone()), &map, &s.image_tensor, s.intrinsics, s.prior, s.search).unwrap()
            })
            .collect();
        let scheduler = Scheduler::start(&fake_factory(&manifest), SchedulerConfig { workers: 1, max_batch: 16, queue_capacity: 16 }).unwrap();
        let answers: Vec<_> = (0..6).map(|i| submit(&scheduler, start(&manifest, &map, i % 5, i == 2))).collect();
        for (i, answer) in answers.into_iter().enumerate() {
            let got = answer.blocking_recv().unwrap();
            if i == 2 {
                let e = got.err().expect("the poisoned request fails");
                assert!(matches!(e, JobError::Step(StepError::NonFinite(_))), "{e}");
            } else {
                let got = got.ok().expect("batch-mates succeed").localization;
                assert!(same(&got, &expected[i % 5]), "request {i} answers as it does alone");
            }
        }
        assert!(scheduler.batch_stats().largest_batch > 3, "{:?}", scheduler.batch_stats());
        assert!(scheduler.shutdown(Duration::from_secs(5)));
    }

    /// An absurd prior is refused at admission into the batch, without reaching a policy call.
    #[test]
    fn an_absurd_prior_fails_before_any_state_is_built() {
        let manifest = manifest();
        let map = map(&manifest);
        let scheduler = Scheduler::start(&fake_factory(&manifest), SchedulerConfig { workers: 1, max_batch: 8, queue_capacity: 8 }).unwrap();
        let mut bad = start(&manifest, &map, 1, false);
        bad.prior = Pose::from_rt(nalgebra::Matrix3::identity(), nalgebra::Vector3::new(3e38, 0.0, 0.0));
        let bad = submit(&scheduler, bad);
        let good = submit(&scheduler, start(&manifest, &map, 1, false));
        assert!(matches!(bad.blocking_recv().unwrap(), Err(JobError::Step(StepError::NonFinite(_)))));
        assert!(good.blocking_recv().unwrap().is_ok());
        assert!(scheduler.shutdown(Duration::from_secs(5)));
    }

    fn counted_factory(manifest: &Arc<Manifest>, calls: &Arc<AtomicUsize>) -> BackendFactory {
        let (m, calls) = (manifest.clone(), calls.clone());
        Arc::new(move || {
            let calls = calls.clone();
            let count = Box::new(move |_: &[f32], _: &[f32], _: usize| {
                calls.fetch_add(1, Ordering::SeqCst);
                None
            });
            Ok(Box::new(FakeBackend::with_policy(m.clone(), count)) as Box<dyn Backend>)
        })
    }

    /// A request alone runs on the lone sessions (all cores), with the answer it gets from the
    /// plain ones; requests that overlap run on the per-worker sessions. Warm-up calls are
    /// counted too, so counts are taken after start.
    #[test]
    fn a_lone_request_runs_on_the_lone_sessions_and_overlapping_ones_do_not() {
        let manifest = manifest();
        let map = map(&manifest);
        let (narrow, lone) = (Arc::new(AtomicUsize::new(0)), Arc::new(AtomicUsize::new(0)));
        let config = SchedulerConfig { workers: 2, max_batch: 8, queue_capacity: 32 };
        let scheduler = Scheduler::start_with_lone(&counted_factory(&manifest, &narrow), Some(&counted_factory(&manifest, &lone)), config).unwrap();
        let (narrow_before, lone_before) = (narrow.load(Ordering::SeqCst), lone.load(Ordering::SeqCst));
        let s = start(&manifest, &map, 1, false);
        let expected = localize(&mut FakeBackend::new(manifest.clone()), &map, &s.image_tensor, s.intrinsics, s.prior, s.search).unwrap();
        let got = submit(&scheduler, s).blocking_recv().unwrap().ok().expect("answered").localization;
        assert!(same(&got, &expected));
        assert_eq!(narrow.load(Ordering::SeqCst), narrow_before, "a request alone never used the per-worker sessions");
        assert_eq!(lone.load(Ordering::SeqCst) - lone_before, expected.iterations(), "one lone policy call per iteration");
        // Twenty at once: the queue is never empty for long, so both workers run side by side
        // on their own sessions.
        let answers: Vec<_> = (0..20).map(|i| submit(&scheduler, start(&manifest, &map, i % 5, false))).collect();
        for answer in answers {
            assert!(answer.blocking_recv().unwrap().is_ok());
        }
        assert!(narrow.load(Ordering::SeqCst) > narrow_before, "overlapping requests used the per-worker sessions");
        assert!(scheduler.shutdown(Duration::from_secs(5)));
    }

    /// Slots count from reservation until a worker takes the job; a dropped slot frees its place.
    #[test]
    fn capacity_is_reserved_before_work_and_released() {
        let manifest = manifest();
        let scheduler = Scheduler::start(&fake_factory(&manifest), SchedulerConfig { workers: 1, max_batch: 8, queue_capacity: 2 }).unwrap();
        let a = scheduler.reserve().ok().unwrap();
        let _b = scheduler.reserve().ok().unwrap();
        assert!(matches!(scheduler.reserve(), Err(SubmitError::QueueFull)));
        assert_eq!(scheduler.queue_depth(), 2);
        drop(a);
        let c = scheduler.reserve().ok().expect("a released slot is free again");
        let map = map(&manifest);
        let (reply, answer) = oneshot::channel();
        let job = Job { start: start(&manifest, &map, 0, false), deadline: Instant::now() + Duration::from_secs(30), span: tracing::Span::none(), reply };
        scheduler.submit(job, c).ok().unwrap();
        assert!(answer.blocking_recv().unwrap().is_ok());
        assert_eq!(scheduler.queue_depth(), 1, "the taken job's slot is released; one is still held");
        scheduler.close();
        assert!(matches!(scheduler.reserve(), Err(SubmitError::Draining)));
    }
}
