//! Fuzzing (proptest) of the service's input path: arbitrary bytes and arbitrary JSON/protobuf
//! values go through decoding, validation, the synchronizer and association (real exported
//! model, real ONNX Runtime). Nothing may panic or hang; every outcome is a value or a typed
//! error of an expected kind.

use std::sync::{Arc, OnceLock};
use std::time::Duration;

use crossview_api::convert as grpc;
use crossview_api::pb;
use crossview_api::types::AssociateRequest;
use crossview_core::Batch;
use crossview_core::Encoder;
use crossview_core::Error as CoreError;
use crossview_model::OnnxEncoder;
use crossview_serve::{Error, ServeConfig, Server, Service, registry};
use proptest::prelude::*;
use prost::Message;

struct Env {
    rt: tokio::runtime::Runtime,
    service: Arc<Service>,
    _server: Server,
    _dir: tempfile::TempDir,
}

fn env() -> &'static Env {
    static ENV: OnceLock<Env> = OnceLock::new();
    ENV.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let path = crossview_testing::export_model(dir.path(), "lab");
        let config = ServeConfig {
            sync_timeout: Duration::from_millis(5),
            ..ServeConfig::default()
        };
        let encoder = OnnxEncoder::load(&path).unwrap();
        let version = encoder.metadata().version.clone();
        let info =
            registry::scene_info("lab", encoder.metadata(), version, &config.limits).unwrap();
        let scenes: Vec<(_, Box<dyn Encoder>)> = vec![(info, Box::new(encoder))];
        let server = Server::from_scenes(config, scenes).unwrap();
        Env {
            rt: tokio::runtime::Runtime::new().unwrap(),
            service: server.service().clone(),
            _server: server,
            _dir: dir,
        }
    })
}

/// Only these error kinds are acceptable answers to bad input.
fn expected(e: &Error) -> bool {
    matches!(
        e,
        Error::Core(
            CoreError::InvalidArgument { .. }
                | CoreError::UnknownScene(_)
                | CoreError::UnknownCamera { .. }
                | CoreError::DuplicateBatch { .. }
        ) | Error::LateBatch { .. }
            | Error::FrameOutOfRange { .. }
            | Error::ResourceExhausted(_)
    )
}

fn push(scene: &str, b: Batch) {
    if let Err(e) = env().service.push(scene, b) {
        assert!(expected(&e), "unexpected error {e:?}");
    }
}

fn associate(scene: &str, r: AssociateRequest) {
    let e = env();
    let out = e.rt.block_on(async {
        tokio::time::timeout(crossview_testing::HANG_GUARD, e.service.associate(scene, r))
            .await
            .expect("hang guard: associate")
    });
    match out {
        Ok(res) => {
            for id in &res.identities {
                assert!(id.confidence.is_finite(), "{res:?}");
            }
        }
        Err(e) => assert!(expected(&e), "unexpected error {e:?}"),
    }
}

fn any_f32() -> impl Strategy<Value = f32> {
    prop_oneof![
        4 => 0.0f32..2000.0,
        1 => any::<f32>(),
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => Just(-1.0f32),
        1 => Just(1e30f32),
    ]
}

fn detection() -> impl Strategy<Value = pb::Detection> {
    (
        proptest::array::uniform4(any_f32()),
        proptest::option::of(any_f32()),
        prop_oneof![Just(vec![]), proptest::collection::vec(any_f32(), 0..6)],
    )
        .prop_map(|(b, score, appearance)| pb::Detection {
            bbox: Some(pb::BoundingBox {
                x1: b[0],
                y1: b[1],
                x2: b[0] + b[2],
                y2: b[1] + b[3],
            }),
            score,
            appearance,
        })
}

fn camera() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("c0".to_string()),
        Just("c1".to_string()),
        Just("c2".to_string()),
        "[a-z0-9]{0,4}"
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        if let Ok(b) = serde_json::from_slice::<Batch>(&bytes) {
            push("lab", b);
        }
        if let Ok(r) = serde_json::from_slice::<AssociateRequest>(&bytes) {
            associate("lab", r);
        }
        if let Ok(b) = pb::Batch::decode(bytes.as_slice())
            && let Ok((scene, b)) = grpc::batch_from_pb(b)
        {
            push(&scene, b);
        }
        if let Ok(r) = pb::AssociateRequest::decode(bytes.as_slice())
            && let Ok((scene, r)) = grpc::associate_from_pb(r)
        {
            associate(&scene, r);
        }
    }

    #[test]
    fn arbitrary_batches_and_frames_never_panic(
        frame_id in 0u64..50,
        cams in proptest::collection::vec((camera(), proptest::collection::vec(detection(), 0..8)), 0..4),
    ) {
        // As protobuf, through the gRPC conversions.
        for (cam, dets) in &cams {
            let b = pb::Batch { scene: "lab".into(), camera: cam.clone(), frame_id, time: None, detections: dets.clone() };
            if let Ok((scene, b)) = grpc::batch_from_pb(b) {
                // And the same batch as JSON text, through the HTTP decoding.
                let json = serde_json::to_vec(&b).unwrap();
                if let Ok(b2) = serde_json::from_slice::<Batch>(&json) {
                    push(&scene, b2);
                }
                push(&scene, b);
            }
        }
        let req = pb::AssociateRequest {
            scene: "lab".into(),
            frame_id,
            time: None,
            views: cams.into_iter().map(|(camera, detections)| pb::CameraView { camera, detections }).collect(),
        };
        if let Ok((scene, r)) = grpc::associate_from_pb(req) {
            associate(&scene, r);
        }
    }
}
