//! What a scene accepts: detection counts, boxes (clipped to the image when they overlap its
//! edge, counted), appearance vectors of one length and bounded magnitude, and the frame-cost
//! budget ([`crate::cost`]).
use std::sync::atomic::Ordering;

use crossview_core::Detection;

use super::Scene;
use crate::cost::frame_cost;
use crate::error::{Error, Result};

/// Largest accepted magnitude of an appearance value: small enough that squared distances stay
/// finite in `f32`. (Box coordinates are bounded by clipping to the image.)
pub(crate) const MAX_MAGNITUDE: f32 = 1e6;

impl Scene {
    /// Checks one camera's detections and clips boxes overlapping the image edge: count cap,
    /// every box and value, one appearance length within the batch and equal to the scene's
    /// once known. Returns the batch's appearance length (when its detections carry vectors);
    /// it does not fix the scene's (only an accepted batch does, see [`Self::push`]).
    /// `field` prefixes error fields (e.g. `views[1].detections`).
    pub(super) fn validate(
        &self,
        field: &str,
        camera: usize,
        detections: &mut [Detection],
    ) -> Result<Option<usize>> {
        if detections.len() > self.limits.max_detections {
            return Err(Error::invalid(
                field,
                format!(
                    "at most {} detections per batch, got {}",
                    self.limits.max_detections,
                    detections.len()
                ),
            ));
        }
        let cam = &self.spec.cameras[camera];
        let mut expected = match self.appearance_len.load(Ordering::Relaxed) {
            0 => None,
            n => Some(n),
        };
        let (mut with_app, mut clipped) = (0, 0);
        for (i, d) in detections.iter_mut().enumerate() {
            let f = format!("{field}[{i}]");
            if let Some(app) = &d.appearance {
                if app.len() > self.limits.max_appearance_len {
                    return Err(Error::invalid(
                        format!("{f}.appearance"),
                        format!(
                            "at most {} values, got {}",
                            self.limits.max_appearance_len,
                            app.len()
                        ),
                    ));
                }
                expected.get_or_insert(app.len());
                with_app += 1;
            }
            d.validate(&f, expected)?;
            if let Some(app) = &d.appearance
                && let Some(k) = app.iter().position(|v| v.abs() > MAX_MAGNITUDE)
            {
                return Err(Error::invalid(
                    format!("{f}.appearance[{k}]"),
                    format!("magnitude must be at most {MAX_MAGNITUDE}"),
                ));
            }
            clipped += usize::from(d.clip_to_image(&f, cam)?);
        }
        if with_app != 0 && with_app != detections.len() {
            return Err(Error::invalid(
                format!("{field}[].appearance"),
                "present on some detections of the batch but not all",
            ));
        }
        if clipped > 0 {
            self.metrics.clipped(self.name(), clipped);
        }
        Ok(expected.filter(|_| with_app > 0))
    }

    /// Checks a batch's appearance length against the scene's (known or not yet).
    pub(super) fn check_appearance(&self, field: &str, len: Option<usize>) -> Result<()> {
        match (self.appearance_len.load(Ordering::Relaxed), len) {
            (known, Some(n)) if known != 0 && known != n => Err(Error::invalid(
                format!("{field}[0].appearance"),
                format!("expected {known} values, got {n}"),
            )),
            _ => Ok(()),
        }
    }

    /// Refuses a frame that would cost more than the budget ([`crate::cost`]).
    pub(super) fn check_cost(&self, field: &str, frame_id: u64, counts: &[usize]) -> Result<()> {
        let cost = frame_cost(counts);
        if cost > self.limits.max_frame_cost {
            return Err(Error::invalid(
                field,
                format!(
                    "frame {frame_id} with {counts:?} boxes per camera would cost {cost} \
                     association units, over the limit of {} (--max-frame-cost): send fewer \
                     detections per camera",
                    self.limits.max_frame_cost
                ),
            ));
        }
        Ok(())
    }
}
