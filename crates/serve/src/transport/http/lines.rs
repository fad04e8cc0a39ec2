//! The JSON Lines form of `POST /v1/scenes/{scene}/batches`: each line pushed as one batch,
//! the answer ([`LinesReport`](crossview_api::types::LinesReport)) streamed as it goes.
use std::convert::Infallible;
use std::sync::Arc;

use axum::body::Bytes;

use crate::error::Error;
use crate::service::Service;
use crossview_api::types::{BatchAck, LineError, LineResult};
use crossview_core::Batch;

/// Input bytes one step of a [`LineRun`] may parse before it yields.
const LINES_STEP_BYTES: usize = 64 << 10;
/// Output bytes after which a step yields its chunk.
const LINES_CHUNK_BYTES: usize = 16 << 10;

/// A JSON Lines body pushed line by line (a recording's scene header line is skipped), its
/// answer streamed as it goes: `{"results": [{"line", "accepted", ...}, ...], "accepted": N,
/// "rejected": M}` plus `"stopped_at_line"` and `"stopped"` when it stopped early.
///
/// Bounded by construction: each step parses at most [`LINES_STEP_BYTES`] of input on the
/// async worker thread and yields one output chunk; the next step runs only when the client
/// has taken the previous chunk (HTTP backpressure), so neither the results nor the time of
/// one step grow with the body. Once more than `max_rejected` lines were rejected and rejected
/// lines outnumber accepted ones, the rest of the body is skipped.
pub(super) struct LineRun {
    svc: Arc<Service>,
    scene: String,
    body: Bytes,
    pos: usize,
    line_no: usize,
    accepted: usize,
    rejected: usize,
    max_rejected: usize,
    first: bool,
    done: bool,
}

impl LineRun {
    pub(super) fn new(svc: Arc<Service>, scene: String, body: Bytes, max_rejected: usize) -> Self {
        LineRun {
            svc,
            scene,
            body,
            pos: 0,
            line_no: 0,
            accepted: 0,
            rejected: 0,
            max_rejected,
            first: true,
            done: false,
        }
    }

    pub(super) fn into_stream(
        self,
    ) -> impl futures::Stream<Item = Result<Bytes, Infallible>> + Send {
        futures::stream::unfold(self, |mut run| async move {
            if run.done {
                return None;
            }
            // Let other tasks on this worker run between steps.
            tokio::task::coop::consume_budget().await;
            let chunk = run.step();
            Some((Ok(chunk), run))
        })
    }

    /// One line's outcome: `None` for skipped lines (blank, scene header).
    fn line(&self, line: &[u8]) -> Option<Result<BatchAck, Error>> {
        if line.iter().all(u8::is_ascii_whitespace) {
            return None;
        }
        let v = match serde_json::from_slice::<serde_json::Value>(line) {
            Ok(v) => v,
            Err(e) => return Some(Err(Error::invalid("body", e.to_string()))),
        };
        if v.get("scene").is_some() && v.get("camera").is_none() {
            return None;
        }
        Some(
            serde_json::from_value::<Batch>(v)
                .map_err(|e| Error::invalid("body", e.to_string()))
                .and_then(|b| self.svc.push(&self.scene, b)),
        )
    }

    /// Processes lines until the step's input or output budget is spent; returns the output.
    fn step(&mut self) -> Bytes {
        let mut out = Vec::with_capacity(LINES_CHUNK_BYTES + 1024);
        if self.first {
            out.extend_from_slice(b"{\"results\":[");
        }
        let start = self.pos;
        while self.pos < self.body.len()
            && self.pos - start < LINES_STEP_BYTES
            && out.len() < LINES_CHUNK_BYTES
        {
            if self.rejected > self.max_rejected && self.rejected > self.accepted {
                break;
            }
            let rest = &self.body[self.pos..];
            let len = rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
            let line = self.body.slice(self.pos..self.pos + len);
            self.pos += len + 1;
            self.line_no += 1;
            let item = match self.line(&line) {
                None => continue,
                Some(Ok(ack)) => {
                    self.accepted += 1;
                    LineResult {
                        line: self.line_no,
                        accepted: true,
                        camera: Some(ack.camera),
                        frame_id: Some(ack.frame_id),
                        error: None,
                    }
                }
                Some(Err(e)) => {
                    if matches!(e, Error::Core(crossview_core::Error::InvalidArgument { ref field, .. }) if field == "body")
                    {
                        self.svc.metrics().error(&e);
                    }
                    self.rejected += 1;
                    LineResult {
                        line: self.line_no,
                        accepted: false,
                        camera: None,
                        frame_id: None,
                        error: Some(LineError {
                            kind: e.kind().to_string(),
                            message: crate::echo::truncate_echo(&e.to_string()).into_owned(),
                        }),
                    }
                }
            };
            if !self.first {
                out.push(b',');
            }
            self.first = false;
            serde_json::to_writer(&mut out, &item).expect("JSON values serialize");
        }
        let stop = self.rejected > self.max_rejected && self.rejected > self.accepted;
        if self.pos >= self.body.len() || stop {
            self.done = true;
            let mut tail =
                serde_json::json!({ "accepted": self.accepted, "rejected": self.rejected });
            if self.pos < self.body.len() {
                tail["stopped_at_line"] = (self.line_no + 1).into();
                tail["stopped"] = format!(
                    "more than {} lines rejected, more than were accepted (--max-rejected-lines); the rest of the body was not read",
                    self.max_rejected
                )
                .into();
            }
            let tail = serde_json::to_string(&tail).expect("JSON values serialize");
            out.extend_from_slice(b"],");
            out.extend_from_slice(&tail.as_bytes()[1..]);
        }
        // Drop what the body no longer needs as soon as possible.
        if self.done {
            self.body = Bytes::new();
        }
        Bytes::from(out)
    }
}
