//! The inference pool: a few threads (one per core by default, `--inference-threads`) that
//! run every scene's queued work.
//!
//! Each scene has a [`Lane`]: its queue of jobs and its worker state (model, tracker, clock
//! watch). A lane with work waits in the pool's ready list; a pool thread takes the first
//! lane, runs **one** job of it and puts the lane back at the end of the list while it has
//! more, so scenes take turns — one heavy scene cannot starve the others — and a scene's jobs
//! still run one at a time, in order. How long a lane's oldest job has waited
//! ([`Lane::delay`]) is the scene's queue delay: what admission and shedding look at.
//!
//! A fixed, small number of threads (instead of one per scene) leaves intake's threads their
//! share of the cores — the scheduler shares a core per thread, and 64 busy encoder threads
//! had left intake a sliver, so batches that arrived in time were refused as late — and keeps
//! the caches' working set to a few models at a time: a frame's wait is its place in the
//! queue, not the luck of 64 threads' time slices.
use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use super::lock;
use super::worker::{Job, Worker};
use crate::error::{Error, Result};

/// The threads and the lanes waiting for them.
#[derive(Debug)]
pub(crate) struct Pool {
    shared: Arc<Shared>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

#[derive(Debug, Default)]
struct Shared {
    ready: Mutex<Ready>,
    wake: Condvar,
}

#[derive(Debug, Default)]
struct Ready {
    lanes: VecDeque<Arc<Lane>>,
    closed: bool,
}

/// One scene's queue in the pool (see the module docs).
pub(super) struct Lane {
    jobs: Mutex<Jobs>,
    /// Signalled when the lane runs dry (for [`Lane::drain`]).
    idle: Condvar,
    /// The scene's worker; dropped once the lane is drained (its result sender with it, so
    /// the scene's result streams end).
    worker: Mutex<Option<Worker>>,
    pool: Arc<Shared>,
}

#[derive(Default)]
struct Jobs {
    queue: VecDeque<(Job, Instant)>,
    /// In the ready list or being run by a pool thread.
    scheduled: bool,
    /// No job is taken any more (the scene closed).
    closed: bool,
}

impl Pool {
    /// Starts `threads` (at least 1) pool threads.
    pub(crate) fn start(threads: usize) -> Result<Pool> {
        let shared = Arc::new(Shared::default());
        let mut handles = Vec::new();
        for k in 0..threads.max(1) {
            let s = shared.clone();
            let h = std::thread::Builder::new()
                .name(format!("inference-{k}"))
                .spawn(move || s.run())
                .map_err(|e| Error::internal_from("cannot start an inference thread", e))?;
            handles.push(h);
        }
        Ok(Pool {
            shared,
            threads: handles,
        })
    }

    /// A lane for one scene's `worker`.
    pub(super) fn lane(&self, worker: Worker) -> Arc<Lane> {
        Arc::new(Lane {
            jobs: Mutex::new(Jobs::default()),
            idle: Condvar::new(),
            worker: Mutex::new(Some(worker)),
            pool: self.shared.clone(),
        })
    }
}

impl Drop for Pool {
    /// Ends the threads once the lanes already waiting have run.
    fn drop(&mut self) {
        lock(&self.shared.ready).closed = true;
        self.shared.wake.notify_all();
        for h in self.threads.drain(..) {
            if h.join().is_err() {
                tracing::error!("inference thread panicked");
            }
        }
    }
}

impl Shared {
    /// A pool thread: run one job of the first ready lane, put the lane back, repeat.
    fn run(&self) {
        while let Some(lane) = self.next() {
            lane.run_one();
        }
    }

    fn next(&self) -> Option<Arc<Lane>> {
        let mut ready = lock(&self.ready);
        loop {
            if let Some(l) = ready.lanes.pop_front() {
                return Some(l);
            }
            if ready.closed {
                return None;
            }
            ready = self.wake.wait(ready).unwrap_or_else(|e| e.into_inner());
        }
    }

    fn schedule(&self, lane: Arc<Lane>) {
        lock(&self.ready).lanes.push_back(lane);
        self.wake.notify_one();
    }
}

impl std::fmt::Debug for Lane {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Lane").finish_non_exhaustive()
    }
}

impl Lane {
    /// Queues `job`; `Err(job)` once the lane is closed.
    pub(super) fn push(self: &Arc<Self>, job: Job) -> std::result::Result<(), Job> {
        let mut jobs = lock(&self.jobs);
        if jobs.closed {
            return Err(job);
        }
        jobs.queue.push_back((job, Instant::now()));
        if !jobs.scheduled {
            jobs.scheduled = true;
            drop(jobs);
            self.pool.schedule(self.clone());
        }
        Ok(())
    }

    /// How long the oldest queued job has waited by `now` (zero when none waits).
    pub(super) fn delay(&self, now: Instant) -> Duration {
        lock(&self.jobs)
            .queue
            .front()
            .map_or(Duration::ZERO, |(_, t)| now.saturating_duration_since(*t))
    }

    /// Runs the oldest job, then puts the lane back in the ready list if more wait.
    fn run_one(self: Arc<Self>) {
        let next = lock(&self.jobs).queue.pop_front();
        if let Some((job, queued_at)) = next
            && let Some(w) = lock(&self.worker).as_mut()
        {
            w.handle(job, queued_at);
        }
        let mut jobs = lock(&self.jobs);
        if jobs.queue.is_empty() {
            jobs.scheduled = false;
            self.idle.notify_all();
        } else {
            drop(jobs);
            self.pool.schedule(self.clone());
        }
    }

    /// Takes no job any more (those queued still run).
    pub(super) fn close(&self) {
        lock(&self.jobs).closed = true;
    }

    /// Closes the lane, waits until the queued jobs have run and drops the worker (a scene's
    /// close).
    pub(super) fn drain(&self) {
        let mut jobs = lock(&self.jobs);
        jobs.closed = true;
        while jobs.scheduled {
            jobs = self.idle.wait(jobs).unwrap_or_else(|e| e.into_inner());
        }
        drop(jobs);
        lock(&self.worker).take();
    }
}
