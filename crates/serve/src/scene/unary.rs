//! Unary association: one already synchronized frame, answered to its caller; it bypasses
//! the synchronizer but takes the same queue (and budget) as the scene's stream frames.
use std::sync::atomic::Ordering;
use std::time::Instant;

use tokio::sync::oneshot;

use crossview_api::types::FrameResult;
use crossview_core::capture::CaptureTime;
use crossview_core::{Detection, Frame};

use super::worker::Job;
use super::{Scene, lock};
use crate::error::{Error, Result};

impl Scene {
    /// Associates one already synchronized frame (unary call); bypasses the synchronizer.
    /// With `time`, the frame's id is the time's tick on the scene's clock (and a `frame_id`
    /// given too must be that tick); the result carries the tick's time.
    pub async fn associate(
        &self,
        frame_id: u64,
        time: Option<CaptureTime>,
        views: Vec<(String, Vec<Detection>)>,
    ) -> Result<FrameResult> {
        let started = Instant::now();
        let (frame_id, tick_time) = match time {
            None => (frame_id, None),
            Some(t) => {
                let tick = self.tick_of_request(frame_id, t)?;
                (tick, self.ticks.map(|k| k.time_of(tick)))
            }
        };
        if lock(&self.serving).is_none() {
            return Err(Error::NoModel(self.spec.name.clone()));
        }
        let n = self.spec.cameras.len();
        let mut frame = Frame::new(frame_id, n);
        let mut app_len: Option<usize> = None;
        for (k, (camera, mut dets)) in views.into_iter().enumerate() {
            let c = self.spec.camera_index(&camera)?;
            if frame.views[c].is_some() {
                return Err(Error::invalid(
                    format!("views[{k}].camera"),
                    format!("camera '{camera}' appears twice"),
                ));
            }
            let field = format!("views[{k}].detections");
            let len = self.validate(&field, c, &mut dets)?;
            // One length over the whole request; a unary call never fixes the scene's.
            if let (Some(a), Some(b)) = (app_len, len)
                && a != b
            {
                return Err(Error::invalid(
                    format!("{field}[0].appearance"),
                    format!("expected {a} values, got {b}"),
                ));
            }
            app_len = app_len.or(len);
            self.check_appearance(&field, len)?;
            frame.views[c] = Some(dets);
        }
        let counts: Vec<usize> = frame
            .views
            .iter()
            .map(|v| v.as_ref().map_or(0, Vec::len))
            .collect();
        self.check_cost("views", frame_id, &counts)?;
        let (tx, rx) = oneshot::channel();
        self.admit(1)?;
        self.queued.fetch_add(1, Ordering::AcqRel);
        let job = Job::Unary {
            frame,
            started,
            reply: tx,
        };
        if self.lane.push(job).is_err() {
            self.queued.fetch_sub(1, Ordering::AcqRel);
            return Err(Error::Unavailable("server is shutting down".into()));
        }
        let mut r = rx
            .await
            .map_err(|_| Error::Unavailable("encoder worker stopped".into()))??;
        r.time = tick_time.or(r.time);
        Ok(r)
    }

    /// The tick of a unary request's capture time `t` (no camera offsets: the frame is already
    /// synchronized); a nonzero `frame_id` must be that tick.
    fn tick_of_request(&self, frame_id: u64, t: CaptureTime) -> Result<u64> {
        let ticks = self
            .ticks
            .ok_or_else(|| super::timing::no_rate(self.name()))?;
        let tick = ticks
            .nearest(t.unix_nanos() as f64)
            .map(|n| n.tick)
            .ok_or_else(|| Error::invalid("time", format!("time {t} is out of range")))?;
        if frame_id != 0 && frame_id != tick {
            return Err(Error::invalid(
                "frame_id",
                format!(
                    "frame_id {frame_id} disagrees with time {t}, whose tick is {tick} ({} \
                     frames/s)",
                    ticks.fps()
                ),
            ));
        }
        Ok(tick)
    }
}
