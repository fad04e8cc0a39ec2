//! A published frame result as it travels to every subscriber, with its JSON encoded at most
//! once per frame (not once per subscriber): thousands of SSE subscribers of one scene then
//! cost one encoding per frame and a copy each.
use std::sync::OnceLock;

use crossview_api::types::FrameWithBoxes;

/// One published frame (derefs to the [`FrameWithBoxes`] it carries).
#[derive(Debug)]
pub struct Published {
    frame: FrameWithBoxes,
    json: OnceLock<String>,
    json_with_boxes: OnceLock<String>,
}

impl Published {
    /// Wraps a frame result for publication.
    pub fn new(frame: FrameWithBoxes) -> Self {
        Published {
            frame,
            json: OnceLock::new(),
            json_with_boxes: OnceLock::new(),
        }
    }

    /// The result as JSON (SPEC's `FrameResult`), or with the frame's boxes: encoded by the
    /// first subscriber that asks, shared by the rest.
    pub fn json(&self, with_boxes: bool) -> &str {
        let (cell, encode): (_, fn(&FrameWithBoxes) -> serde_json::Result<String>) = if with_boxes {
            (&self.json_with_boxes, |f| serde_json::to_string(f))
        } else {
            (&self.json, |f| serde_json::to_string(&f.result))
        };
        cell.get_or_init(|| {
            // Finite numbers only (validated input): encoding cannot fail; stay total anyway.
            encode(&self.frame)
                .unwrap_or_else(|e| serde_json::json!({ "error": e.to_string() }).to_string())
        })
    }
}

impl std::ops::Deref for Published {
    type Target = FrameWithBoxes;

    fn deref(&self) -> &FrameWithBoxes {
        &self.frame
    }
}
