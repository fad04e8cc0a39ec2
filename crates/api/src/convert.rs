//! Every conversion between the protobuf messages ([`crate::pb`]) and the domain and JSON types
//! (`crossview_core`, [`crate::types`]), in both directions.
use crossview_core::capture::CaptureTime;
use crossview_core::identity::Identity;
use crossview_core::{Batch, Detection, Error, Frame, Result, SceneSpec};

use crate::pb;
use crate::types;

/// Protobuf detections → domain detections; a missing box is an error naming its field.
pub(crate) fn detections_from_pb(field: &str, dets: Vec<pb::Detection>) -> Result<Vec<Detection>> {
    dets.into_iter()
        .enumerate()
        .map(|(i, d)| {
            let b = d
                .bbox
                .ok_or_else(|| Error::invalid(format!("{field}[{i}].bbox"), "missing"))?;
            Ok(Detection {
                bbox: [b.x1, b.y1, b.x2, b.y2],
                score: d.score.unwrap_or(1.0),
                id: None,
                appearance: (!d.appearance.is_empty()).then_some(d.appearance),
            })
        })
        .collect()
}

/// A protobuf timestamp → a capture time; out of range (before 1970, past 2262, nanos outside
/// `0..1e9`) is an error naming `field`.
pub fn time_from_pb(field: &str, t: Option<prost_types::Timestamp>) -> Result<Option<CaptureTime>> {
    let Some(t) = t else { return Ok(None) };
    if !(0..1_000_000_000).contains(&t.nanos) {
        return Err(Error::invalid(
            field,
            format!("nanos {} is outside 0..999999999", t.nanos),
        ));
    }
    let ns = t
        .seconds
        .checked_mul(1_000_000_000)
        .and_then(|s| s.checked_add(i64::from(t.nanos)))
        .ok_or_else(|| Error::invalid(field, format!("{} s is beyond 2262", t.seconds)))?;
    CaptureTime::from_unix_nanos(ns)
        .map(Some)
        .map_err(|e| Error::invalid(field, e))
}

/// A capture time → a protobuf timestamp.
pub fn time_to_pb(t: CaptureTime) -> prost_types::Timestamp {
    let ns = t.unix_nanos();
    prost_types::Timestamp {
        seconds: ns.div_euclid(1_000_000_000),
        nanos: ns.rem_euclid(1_000_000_000) as i32,
    }
}

/// Protobuf batch → (scene, domain batch).
pub fn batch_from_pb(b: pb::Batch) -> Result<(String, Batch)> {
    let detections = detections_from_pb("detections", b.detections)?;
    Ok((
        b.scene,
        Batch {
            camera: b.camera,
            frame_id: b.frame_id,
            time: time_from_pb("time", b.time)?,
            detections,
        },
    ))
}

/// Protobuf unary request → (scene, domain request).
pub fn associate_from_pb(r: pb::AssociateRequest) -> Result<(String, types::AssociateRequest)> {
    let views = r
        .views
        .into_iter()
        .enumerate()
        .map(|(k, v)| {
            Ok(types::CameraView {
                camera: v.camera,
                detections: detections_from_pb(&format!("views[{k}].detections"), v.detections)?,
            })
        })
        .collect::<Result<_>>()?;
    Ok((
        r.scene,
        types::AssociateRequest {
            frame_id: r.frame_id,
            views,
            time: time_from_pb("time", r.time)?,
        },
    ))
}

/// A core identity of scene `spec` as its published form (members named by camera), with
/// its track id when the frame was tracked.
pub fn identity_out(spec: &SceneSpec, id: Identity, track_id: Option<u64>) -> types::IdentityOut {
    types::IdentityOut {
        id: id.id,
        track_id,
        confidence: id.confidence,
        members: id
            .members
            .into_iter()
            .map(|(c, index)| types::Member {
                camera: spec.cameras[c].name.clone(),
                camera_index: c,
                index,
            })
            .collect(),
    }
}

/// A published identity back as the core type (what a client scores).
pub fn identity_from_out(i: &types::IdentityOut) -> Identity {
    Identity {
        id: i.id,
        confidence: i.confidence,
        members: i
            .members
            .iter()
            .map(|m| (m.camera_index, m.index))
            .collect(),
    }
}

/// A protobuf identity back as the core type (what a gRPC client scores).
pub fn identity_from_pb(i: &pb::Identity) -> Identity {
    Identity {
        id: i.id as usize,
        confidence: i.confidence,
        members: i
            .members
            .iter()
            .map(|m| (m.camera_index as usize, m.index as usize))
            .collect(),
    }
}

/// Domain result → protobuf.
pub fn result_to_pb(r: &types::FrameResult) -> pb::FrameResult {
    pb::FrameResult {
        scene: r.scene.clone(),
        frame_id: r.frame_id,
        time: r.time.map(time_to_pb),
        complete: r.complete,
        missing_cameras: r.missing_cameras.clone(),
        fenced_cameras: r.fenced_cameras.clone(),
        identities: r
            .identities
            .iter()
            .map(|i| pb::Identity {
                id: i.id as u32,
                track_id: i.track_id,
                confidence: i.confidence,
                members: i
                    .members
                    .iter()
                    .map(|m| pb::Member {
                        camera: m.camera.clone(),
                        camera_index: m.camera_index as u32,
                        index: m.index as u32,
                    })
                    .collect(),
            })
            .collect(),
        latency_ms: r.latency_ms,
        error: r.error.clone().unwrap_or_default(),
        error_kind: r.error_kind.clone().unwrap_or_default(),
        status: match r.status {
            types::ResultStatus::Associated => pb::ResultStatus::Associated,
            types::ResultStatus::NoModel => pb::ResultStatus::NoModel,
            types::ResultStatus::Failed => pb::ResultStatus::Failed,
            types::ResultStatus::Shed => pb::ResultStatus::Shed,
        } as i32,
        model_version: r.model_version.clone().unwrap_or_default(),
    }
}

/// Reload outcome → protobuf.
pub fn reload_to_pb(o: types::ReloadOutcome) -> pb::ReloadOutcome {
    pb::ReloadOutcome {
        scene: o.scene,
        outcome: o.outcome,
        version: o.version.unwrap_or_default(),
        error: o.error.unwrap_or_default(),
    }
}

/// Scene description → protobuf.
pub fn scene_to_pb(s: types::SceneDescription) -> pb::Scene {
    pb::Scene {
        name: s.name,
        cameras: s
            .cameras
            .into_iter()
            .map(|c| pb::Camera {
                name: c.name,
                width: c.width,
                height: c.height,
                offset: c.offset,
            })
            .collect(),
        threshold: s.threshold,
        alpha: s.alpha,
        model_version: s.model_version.unwrap_or_default(),
        appearance_length: s.appearance_length.unwrap_or(0) as u32,
        sync_timeout_ms: s.sync_timeout_ms,
        clock: s.clock.map(clock_to_pb),
        fit: s.fit.map(fit_to_pb),
        retrain: s.retrain.map(retrain_to_pb),
    }
}

/// Healing status → protobuf.
pub fn retrain_to_pb(r: types::RetrainStatus) -> pb::RetrainStatus {
    pb::RetrainStatus {
        state: r.state,
        cameras: r.cameras,
        attempts: r.attempts,
        swapped: r.swapped,
        last_outcome: r.last_outcome.unwrap_or_default(),
        last_reason: r.last_reason.unwrap_or_default(),
        last_model: r.last_model.unwrap_or_default(),
    }
}

/// Live camera fit → protobuf.
pub fn fit_to_pb(f: types::FitEstimate) -> pb::FitEstimate {
    pb::FitEstimate {
        frames: u32::try_from(f.frames).unwrap_or(u32::MAX),
        as_of_frame: f.as_of_frame,
        cameras: f
            .cameras
            .into_iter()
            .map(|c| pb::CameraFit {
                camera: c.camera,
                known: c.score.is_some(),
                score: c.score.unwrap_or(0.0),
                state: c.state,
            })
            .collect(),
    }
}

/// Live clock estimate → protobuf.
pub fn clock_to_pb(c: types::ClockEstimate) -> pb::ClockEstimate {
    pb::ClockEstimate {
        frames: u32::try_from(c.frames).unwrap_or(u32::MAX),
        as_of_frame: c.as_of_frame,
        step: c.step,
        reference: c.reference,
        cameras: c
            .cameras
            .into_iter()
            .map(|c| pb::CameraClock {
                camera: c.camera,
                known: c.offset_frames.is_some(),
                offset_frames: c.offset_frames.unwrap_or(0.0),
                offset_ids: c.offset_ids.unwrap_or(0),
                confidence: c.confidence,
                offset_ms: c.offset_ms,
                drift_ms_per_min: c.drift_ms_per_min,
                jitter_ms: c.jitter_ms,
            })
            .collect(),
    }
}

/// The wire form of one detection: box, score, appearance — never the ground-truth id.
pub fn detection_to_pb(d: &Detection) -> pb::Detection {
    pb::Detection {
        bbox: Some(pb::BoundingBox {
            x1: d.bbox[0],
            y1: d.bbox[1],
            x2: d.bbox[2],
            y2: d.bbox[3],
        }),
        score: Some(d.score),
        appearance: d.appearance.clone().unwrap_or_default(),
    }
}

/// A domain batch as the protobuf message for scene `scene`.
pub fn batch_to_pb(scene: &str, b: &Batch) -> pb::Batch {
    pb::Batch {
        scene: scene.to_string(),
        camera: b.camera.clone(),
        frame_id: b.frame_id,
        detections: b.detections.iter().map(detection_to_pb).collect(),
        time: b.time.map(time_to_pb),
    }
}

/// The boxes of every camera that reported `frame` of scene `spec` (the `views` of a
/// [`types::FrameWithBoxes`]), in scene order; views beyond the scene's cameras are ignored.
pub fn frame_boxes(spec: &SceneSpec, frame: &Frame) -> Vec<types::CameraBoxes> {
    spec.cameras
        .iter()
        .zip(&frame.views)
        .enumerate()
        .filter_map(|(c, (cam, view))| {
            view.as_ref().map(|dets| types::CameraBoxes {
                camera: cam.name.clone(),
                camera_index: c,
                boxes: dets.iter().map(|d| d.bbox).collect(),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossview_core::CameraSpec;

    #[test]
    fn a_frame_with_boxes_is_the_result_plus_the_reporting_cameras_boxes() {
        let cam = |name: &str| CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: name.into(),
            width: 640,
            height: 480,
        };
        let spec = SceneSpec {
            name: "s".into(),
            cameras: vec![cam("a"), cam("b"), cam("c")],
        };
        let det = |x: f32| Detection {
            bbox: [x, 1.0, x + 10.0, 50.0],
            score: 1.0,
            id: Some(7),
            appearance: None,
        };
        let mut frame = Frame::new(3, 3);
        frame.views[0] = Some(vec![det(0.0), det(20.0)]);
        frame.views[2] = Some(vec![]);
        let views = frame_boxes(&spec, &frame);
        let result = types::FrameResult {
            scene: "s".into(),
            frame_id: 3,
            time: None,
            complete: false,
            missing_cameras: vec!["b".into()],
            fenced_cameras: vec![],
            identities: vec![],
            latency_ms: 1.5,
            error: None,
            error_kind: None,
            status: types::ResultStatus::Associated,
            model_version: Some("v@0123456789ab".into()),
        };
        let with = types::FrameWithBoxes {
            result: result.clone(),
            views,
        };
        let mut json = serde_json::to_value(&with).unwrap();
        assert_eq!(
            json["views"],
            serde_json::json!([
                { "camera": "a", "camera_index": 0, "boxes": [[0.0, 1.0, 10.0, 50.0], [20.0, 1.0, 30.0, 50.0]] },
                { "camera": "c", "camera_index": 2, "boxes": [] },
            ])
        );
        json.as_object_mut().unwrap().remove("views");
        assert_eq!(json, serde_json::to_value(&result).unwrap());
        let back: types::FrameWithBoxes =
            serde_json::from_value(serde_json::to_value(&with).unwrap()).unwrap();
        assert_eq!(back, with);
    }
}
