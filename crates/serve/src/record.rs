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
//! **Crash safety.** A line is only ever written after the lines before it, so after a crash
//! (SIGKILL, power loss) only the *last* line of a file can be incomplete. At start-up the
//! recorder repairs every recording file under `DIR`: a tail after the last newline is cut
//! off (a file with no complete line, or an empty one, is removed), and it always starts new
//! files, never appending to old ones. Readers (`crossview_data`) also drop a torn last line of
//! each file with a count, so a recording can be read before a restart too. Graceful shutdown
//! drains the queue, writes and `fsync`s every file.
use std::collections::BTreeMap;
use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, Sender, TryRecvError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Serialize;

use crossview_core::{Detection, Error, Result, SceneSpec};

use crate::metrics::Metrics;

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

/// One accepted batch on its way to the writer.
enum Msg {
    Batch {
        scene: usize,
        camera: String,
        frame_id: u64,
        detections: Vec<Detection>,
        cost: usize,
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
        metrics: Metrics,
    ) -> Result<Arc<Recorder>> {
        config.validate()?;
        let writer = Writer::open(config.clone(), scenes, metrics.clone())?;
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

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Memory a queued batch holds (an estimate, for the queue bound).
fn batch_cost(camera: &str, detections: &[Detection]) -> usize {
    let vectors: usize = detections
        .iter()
        .map(|d| d.appearance.as_ref().map_or(0, |a| a.len() * 4))
        .sum();
    128 + camera.len() + std::mem::size_of_val(detections) + vectors
}

impl SceneRecorder {
    /// Queues one accepted batch for the writer; never blocks. Call it where the batch is
    /// accepted, under the scene's intake lock, so batches are written in acceptance order.
    /// A batch the queue has no room for is counted as dropped.
    pub(crate) fn record(&self, camera: &str, frame_id: u64, detections: Vec<Detection>) {
        let r = &*self.recorder;
        let name = &r.names[self.scene];
        let cost = batch_cost(camera, &detections);
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
            camera: camera.to_string(),
            frame_id,
            detections,
            cost,
        };
        if r.tx.send(msg).is_err() {
            r.queued.fetch_sub(cost, Ordering::AcqRel);
            r.metrics.record_dropped(name, "write_error", 1);
        }
    }
}

/// The header line of a recording file.
#[derive(Serialize)]
struct HeaderRef<'a> {
    scene: &'a SceneSpec,
}

/// One batch line.
#[derive(Serialize)]
struct BatchRef<'a> {
    camera: &'a str,
    frame_id: u64,
    detections: &'a [Detection],
}

/// A recording file under `DIR`.
#[derive(Debug)]
struct FileEntry {
    path: PathBuf,
    /// Bytes on disk plus bytes buffered for it.
    bytes: u64,
    /// The served scene writing it now, if it is a scene's current file.
    open_by: Option<usize>,
}

/// A scene's current file.
struct OpenFile {
    seq: u64,
    file: File,
    opened: Instant,
    /// Bytes on disk (all whole lines).
    committed: u64,
    /// Whole lines not yet written.
    buffer: Vec<u8>,
    buffered_lines: u64,
}

struct SceneState {
    name: String,
    dir: PathBuf,
    header: Vec<u8>,
    open: Option<OpenFile>,
    last_error_log: Option<Instant>,
}

/// The writer thread's state: every recording file under `DIR` and the scenes' open files.
struct Writer {
    config: RecordConfig,
    metrics: Metrics,
    scenes: Vec<SceneState>,
    /// Every recording file under `DIR`, by sequence number (oldest first).
    files: BTreeMap<u64, FileEntry>,
    total: u64,
    next_seq: u64,
    line: Vec<u8>,
}

/// The sequence number of a recording file name `<seq>-<...>.jsonl`.
fn file_seq(name: &str) -> Option<u64> {
    let stem = name.strip_suffix(".jsonl")?;
    let (seq, _) = stem.split_once('-')?;
    (seq.len() == 10 && seq.bytes().all(|b| b.is_ascii_digit()))
        .then(|| seq.parse().ok())
        .flatten()
}

/// Cuts a torn tail (bytes after the last newline) off `path`; removes the file when it holds
/// no complete line. Returns the repaired size, `None` when the file was removed.
fn repair(path: &Path) -> std::io::Result<Option<u64>> {
    let mut f = OpenOptions::new().read(true).write(true).open(path)?;
    let len = f.metadata()?.len();
    let mut end = len;
    let mut chunk = vec![0u8; 64 << 10];
    let keep = loop {
        if end == 0 {
            break 0;
        }
        let n = chunk.len().min(end as usize);
        let start = end - n as u64;
        f.seek(SeekFrom::Start(start))?;
        f.read_exact(&mut chunk[..n])?;
        if let Some(i) = chunk[..n].iter().rposition(|&b| b == b'\n') {
            break start + i as u64 + 1;
        }
        end = start;
    };
    if keep == 0 {
        drop(f);
        std::fs::remove_file(path)?;
        if len > 0 {
            tracing::warn!(path = %path.display(), bytes = len, "removed a recording file without one complete line (torn by a crash)");
        }
        return Ok(None);
    }
    if keep < len {
        f.set_len(keep)?;
        f.sync_all()?;
        tracing::warn!(path = %path.display(), cut_bytes = len - keep, "cut the torn last line of a recording file (left by a crash)");
    }
    Ok(Some(keep))
}

fn io_err(path: &Path, e: std::io::Error) -> Error {
    Error::io(path, e)
}

impl Writer {
    fn open(config: RecordConfig, scenes: &[SceneSpec], metrics: Metrics) -> Result<Writer> {
        let dir = &config.dir;
        std::fs::create_dir_all(dir).map_err(|e| io_err(dir, e))?;
        let mut states = Vec::new();
        for spec in scenes {
            if spec.name.chars().all(|c| c == '.') {
                return Err(Error::invalid(
                    "--record",
                    format!("cannot record scene '{}' (not a directory name)", spec.name),
                ));
            }
            let sdir = dir.join(&spec.name);
            std::fs::create_dir_all(&sdir).map_err(|e| io_err(&sdir, e))?;
            let mut header = serde_json::to_vec(&HeaderRef { scene: spec })
                .map_err(|e| Error::internal_from("cannot serialize the scene header", e))?;
            header.push(b'\n');
            states.push(SceneState {
                name: spec.name.clone(),
                dir: sdir,
                header,
                open: None,
                last_error_log: None,
            });
        }
        // Every recording file under DIR/*/, torn tails repaired.
        let mut files = BTreeMap::new();
        let subdirs = std::fs::read_dir(dir).map_err(|e| io_err(dir, e))?;
        for sub in subdirs.flatten() {
            if !sub.file_type().is_ok_and(|t| t.is_dir()) {
                continue;
            }
            let Ok(entries) = std::fs::read_dir(sub.path()) else {
                continue;
            };
            for entry in entries.flatten() {
                let name = entry.file_name();
                let Some(seq) = name.to_str().and_then(file_seq) else {
                    continue;
                };
                if !entry.file_type().is_ok_and(|t| t.is_file()) {
                    continue;
                }
                let path = entry.path();
                match repair(&path) {
                    Ok(Some(bytes)) => {
                        files.insert(
                            seq,
                            FileEntry {
                                path,
                                bytes,
                                open_by: None,
                            },
                        );
                    }
                    Ok(None) => {}
                    Err(e) => return Err(io_err(&path, e)),
                }
            }
        }
        let total = files.values().map(|f| f.bytes).sum();
        let next_seq = files.keys().next_back().map_or(1, |s| s + 1);
        let mut writer = Writer {
            config,
            metrics,
            scenes: states,
            files,
            total,
            next_seq,
            line: Vec::new(),
        };
        writer.make_room(0, None);
        writer.gauge();
        Ok(writer)
    }

    fn run(mut self, rx: Receiver<Msg>, queued: Arc<AtomicUsize>) {
        loop {
            let msg = match rx.try_recv() {
                Ok(m) => m,
                Err(TryRecvError::Empty) => {
                    // The queue ran dry: hand everything buffered to the kernel.
                    self.flush_all();
                    match rx.recv() {
                        Ok(m) => m,
                        Err(_) => break,
                    }
                }
                Err(TryRecvError::Disconnected) => break,
            };
            match msg {
                Msg::Batch {
                    scene,
                    camera,
                    frame_id,
                    detections,
                    cost,
                } => {
                    self.write(scene, &camera, frame_id, &detections);
                    queued.fetch_sub(cost, Ordering::AcqRel);
                }
                Msg::Stop => break,
            }
        }
        for s in 0..self.scenes.len() {
            self.close_file(s);
        }
        tracing::info!(dir = %self.config.dir.display(), "recording flushed");
    }

    /// Writes one batch line of scene `s` (rotating and making room first).
    fn write(&mut self, s: usize, camera: &str, frame_id: u64, detections: &[Detection]) {
        self.line.clear();
        let batch = BatchRef {
            camera,
            frame_id,
            detections,
        };
        if let Err(e) = serde_json::to_writer(&mut self.line, &batch) {
            // Cannot happen for validated batches (finite numbers); counted all the same.
            self.failed(s, &std::io::Error::other(e), 1);
            return;
        }
        self.line.push(b'\n');
        let len = self.line.len() as u64;
        if let Some(f) = &self.scenes[s].open {
            let size = f.committed + f.buffer.len() as u64;
            let header = self.scenes[s].header.len() as u64;
            let full = size + len > self.config.max_file_bytes && size > header;
            if full || f.opened.elapsed() >= self.config.max_file_age {
                self.close_file(s);
            }
        }
        // Room for the line (and the header of a new file), oldest files first.
        loop {
            let header = if self.scenes[s].open.is_none() {
                self.scenes[s].header.len() as u64
            } else {
                0
            };
            if !self.make_room(len + header, Some(s)) {
                break;
            }
        }
        if self.scenes[s].open.is_none()
            && let Err(e) = self.start_file(s)
        {
            self.failed(s, &e, 1);
            return;
        }
        let Some(f) = self.scenes[s].open.as_mut() else {
            return;
        };
        f.buffer.extend_from_slice(&self.line);
        f.buffered_lines += 1;
        let seq = f.seq;
        let flush = f.buffer.len() >= WRITE_CHUNK;
        if let Some(e) = self.files.get_mut(&seq) {
            e.bytes += len;
        }
        self.total += len;
        if flush {
            self.flush(s);
        }
    }

    /// Removes the oldest files until `need` more bytes fit within `max_bytes`. Returns true
    /// when it removed the current file of scene `writing` (whose caller must then start a new
    /// file, with a header, and ask again).
    fn make_room(&mut self, need: u64, writing: Option<usize>) -> bool {
        while self.total + need > self.config.max_bytes {
            let Some((seq, entry)) = self.files.pop_first() else {
                return false;
            };
            if let Some(s) = entry.open_by {
                // A scene's current file: drop its handle and buffer (those lines are removed
                // with the file; they count as recorded, then removed as the oldest).
                if let Some(f) = self.scenes[s].open.take() {
                    self.metrics
                        .record_written(&self.scenes[s].name, f.buffered_lines, 0);
                }
            }
            self.total = self.total.saturating_sub(entry.bytes);
            match std::fs::remove_file(&entry.path) {
                Ok(()) => {
                    tracing::debug!(path = %entry.path.display(), seq, "removed the oldest recording file (--record-max-bytes)")
                }
                Err(e) => {
                    tracing::warn!(path = %entry.path.display(), error = %e, "cannot remove an old recording file")
                }
            }
            self.metrics.record_file_removed();
            self.gauge();
            if entry.open_by.is_some() && entry.open_by == writing {
                return true;
            }
        }
        false
    }

    /// Starts scene `s`'s next file with its header.
    fn start_file(&mut self, s: usize) -> std::io::Result<()> {
        let seq = self.next_seq;
        self.next_seq += 1;
        let now = time::OffsetDateTime::now_utc();
        let name = format!(
            "{seq:010}-{:04}{:02}{:02}T{:02}{:02}{:02}Z.jsonl",
            now.year(),
            u8::from(now.month()),
            now.day(),
            now.hour(),
            now.minute(),
            now.second()
        );
        let st = &mut self.scenes[s];
        let path = st.dir.join(name);
        let mut file = OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&path)?;
        // The header goes out at once: a file on disk always starts with a whole header.
        if let Err(e) = file.write_all(&st.header) {
            drop(file);
            let _ = std::fs::remove_file(&path);
            return Err(e);
        }
        let bytes = st.header.len() as u64;
        st.open = Some(OpenFile {
            seq,
            file,
            opened: Instant::now(),
            committed: bytes,
            buffer: Vec::with_capacity(WRITE_CHUNK + 4096),
            buffered_lines: 0,
        });
        tracing::debug!(path = %path.display(), "started a recording file");
        self.files.insert(
            seq,
            FileEntry {
                path,
                bytes,
                open_by: Some(s),
            },
        );
        self.total += bytes;
        self.gauge();
        Ok(())
    }

    /// Writes scene `s`'s buffered lines with one call.
    fn flush(&mut self, s: usize) {
        let Some(f) = self.scenes[s].open.as_mut() else {
            return;
        };
        if f.buffer.is_empty() {
            return;
        }
        match f.file.write_all(&f.buffer) {
            Ok(()) => {
                f.committed += f.buffer.len() as u64;
                let (lines, bytes) = (f.buffered_lines, f.buffer.len() as u64);
                f.buffer.clear();
                f.buffered_lines = 0;
                self.metrics
                    .record_written(&self.scenes[s].name, lines, bytes);
            }
            Err(e) => {
                let lines = f.buffered_lines;
                self.failed(s, &e, lines);
            }
        }
    }

    fn flush_all(&mut self) {
        for s in 0..self.scenes.len() {
            self.flush(s);
        }
        self.gauge();
    }

    /// Flushes, `fsync`s and closes scene `s`'s current file.
    fn close_file(&mut self, s: usize) {
        self.flush(s);
        if let Some(f) = self.scenes[s].open.take() {
            if let Some(e) = self.files.get_mut(&f.seq) {
                e.open_by = None;
            }
            if let Err(e) = f.file.sync_data() {
                self.log_error(s, &e);
            }
        }
    }

    /// A failed write of scene `s`: `lost` batches are not recorded; the file is cut back to
    /// its last complete write and closed, so the next batch starts a new file.
    fn failed(&mut self, s: usize, e: &std::io::Error, lost: u64) {
        self.log_error(s, e);
        let name = self.scenes[s].name.clone();
        self.metrics.record_write_error(&name);
        self.metrics.record_dropped(&name, "write_error", lost);
        if let Some(f) = self.scenes[s].open.take() {
            let _ = f.file.set_len(f.committed);
            if let Some(entry) = self.files.get_mut(&f.seq) {
                self.total = self
                    .total
                    .saturating_sub(entry.bytes - f.committed.min(entry.bytes));
                entry.bytes = f.committed;
                entry.open_by = None;
            }
        }
    }

    /// Logs a write error, at most once every 10 s per scene.
    fn log_error(&mut self, s: usize, e: &std::io::Error) {
        let st = &mut self.scenes[s];
        if st
            .last_error_log
            .is_none_or(|t| t.elapsed() >= Duration::from_secs(10))
        {
            tracing::error!(scene = %st.name, dir = %st.dir.display(), error = %e, "recording write failed (batches not recorded are counted in crossview_record_dropped_total)");
            st.last_error_log = Some(Instant::now());
        }
    }

    fn gauge(&self) {
        self.metrics.record_disk_bytes(self.total);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names_parse() {
        assert_eq!(file_seq("0000000042-20260101T000000Z.jsonl"), Some(42));
        assert_eq!(file_seq("42-x.jsonl"), None);
        assert_eq!(file_seq("0000000042-x.json"), None);
        assert_eq!(file_seq("notes.jsonl"), None);
    }

    #[test]
    fn repair_cuts_the_torn_tail_and_removes_headless_files() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.jsonl");
        std::fs::write(&p, b"{\"a\":1}\n{\"b\":2}\n{\"c\":").unwrap();
        assert_eq!(repair(&p).unwrap(), Some(16));
        assert_eq!(std::fs::read(&p).unwrap(), b"{\"a\":1}\n{\"b\":2}\n");
        assert_eq!(repair(&p).unwrap(), Some(16));
        std::fs::write(&p, b"{\"scene\": {\"na").unwrap();
        assert_eq!(repair(&p).unwrap(), None);
        assert!(!p.exists());
        std::fs::write(&p, b"").unwrap();
        assert_eq!(repair(&p).unwrap(), None);
        // A tail longer than one read chunk.
        let mut text = b"{\"a\":1}\n".to_vec();
        text.extend(std::iter::repeat_n(0u8, 200_000));
        std::fs::write(&p, &text).unwrap();
        assert_eq!(repair(&p).unwrap(), Some(8));
    }
}
