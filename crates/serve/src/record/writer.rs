//! The recorder's writer thread: serializes accepted batches into the scenes' files, rotates
//! them, keeps every file under `DIR` within `max_bytes` (its books following the disk) and
//! repairs torn tails at start-up (see the parent module's docs).
use std::collections::BTreeMap;
use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, TryRecvError};
use std::time::{Duration, Instant};

use super::{Msg, RecordConfig, WRITE_CHUNK};
use crate::error::{Error, Result};
use crate::metrics::Metrics;
use crossview_core::capture::CaptureTime;
use crossview_core::types::{BatchLine, HeaderLine};
use crossview_core::{Detection, SceneSpec};

/// A recording file under `DIR`.
#[derive(Debug)]
struct FileEntry {
    path: PathBuf,
    /// Bytes on disk plus bytes buffered for it.
    bytes: u64,
    /// The served scene writing it now, if it is a scene's current file.
    open_by: Option<usize>,
    /// Removing it failed (logged once): it stays on disk, so it stays counted.
    remove_failed: bool,
}

/// What [`Writer::make_room`] achieved.
#[derive(Debug, PartialEq, Eq)]
enum Room {
    /// The bytes fit now.
    Made,
    /// It removed the writing scene's current file: start a new one and ask again.
    RemovedCurrent,
    /// No file that could be removed is left and the bytes still do not fit.
    Full,
}

/// How often the writer checks its accounting against the disk (files removed from outside).
const RECONCILE_EVERY: Duration = Duration::from_secs(1);

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
    /// The scene as the current file's header declares it (clock offsets as applied).
    spec: SceneSpec,
    /// The frame rate its headers declare: the scene's declared rate, or its clock's once it
    /// is fed capture times (its frame ids are then ticks of that rate).
    fps: Option<f64>,
    /// The scene's clock (declared, or the model's training rate).
    clock_fps: Option<f64>,
    header: Vec<u8>,
    open: Option<OpenFile>,
    last_error_log: Option<Instant>,
}

/// The writer thread's state: every recording file under `DIR` and the scenes' open files.
pub(super) struct Writer {
    config: RecordConfig,
    metrics: Metrics,
    scenes: Vec<SceneState>,
    /// Every recording file under `DIR`, by sequence number (oldest first).
    files: BTreeMap<u64, FileEntry>,
    total: u64,
    next_seq: u64,
    line: Vec<u8>,
    /// When the books were last checked against the disk ([`Writer::reconcile`]).
    last_reconcile: Instant,
}

/// A recording's first line for `spec` at `fps` (the scene's declared rate, if any),
/// newline included.
fn header_line(spec: &SceneSpec, fps: Option<f64>) -> Result<Vec<u8>> {
    let mut header = serde_json::to_vec(&HeaderLine { scene: spec, fps })
        .map_err(|e| Error::internal_from("cannot serialize the scene header", e))?;
    header.push(b'\n');
    Ok(header)
}

/// The sequence number of a recording file name `<seq>-<...>.jsonl`.
pub(super) fn file_seq(name: &str) -> Option<u64> {
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
    crossview_core::Error::io(path, e).into()
}

impl Writer {
    pub(super) fn open(
        config: RecordConfig,
        scenes: &[SceneSpec],
        rates: &[super::SceneRate],
        metrics: Metrics,
    ) -> Result<Writer> {
        let dir = &config.dir;
        std::fs::create_dir_all(dir).map_err(|e| io_err(dir, e))?;
        let mut states = Vec::new();
        for (k, spec) in scenes.iter().enumerate() {
            let rate = rates.get(k).copied().unwrap_or_default();
            let fps = rate.declared;
            if spec.name.chars().all(|c| c == '.') {
                return Err(Error::invalid(
                    "--record",
                    format!("cannot record scene '{}' (not a directory name)", spec.name),
                ));
            }
            let sdir = dir.join(&spec.name);
            std::fs::create_dir_all(&sdir).map_err(|e| io_err(&sdir, e))?;
            states.push(SceneState {
                name: spec.name.clone(),
                dir: sdir,
                spec: spec.clone(),
                fps,
                clock_fps: rate.clock,
                header: header_line(spec, fps)?,
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
                                remove_failed: false,
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
            last_reconcile: Instant::now(),
        };
        writer.make_room(0, None);
        writer.gauge();
        Ok(writer)
    }

    pub(super) fn run(mut self, rx: Receiver<Msg>, queued: Arc<AtomicUsize>) {
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
                    camera_index,
                    offset,
                    frame_id,
                    time,
                    detections,
                    cost,
                } => {
                    self.follow_offset(scene, camera_index, offset);
                    if time.is_some() {
                        self.follow_clock(scene);
                    }
                    self.write(scene, camera_index, frame_id, time, &detections);
                    queued.fetch_sub(cost, Ordering::AcqRel);
                }
                Msg::Mark { scene, reply } => {
                    self.close_file(scene);
                    let _ = reply.send(self.next_seq);
                }
                Msg::Stop => break,
            }
        }
        for s in 0..self.scenes.len() {
            self.close_file(s);
        }
        tracing::info!(dir = %self.config.dir.display(), "recording flushed");
    }

    /// Starts a new file for scene `s` when camera `cam`'s batch was grouped by another clock
    /// offset than the current file's header declares (`--auto-align` changed it).
    fn follow_offset(&mut self, s: usize, cam: usize, offset: i64) {
        let st = &mut self.scenes[s];
        let Some(c) = st.spec.cameras.get_mut(cam) else {
            return;
        };
        if c.offset == offset {
            return;
        }
        tracing::info!(scene = %st.name, camera = %c.name, from = c.offset, to = offset,
            "recording: a camera's clock offset changed; starting a new file");
        c.offset = offset;
        match header_line(&st.spec, st.fps) {
            Ok(h) => st.header = h,
            Err(e) => tracing::error!(error = %e, "cannot serialize the scene header"),
        }
        self.close_file(s);
    }

    /// Scene `s` is fed capture times: its headers declare its clock's rate from now on (a
    /// file begun without it is closed).
    fn follow_clock(&mut self, s: usize) {
        let st = &mut self.scenes[s];
        if st.fps.is_some() || st.clock_fps.is_none() {
            return;
        }
        st.fps = st.clock_fps;
        match header_line(&st.spec, st.fps) {
            Ok(h) => st.header = h,
            Err(e) => tracing::error!(error = %e, "cannot serialize the scene header"),
        }
        self.close_file(s);
    }

    /// Writes one batch line of scene `s`'s camera number `cam` (rotating and making room
    /// first).
    fn write(
        &mut self,
        s: usize,
        cam: usize,
        frame_id: u64,
        time: Option<CaptureTime>,
        detections: &[Detection],
    ) {
        self.line.clear();
        let written = match self.scenes[s].spec.cameras.get(cam) {
            Some(c) => {
                let batch = BatchLine {
                    camera: &c.name,
                    frame_id,
                    time,
                    detections,
                };
                serde_json::to_writer(&mut self.line, &batch).map_err(std::io::Error::other)
            }
            // Cannot happen: the scene resolved the index from this same camera list.
            None => Err(std::io::Error::other(format!("no camera number {cam}"))),
        };
        if let Err(e) = written {
            // Cannot happen for validated batches (finite numbers); counted all the same.
            self.failed(s, &e, 1);
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
        self.reconcile();
        // Room for the line (and the header of a new file), oldest files first.
        loop {
            let header = if self.scenes[s].open.is_none() {
                self.scenes[s].header.len() as u64
            } else {
                0
            };
            match self.make_room(len + header, Some(s)) {
                Room::Made => break,
                Room::RemovedCurrent => continue,
                Room::Full => {
                    // Old files that cannot be removed fill the budget: the bound wins.
                    self.metrics
                        .record_dropped(&self.scenes[s].name, "no_room", 1);
                    return;
                }
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

    /// Removes the oldest files until `need` more bytes fit within `max_bytes`. A file that
    /// cannot be removed stays on disk and so stays counted (the next oldest is tried): the
    /// bound holds on disk, not only in the books. `Full` when nothing more can be removed.
    fn make_room(&mut self, need: u64, writing: Option<usize>) -> Room {
        let mut stuck: Vec<u64> = Vec::new();
        while self.total + need > self.config.max_bytes {
            let Some(seq) = self.files.keys().find(|k| !stuck.contains(k)).copied() else {
                return Room::Full;
            };
            let path = self.files[&seq].path.clone();
            match std::fs::remove_file(&path) {
                Ok(()) => {
                    tracing::debug!(path = %path.display(), seq, "removed the oldest recording file (--record-max-bytes)")
                }
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    tracing::debug!(path = %path.display(), seq, "an old recording file was already gone")
                }
                Err(e) => {
                    if let Some(entry) = self.files.get_mut(&seq)
                        && !std::mem::replace(&mut entry.remove_failed, true)
                    {
                        tracing::warn!(path = %path.display(), error = %e, "cannot remove an old recording file; it stays counted against --record-max-bytes");
                    }
                    stuck.push(seq);
                    continue;
                }
            }
            let removed_current = self.forget(seq) == writing && writing.is_some();
            self.metrics.record_file_removed();
            self.gauge();
            if removed_current {
                return Room::RemovedCurrent;
            }
        }
        Room::Made
    }

    /// Drops file `seq` (gone from disk) from the books: its bytes, and the handle of the
    /// scene writing it (those lines count as recorded, then removed). Returns that scene.
    fn forget(&mut self, seq: u64) -> Option<usize> {
        let entry = self.files.remove(&seq)?;
        self.total = self.total.saturating_sub(entry.bytes);
        let s = entry.open_by?;
        if let Some(f) = self.scenes[s].open.take() {
            self.metrics
                .record_written(&self.scenes[s].name, f.buffered_lines, 0);
        }
        Some(s)
    }

    /// Brings the books in line with the disk, at most once per [`RECONCILE_EVERY`]: files
    /// removed from outside leave the accounting (a scene writing one starts a new file, its
    /// directory re-created if that went too).
    fn reconcile(&mut self) {
        if self.last_reconcile.elapsed() < RECONCILE_EVERY {
            return;
        }
        self.last_reconcile = Instant::now();
        let gone: Vec<u64> = self
            .files
            .iter()
            .filter(|(_, e)| matches!(e.path.try_exists(), Ok(false)))
            .map(|(seq, _)| *seq)
            .collect();
        for seq in gone {
            if let Some(s) = self.forget(seq) {
                tracing::warn!(scene = %self.scenes[s].name, "the current recording file was removed from outside; starting a new one");
            }
        }
        self.gauge();
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
        let create = || OpenOptions::new().write(true).create_new(true).open(&path);
        let mut file = match create() {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                // The scene's directory was removed from outside: make it again.
                tracing::warn!(dir = %st.dir.display(), "the recording directory was removed; re-creating it");
                std::fs::create_dir_all(&st.dir)?;
                create()?
            }
            r => r?,
        };
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
                remove_failed: false,
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
        self.reconcile();
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
