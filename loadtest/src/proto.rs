//! The server's gRPC API (`crossview.v1`), compiled from `proto/` by `build.rs`, and the
//! conversion from the recording's batch type.
#![allow(clippy::all, missing_docs)]

tonic::include_proto!("crossview.v1");

/// A recording batch as the protobuf message for scene `scene`.
pub fn batch_to_proto(scene: &str, b: &crossview::core::Batch) -> Batch {
    Batch {
        scene: scene.to_string(),
        camera: b.camera.clone(),
        frame_id: b.frame_id,
        detections: b
            .detections
            .iter()
            .map(|d| Detection {
                bbox: Some(BoundingBox {
                    x1: d.bbox[0],
                    y1: d.bbox[1],
                    x2: d.bbox[2],
                    y2: d.bbox[3],
                }),
                score: Some(d.score),
                appearance: d.appearance.clone().unwrap_or_default(),
            })
            .collect(),
    }
}
