//! The ingestion thread: reads a [`FrameSource`], decodes and undistorts frames in
//! parallel (its own small rayon pool), tags phases, and hands frames and events to the
//! consumer through a bounded buffer with one of two policies:
//! - [`Policy::Replay`]: the producer blocks when the buffer is full; nothing is dropped.
//! - [`Policy::Live`]: the oldest buffered *frame* is dropped to make room (events and
//!   errors are never dropped); drops are counted.
//!
//! Shutdown: [`Ingest::stop`] (or dropping the handle) asks the thread to stop, wakes
//! it if it is blocked, and joins it. A fatal error reaches the consumer as
//! [`Message::Error`] before the stream ends.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;

use rayon::prelude::*;
use serde::Serialize;

use crate::detect::MotionEvent;
use crate::error::Error;
use crate::frame::Frame;
use crate::pipeline::{PhaseTagger, Processed, Processor, Skip};
use crate::source::FrameSource;

/// Buffer policy.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Policy {
    Replay,
    Live,
}

/// What the consumer receives.
#[derive(Debug)]
pub enum Message {
    Frame(Frame),
    Event(MotionEvent),
    /// A fatal error: the stream ends after it.
    Error(Error),
}

#[derive(Clone, Debug)]
pub struct IngestConfig {
    pub policy: Policy,
    /// Buffer capacity in messages (at least 1).
    pub capacity: usize,
    /// Frames decoded together (parallelism); 2 x threads is a good value.
    pub batch: usize,
    /// Threads of the ingestion pool (decoding and undistortion).
    pub threads: usize,
    /// Consecutive unreadable frames after which the source is declared broken.
    pub max_consecutive_errors: usize,
    /// Hand frames over no faster than they were recorded (replaying a file as if it were
    /// live, e.g. for the live preview): frame k is released at start + (t_k - t_0).
    pub realtime: bool,
}

impl Default for IngestConfig {
    fn default() -> Self {
        let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2).min(8);
        IngestConfig {
            policy: Policy::Replay,
            capacity: 16,
            batch: 2 * threads,
            threads,
            max_consecutive_errors: 16,
            realtime: false,
        }
    }
}

/// Counters, readable while the thread runs.
#[derive(Debug, Default)]
struct Counters {
    read: AtomicU64,
    delivered: AtomicU64,
    dropped: AtomicU64,
    corrupt: AtomicU64,
    unposed: AtomicU64,
    out_of_order: AtomicU64,
}

/// A snapshot of the counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct IngestStats {
    /// Frames read from the source (including corrupt ones).
    pub read: u64,
    /// Frames put into the buffer.
    pub delivered: u64,
    /// Frames dropped by the live policy.
    pub dropped: u64,
    /// Frames skipped because they would not read or decode.
    pub corrupt: u64,
    /// Frames skipped because no pose was available at their time.
    pub unposed: u64,
    /// Frames skipped because their time was not after the frame before them
    /// (the recording's clock jumped back: [`ClockOrder`]).
    pub out_of_order: u64,
}

/// A recording's frames must come in time order: where the clock jumps back (files
/// joined out of order, a device clock reset), the frames up to the time already
/// reached are skipped and counted, with a warning naming the frame where it
/// happened. Kept, they would fall into a phase whose time has passed and give the
/// motion frames out of order. Frames whose phase the source gives (datasets, whose
/// nominal clock restarts per phase) are not checked.
#[derive(Default)]
struct ClockOrder {
    last_ns: Option<i64>,
    /// Skipping since a jump back (so that a jump is reported once).
    skipping: bool,
}

impl ClockOrder {
    fn accepts(&mut self, p: &Processed, source: &str) -> bool {
        if p.given_phase.is_some() {
            return true;
        }
        match self.last_ns {
            Some(last) if p.timestamp_ns <= last => {
                if !self.skipping {
                    let (now_s, last_s) = (p.timestamp_ns as f64 * 1e-9, last as f64 * 1e-9);
                    tracing::warn!(
                        "{source}: the clock jumps back at frame {} ({now_s:.3} s after {last_s:.3} s); skipping frames until it passes {last_s:.3} s",
                        p.frame.index
                    );
                }
                self.skipping = true;
                false
            }
            _ => {
                self.last_ns = Some(p.timestamp_ns);
                self.skipping = false;
                true
            }
        }
    }
}

struct QueueState {
    items: VecDeque<Message>,
    producer_done: bool,
    consumer_gone: bool,
}

struct Queue {
    state: Mutex<QueueState>,
    not_empty: Condvar,
    not_full: Condvar,
    capacity: usize,
}

impl Queue {
    fn lock(&self) -> MutexGuard<'_, QueueState> {
        // A poisoned lock only means another thread panicked mid-update of a VecDeque of
        // owned messages; the data is still consistent enough to drain.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Push; returns false if the consumer is gone (stop producing).
    fn push(&self, m: Message, policy: Policy, counters: &Counters) -> bool {
        let is_frame = matches!(m, Message::Frame(_));
        let mut s = self.lock();
        loop {
            if s.consumer_gone {
                return false;
            }
            if s.items.len() < self.capacity {
                break;
            }
            if policy == Policy::Live {
                if let Some(pos) = s.items.iter().position(|x| matches!(x, Message::Frame(_))) {
                    s.items.remove(pos);
                    counters.dropped.fetch_add(1, Ordering::Relaxed);
                    break;
                }
                // Only events/errors buffered: let it grow rather than lose one.
                break;
            }
            s = self.not_full.wait(s).unwrap_or_else(|p| p.into_inner());
        }
        s.items.push_back(m);
        if is_frame {
            counters.delivered.fetch_add(1, Ordering::Relaxed);
        }
        self.not_empty.notify_one();
        true
    }

    fn pop(&self, block: bool) -> Option<Message> {
        let mut s = self.lock();
        loop {
            if let Some(m) = s.items.pop_front() {
                self.not_full.notify_one();
                return Some(m);
            }
            if s.producer_done || !block {
                return None;
            }
            s = self.not_empty.wait(s).unwrap_or_else(|p| p.into_inner());
        }
    }

    fn close_producer(&self) {
        self.lock().producer_done = true;
        self.not_empty.notify_all();
    }

    fn close_consumer(&self) {
        let mut s = self.lock();
        s.consumer_gone = true;
        s.items.clear();
        self.not_full.notify_all();
    }
}

/// A running ingestion thread.
pub struct Ingest {
    queue: Arc<Queue>,
    stop: Arc<AtomicBool>,
    counters: Arc<Counters>,
    handle: Option<JoinHandle<Vec<MotionEvent>>>,
    events: Vec<MotionEvent>,
}

impl Ingest {
    /// Start the thread. The source, processor and tagger move onto it.
    pub fn spawn(
        mut source: Box<dyn FrameSource>,
        processor: Processor,
        mut tagger: PhaseTagger,
        cfg: IngestConfig,
    ) -> std::io::Result<Self> {
        let queue = Arc::new(Queue {
            state: Mutex::new(QueueState { items: VecDeque::new(), producer_done: false, consumer_gone: false }),
            not_empty: Condvar::new(),
            not_full: Condvar::new(),
            capacity: cfg.capacity.max(1),
        });
        let stop = Arc::new(AtomicBool::new(false));
        let counters = Arc::new(Counters::default());
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(cfg.threads.max(1))
            .thread_name(|i| format!("aim-ingest-{i}"))
            .build()
            .map_err(std::io::Error::other)?;
        let (q, st, c) = (queue.clone(), stop.clone(), counters.clone());
        let handle = std::thread::Builder::new().name("aim-ingest".into()).spawn(move || {
            let policy = cfg.policy;
            // Realtime pacing: (first frame's timestamp, when it was handed over).
            let mut t0: Option<(f64, std::time::Instant)> = None;
            let send = |m: Message, t0: &mut Option<(f64, std::time::Instant)>| {
                if let (true, Message::Frame(f)) = (cfg.realtime, &m) {
                    let (first, started) = *t0.get_or_insert((f.timestamp_s, std::time::Instant::now()));
                    let due = std::time::Duration::from_secs_f64((f.timestamp_s - first).max(0.0));
                    if let Some(wait) = due.checked_sub(started.elapsed()) {
                        std::thread::sleep(wait);
                    }
                }
                q.push(m, policy, &c)
            };
            let mut consecutive_errors = 0usize;
            let mut clock = ClockOrder::default();
            let source_name = source.describe();
            'outer: loop {
                if st.load(Ordering::Relaxed) {
                    break;
                }
                let mut batch = Vec::with_capacity(cfg.batch.max(1));
                let mut end = false;
                while batch.len() < cfg.batch.max(1) {
                    match source.next_frame() {
                        None => {
                            end = true;
                            break;
                        }
                        Some(Ok(r)) => {
                            c.read.fetch_add(1, Ordering::Relaxed);
                            batch.push(r);
                        }
                        Some(Err(e)) => {
                            c.read.fetch_add(1, Ordering::Relaxed);
                            c.corrupt.fetch_add(1, Ordering::Relaxed);
                            consecutive_errors += 1;
                            tracing::warn!("skipping unreadable frame: {e}");
                            if consecutive_errors > cfg.max_consecutive_errors {
                                send(
                                    Message::Error(Error::Other(format!(
                                        "{}: {consecutive_errors} unreadable frames in a row, giving up; last: {e}",
                                        source.describe()
                                    ))),
                                    &mut t0,
                                );
                                break 'outer;
                            }
                        }
                    }
                }
                let processed: Vec<_> = pool.install(|| batch.into_par_iter().map(|r| processor.process(r)).collect());
                for p in processed {
                    match p {
                        Ok(p) if !clock.accepts(&p, &source_name) => {
                            c.out_of_order.fetch_add(1, Ordering::Relaxed);
                        }
                        Ok(p) => {
                            consecutive_errors = 0;
                            let (frames, ev) = tagger.push(p);
                            if let Some(ev) = ev {
                                if !send(Message::Event(ev), &mut t0) {
                                    break 'outer;
                                }
                            }
                            for f in frames {
                                if !send(Message::Frame(f), &mut t0) {
                                    break 'outer;
                                }
                            }
                        }
                        Err(Skip::Corrupt(msg)) => {
                            c.corrupt.fetch_add(1, Ordering::Relaxed);
                            tracing::warn!("skipping corrupt frame: {msg}");
                        }
                        Err(Skip::NoPose(msg)) => {
                            c.unposed.fetch_add(1, Ordering::Relaxed);
                            tracing::debug!("skipping frame without pose: {msg}");
                        }
                    }
                }
                if end {
                    for f in tagger.flush() {
                        if !send(Message::Frame(f), &mut t0) {
                            break;
                        }
                    }
                    break;
                }
            }
            q.close_producer();
            tagger.tracker.events.clone()
        })?;
        Ok(Ingest { queue, stop, counters, handle: Some(handle), events: Vec::new() })
    }

    /// Next message, blocking; None when the stream has ended.
    pub fn recv(&self) -> Option<Message> {
        self.queue.pop(true)
    }

    /// Next message if one is buffered.
    pub fn try_recv(&self) -> Option<Message> {
        self.queue.pop(false)
    }

    pub fn stats(&self) -> IngestStats {
        let c = &self.counters;
        IngestStats {
            read: c.read.load(Ordering::Relaxed),
            delivered: c.delivered.load(Ordering::Relaxed),
            dropped: c.dropped.load(Ordering::Relaxed),
            corrupt: c.corrupt.load(Ordering::Relaxed),
            unposed: c.unposed.load(Ordering::Relaxed),
            out_of_order: c.out_of_order.load(Ordering::Relaxed),
        }
    }

    /// Stop the thread (if still running), join it, and return the final counters and
    /// the events it detected.
    pub fn stop(mut self) -> (IngestStats, Vec<MotionEvent>) {
        self.shutdown();
        (self.stats(), std::mem::take(&mut self.events))
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.queue.close_consumer();
        if let Some(h) = self.handle.take() {
            match h.join() {
                Ok(ev) => self.events = ev,
                Err(_) => tracing::error!("ingestion thread panicked"),
            }
        }
    }
}

impl Drop for Ingest {
    fn drop(&mut self) {
        self.shutdown();
    }
}

impl Iterator for &Ingest {
    type Item = Message;
    fn next(&mut self) -> Option<Message> {
        self.recv()
    }
}

/// Run a source to the end on the calling thread's pool and collect frames and events
/// (batch use; same processing as the thread).
pub fn collect_all(
    source: &mut dyn FrameSource,
    processor: &Processor,
    tagger: &mut PhaseTagger,
) -> (Vec<Frame>, Vec<MotionEvent>, IngestStats) {
    let mut frames = Vec::new();
    let mut stats = IngestStats::default();
    let mut raws = Vec::new();
    while let Some(r) = source.next_frame() {
        stats.read += 1;
        match r {
            Ok(r) => raws.push(r),
            Err(e) => {
                stats.corrupt += 1;
                tracing::warn!("skipping unreadable frame: {e}");
            }
        }
    }
    let processed: Vec<_> = raws.into_par_iter().map(|r| processor.process(r)).collect();
    let (mut clock, source_name) = (ClockOrder::default(), source.describe());
    for p in processed {
        match p {
            Ok(p) if !clock.accepts(&p, &source_name) => stats.out_of_order += 1,
            Ok(p) => frames.extend(tagger.push(p).0),
            Err(Skip::Corrupt(m)) => {
                stats.corrupt += 1;
                tracing::warn!("skipping corrupt frame: {m}");
            }
            Err(Skip::NoPose(_)) => stats.unposed += 1,
        }
    }
    frames.extend(tagger.flush());
    stats.delivered = frames.len() as u64;
    let events = tagger.tracker.events.clone();
    fill_motion_time(&mut frames, &events);
    (frames, events, stats)
}

/// The time within the motion of a frame at `timestamp_s`:
/// `(t - hand_in) / (hand_out - hand_in)` in [0, 1]; None until `events` hold a
/// hand-in and a later hand-out (the whole window is known).
pub fn motion_time(timestamp_s: f64, events: &[MotionEvent]) -> Option<f32> {
    let (Some(t_in), Some(t_out)) = crate::detect::window_of(events) else { return None };
    (t_out > t_in).then(|| ((timestamp_s - t_in) / (t_out - t_in)).clamp(0.0, 1.0) as f32)
}

/// Batch only (the whole window is known): give `Motion` frames without a motion time
/// their [`motion_time`].
pub fn fill_motion_time(frames: &mut [Frame], events: &[MotionEvent]) {
    for f in frames.iter_mut() {
        if f.phase == crate::frame::Phase::Motion && f.motion_time.is_none() {
            f.motion_time = motion_time(f.timestamp_s, events);
        }
    }
}
