//! Recording of every accepted batch (`crossview serve --record DIR`), in the SPEC §7 format,
//! to rotating files, without ever holding up association.
//!
//! **Layout.** One directory per scene, `DIR/<scene>/`, holding files named
//! `<seq>-<UTC time>.jsonl` (`seq` ten digits, one counter over the whole of `DIR`, so names
//! sort in the order the files were started). Each file begins with its scene header line and
//! is a valid recording on its own; a scene's files together (read in name order, e.g.
//! `crossview eval --data DIR/<scene>`) are the scene's accepted batches in acceptance order.
//!
//! **Rotation and retention.** A scene's file is closed (flushed and `fsync`ed) and the next
//! one started when the next line would take it past `max_file_bytes`, or when a batch arrives
//! once the file is `max_file_age` old. The recording files under `DIR` (every scene, also
//! scenes not served now) never take more than `max_bytes` together: before a line is written,
//! the oldest files (lowest `seq`) are removed until it fits — the oldest file may be a scene's
//! current one, which then starts afresh.
//!
//! **Never in the way.** [`SceneRecorder::record`] only hands the batch (already validated and
//! accepted) to a bounded in-memory queue (`queue_bytes`, an estimate of the batches' memory)
//! read by one dedicated writer thread; it never blocks and never does I/O. A batch that does
//! not fit is not recorded and counted (`crossview_record_dropped_total{reason="queue_full"}`).
//! The writer serializes the lines, buffers them (up to 64 KiB per file) and writes whole lines
//! with one `write` call, whenever the buffer fills or the queue runs dry (so what was accepted
//! reaches the kernel within moments even at a trickle). A write error is logged (rate-limited)
//! and counted (`crossview_record_write_errors_total`; the lost batches in
//! `crossview_record_dropped_total{reason="write_error"}`); the file is cut back to its last
//! complete write and the next batch starts a new file. It never stops the server.
//!
//! **Clock offsets.** A file's header carries each camera's clock offset as the server applied
//! it to the file's batches. When `--auto-align` changes a camera's offset, the scene's file is
//! closed and the next one starts with the new offsets, so every file reads back (and several
//! files together, each by its own header) grouped as the server grouped them.
//!
//! **Crash safety.** A line is only ever written after the lines before it, so after a crash
//! (SIGKILL, power loss) only the *last* line of a file can be incomplete. At start-up the
//! recorder repairs every recording file under `DIR`: a tail after the last newline is cut
//! off (a file with no complete line, or an empty one, is removed), and it always starts new
//! files, never appending to old ones. Readers (`crossview_data`) also drop a torn last line of
//! each file with a count, so a recording can be read before a restart too. Graceful shutdown
//! drains the queue, writes and `fsync`s every file.
mod writer;

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crossview_core::capture::CaptureTime;
use crossview_core::{Detection, SceneSpec};

use crate::error::{Error, Result};
use crate::metrics::Metrics;
use writer::Writer;

/// A file's buffer is written out once it holds this much.
const WRITE_CHUNK: usize = 64 << 10;

/// Where and how `crossview serve --record` writes (see the module docs).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordConfig {
    /// The recording directory; one sub-directory per scene.
    pub dir: PathBuf,
    /// A file is rotated before it would grow past this many bytes.
    pub max_file_bytes: u64,
    /// A file is rotated when a batch arrives once it is this old.
    pub max_file_age: Duration,
    /// All recording files under `dir` together stay within this many bytes (the oldest
    /// files are removed first).
    pub max_bytes: u64,
    /// Memory (an estimate) of the batches waiting for the writer; beyond it batches are not
    /// recorded (and counted).
    pub queue_bytes: usize,
}

impl RecordConfig {
    /// Defaults for recording into `dir`: 64 MiB files, rotated after 10 minutes, 1 GiB in
    /// all, a 64 MiB queue.
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        RecordConfig {
            dir: dir.into(),
            max_file_bytes: 64 << 20,
            max_file_age: Duration::from_secs(600),
            max_bytes: 1 << 30,
            queue_bytes: 64 << 20,
        }
    }

    fn validate(&self) -> Result<()> {
        if self.max_file_bytes == 0 || self.max_bytes == 0 || self.queue_bytes == 0 {
            return Err(Error::invalid(
                "--record",
                "--record-max-file-bytes, --record-max-bytes and --record-queue-bytes must be positive",
            ));
        }
        if self.max_file_bytes > self.max_bytes {
            return Err(Error::invalid(
                "--record-max-file-bytes",
                format!(
                    "{} is more than --record-max-bytes {}",
                    self.max_file_bytes, self.max_bytes
                ),
            ));
        }
        if self.max_file_age.is_zero() {
            return Err(Error::invalid("--record-max-file-age", "must be positive"));
        }
        Ok(())
    }
}

/// A recorded scene's frame rates: the one it declares (its headers declare it), and its
/// clock's (declared, or the model's training rate: declared in the headers once the scene is
/// fed capture times).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct SceneRate {
    pub declared: Option<f64>,
    pub clock: Option<f64>,
}

/// One accepted batch on its way to the writer.
enum Msg {
    Batch {
        scene: usize,
        /// The camera's index in the scene (its name is in the writer's scene), and the clock
        /// offset its batch was grouped by.
        camera_index: usize,
        offset: i64,
        frame_id: u64,
        /// Its capture time, when it came with one.
        time: Option<CaptureTime>,
        detections: Vec<Detection>,
        cost: usize,
    },
    /// Close the scene's current file (its next batch starts a new one) and answer with the
    /// sequence number the next file of the whole directory will get.
    Mark {
        scene: usize,
        reply: tokio::sync::oneshot::Sender<u64>,
    },
    Stop,
}

/// The server's recorder: the queue to the writer thread (see the module docs).
pub(crate) struct Recorder {
    tx: Sender<Msg>,
    queued: Arc<AtomicUsize>,
    capacity: usize,
    closed: AtomicBool,
    metrics: Metrics,
    names: Vec<String>,
    /// The recording directory (scenes' directories below it).
    dir: PathBuf,
    writer: Mutex<Option<std::thread::JoinHandle<()>>>,
}

impl std::fmt::Debug for Recorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recorder")
            .field("scenes", &self.names)
            .finish()
    }
}

/// One scene's handle on the server's recorder (see the module docs).
#[derive(Clone)]
pub struct SceneRecorder {
    recorder: Arc<Recorder>,
    scene: usize,
}

impl Recorder {
    /// Prepares `config.dir` (creates it and the scenes' directories, repairs torn tails,
    /// applies the size bound) and starts the writer thread.
    pub(crate) fn start(
        config: RecordConfig,
        scenes: &[SceneSpec],
        rates: &[SceneRate],
        metrics: Metrics,
    ) -> Result<Arc<Recorder>> {
        config.validate()?;
        let writer = Writer::open(config.clone(), scenes, rates, metrics.clone())?;
        let (tx, rx) = std::sync::mpsc::channel();
        let queued = Arc::new(AtomicUsize::new(0));
        let q = queued.clone();
        let handle = std::thread::Builder::new()
            .name("recorder".into())
            .spawn(move || writer.run(rx, q))
            .map_err(|e| Error::internal_from("cannot start the recorder thread", e))?;
        tracing::info!(dir = %config.dir.display(), max_file_bytes = config.max_file_bytes,
            max_file_age = ?config.max_file_age, max_bytes = config.max_bytes, "recording accepted batches");
        Ok(Arc::new(Recorder {
            tx,
            queued,
            capacity: config.queue_bytes,
            closed: AtomicBool::new(false),
            metrics,
            names: scenes.iter().map(|s| s.name.clone()).collect(),
            dir: config.dir.clone(),
            writer: Mutex::new(Some(handle)),
        }))
    }

    /// The handle for scene number `scene` (its index in the `scenes` given to
    /// [`Recorder::start`]).
    pub(crate) fn scene(self: &Arc<Self>, scene: usize) -> SceneRecorder {
        SceneRecorder {
            recorder: self.clone(),
            scene,
        }
    }

    /// Stops the writer once it has written everything queued (flushed and `fsync`ed).
    /// Blocking; call after the scenes stopped accepting batches.
    pub(crate) fn close(&self) {
        if self.closed.swap(true, Ordering::AcqRel) {
            return;
        }
        let _ = self.tx.send(Msg::Stop);
        if let Some(h) = lock(&self.writer).take()
            && h.join().is_err()
        {
            tracing::error!("recorder thread panicked");
        }
    }
}

use crate::locks::lock;

/// Memory a queued batch holds (an estimate, for the queue bound).
fn batch_cost(detections: &[Detection]) -> usize {
    let vectors: usize = detections
        .iter()
        .map(|d| d.appearance.as_ref().map_or(0, |a| a.len() * 4))
        .sum();
    128 + std::mem::size_of_val(detections) + vectors
}

impl SceneRecorder {
    /// The scene's recording directory.
    pub(crate) fn dir(&self) -> PathBuf {
        self.recorder.dir.join(&self.recorder.names[self.scene])
    }

    /// Closes the scene's current file, so that what is accepted from now on goes to files
    /// of their own, and returns the first sequence number those files can have (`None` when
    /// the recorder has stopped). Batches queued before the call stay before the mark.
    pub(crate) async fn mark(&self) -> Option<u64> {
        let (reply, rx) = tokio::sync::oneshot::channel();
        let msg = Msg::Mark {
            scene: self.scene,
            reply,
        };
        self.recorder.tx.send(msg).ok()?;
        rx.await.ok()
    }

    /// This scene's recording files whose sequence number is `from` or more, with their
    /// sequence numbers, oldest first.
    pub(crate) fn files_from(&self, from: u64) -> Vec<(u64, PathBuf)> {
        let Ok(entries) = std::fs::read_dir(self.dir()) else {
            return Vec::new();
        };
        let mut files: Vec<(u64, PathBuf)> = entries
            .flatten()
            .filter_map(|e| {
                let seq = writer::file_seq(e.file_name().to_str()?)?;
                (seq >= from).then(|| (seq, e.path()))
            })
            .collect();
        files.sort_unstable();
        files
    }

    /// Queues one accepted batch of camera number `camera_index`, grouped by clock offset
    /// `offset`, for the writer; never blocks. Call it where the batch is accepted, under the
    /// scene's intake lock, so batches are written in acceptance order. A batch the queue has
    /// no room for is counted as dropped. `frame_id` is the camera's own id as the scene placed
    /// the batch (a timestamped batch's tick, so a reader groups it as the server did), `time`
    /// its capture time.
    pub(crate) fn record(
        &self,
        camera_index: usize,
        offset: i64,
        frame_id: u64,
        time: Option<CaptureTime>,
        detections: Vec<Detection>,
    ) {
        let r = &*self.recorder;
        let name = &r.names[self.scene];
        let cost = batch_cost(&detections);
        let reserved = r
            .queued
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |q| {
                (q + cost <= r.capacity && !r.closed.load(Ordering::Acquire)).then_some(q + cost)
            })
            .is_ok();
        if !reserved {
            r.metrics.record_dropped(name, "queue_full", 1);
            return;
        }
        let msg = Msg::Batch {
            scene: self.scene,
            camera_index,
            offset,
            frame_id,
            time,
            detections,
            cost,
        };
        if r.tx.send(msg).is_err() {
            r.queued.fetch_sub(cost, Ordering::AcqRel);
            r.metrics.record_dropped(name, "write_error", 1);
        }
    }
}
