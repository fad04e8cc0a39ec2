//! Bad inputs get the right status on both transports, with the field named: NaN box,
//! inverted box, unknown camera or scene, oversized body, wrong appearance length, too many
//! detections, malformed JSON, and missing or wrong bearer tokens.

use crossview_api::pb;
use crossview_testing::*;
use futures::StreamExt;
use tonic::Code;

async fn push_one(
    client: &mut pb::association_client::AssociationClient<tonic::transport::Channel>,
    b: pb::Batch,
) -> pb::BatchAck {
    let mut acks = client
        .push(futures::stream::iter(vec![b]))
        .await
        .unwrap()
        .into_inner();
    guard("ack", acks.next()).await.unwrap().unwrap()
}

/// The error of a unary `Associate` of frame 1 of scene `lab` with `detections` from camera
/// `c0` alone.
async fn associate_error(
    client: &mut pb::association_client::AssociationClient<tonic::transport::Channel>,
    detections: Vec<pb::Detection>,
) -> tonic::Status {
    client
        .associate(pb::AssociateRequest {
            scene: "lab".into(),
            frame_id: 1,
            time: None,
            views: vec![pb::CameraView {
                camera: "c0".into(),
                detections,
            }],
        })
        .await
        .unwrap_err()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_inputs_get_the_right_status() {
    let server = start(|c| {
        c.limits.max_request_bytes = 64 * 1024;
        c.limits.max_detections = 50;
    })
    .await;
    let mut client = server.grpc().await;
    let http = reqwest::Client::new();
    let batches = server.url("/v1/scenes/lab/batches");

    // NaN box: gRPC can carry it; JSON cannot, so over HTTP the body itself is invalid.
    let mut b = batch(0, 1, 1);
    b.detections[0].bbox.as_mut().unwrap().x1 = f32::NAN;
    let ack = push_one(&mut client, b).await;
    assert_eq!(ack.code, Code::InvalidArgument as i32, "{ack:?}");
    assert!(ack.message.contains("detections[0].bbox"), "{ack:?}");
    let r = http
        .post(&batches)
        .header("content-type", "application/json")
        .body(r#"{"camera":"c0","frame_id":1,"detections":[{"bbox":[NaN,1,2,3]}]}"#)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 422);
    let body: serde_json::Value = r.json().await.unwrap();
    assert_eq!(body["error"]["field"], "body");

    // Inverted box.
    let mut b = batch(0, 1, 2);
    let bb = b.detections[1].bbox.as_mut().unwrap();
    std::mem::swap(&mut bb.x1, &mut bb.x2);
    let ack = push_one(&mut client, b).await;
    assert_eq!(ack.code, Code::InvalidArgument as i32);
    assert!(ack.message.contains("detections[1].bbox"), "{ack:?}");
    let (status, body) = server
        .post_json(
            "/v1/scenes/lab/batches",
            &serde_json::json!({"camera":"c0","frame_id":1,"detections":[{"bbox":[10,10,5,20]}]}),
        )
        .await;
    assert_eq!(status, 422);
    assert_eq!(body["error"]["field"], "detections[0].bbox");

    // Missing box in protobuf.
    let mut b = batch(0, 1, 1);
    b.detections[0].bbox = None;
    assert_eq!(
        push_one(&mut client, b).await.code,
        Code::InvalidArgument as i32
    );

    // Unknown camera / scene.
    let mut b = batch(0, 1, 1);
    b.camera = "nope".into();
    assert_eq!(push_one(&mut client, b).await.code, Code::NotFound as i32);
    let mut b = batch(0, 1, 1);
    b.scene = "nowhere".into();
    assert_eq!(push_one(&mut client, b).await.code, Code::NotFound as i32);
    let (status, _) = server
        .post_json(
            "/v1/scenes/lab/batches",
            &serde_json::json!({"camera":"nope","frame_id":1,"detections":[]}),
        )
        .await;
    assert_eq!(status, 404);
    let r = http
        .get(server.url("/v1/scenes/nowhere"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 404);
    let e = client
        .get_scene(pb::GetSceneRequest {
            scene: "nowhere".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    // The error's kind travels as status metadata (as `error.kind` over HTTP), and for a bad
    // argument its field too.
    let meta = |e: &tonic::Status, key: &str| {
        e.metadata()
            .get(key)
            .map(|v| v.to_str().unwrap().to_string())
    };
    assert_eq!(
        meta(&e, "crossview-error-kind").as_deref(),
        Some("unknown_scene")
    );
    assert_eq!(meta(&e, "crossview-error-field"), None);
    let mut inverted = batch(0, 1, 1);
    inverted.detections[0].bbox = Some(pb::BoundingBox {
        x1: 50.0,
        y1: 50.0,
        x2: 10.0,
        y2: 10.0,
    });
    let e = associate_error(&mut client, inverted.detections).await;
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert_eq!(
        meta(&e, "crossview-error-kind").as_deref(),
        Some("invalid_argument")
    );
    let field = meta(&e, "crossview-error-field").expect("the field of a bad argument");
    assert!(field.contains("bbox"), "{field} / {}", e.message());

    // Oversized body: 413 over HTTP; over gRPC the message-size limit refuses it.
    let big = serde_json::json!({
        "camera": "c0", "frame_id": 1,
        "detections": vec![serde_json::json!({"bbox": [1.0, 2.0, 3.0, 4.0], "appearance": vec![0.5f32; 512]}); 40],
    });
    let (status, _) = server.post_json("/v1/scenes/lab/batches", &big).await;
    assert_eq!(status, 413);
    let mut b = batch(0, 1, 40);
    for d in &mut b.detections {
        d.appearance = vec![0.5; 512];
    }
    let e = associate_error(&mut client, b.detections).await;
    assert_eq!(e.code(), Code::OutOfRange, "{e:?}");

    // Too many detections in one batch.
    let ack = push_one(&mut client, batch(0, 1, 51)).await;
    assert_eq!(ack.code, Code::InvalidArgument as i32);
    assert!(ack.message.contains("detections"), "{ack:?}");

    // Appearance length: the first vector fixes it for the scene.
    let mut b = batch(0, 2, 2);
    for d in &mut b.detections {
        d.appearance = vec![0.1, 0.2, 0.3, 0.4];
    }
    assert_eq!(push_one(&mut client, b).await.code, 0);
    let mut b = batch(1, 2, 1);
    b.detections[0].appearance = vec![0.1; 5];
    let ack = push_one(&mut client, b).await;
    assert_eq!(ack.code, Code::InvalidArgument as i32);
    assert!(ack.message.contains("appearance"), "{ack:?}");
    let b = serde_json::json!({"camera":"c2","frame_id":2,"detections":[{"bbox":[1,2,3,4],"appearance":[1,2,3]}]});
    let (status, body) = server.post_json("/v1/scenes/lab/batches", &b).await;
    assert_eq!(status, 422);
    assert_eq!(body["error"]["field"], "detections[0].appearance");

    // Malformed JSON and a wrong type.
    let r = http
        .post(&batches)
        .body("{not json")
        .header("content-type", "application/json")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 422);
    let (status, _) = server
        .post_json(
            "/v1/scenes/lab/associate",
            &serde_json::json!({"frame_id": -1, "views": []}),
        )
        .await;
    assert_eq!(status, 422);

    let m = server.metrics().await;
    assert!(
        metric(&m, "crossview_errors_total{kind=\"invalid_argument\"}") >= 8.0,
        "{m}"
    );
    assert!(
        metric(&m, "crossview_errors_total{kind=\"unknown_camera\"}") >= 2.0,
        "{m}"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bearer_token_is_required_except_for_health_and_metrics() {
    let server = start(|c| c.api_keys = vec!["s3cret".into(), "other".into()]).await;
    let http = reqwest::Client::new();

    let r = http.get(server.url("/v1/scenes")).send().await.unwrap();
    assert_eq!(r.status(), 401);
    let r = http
        .get(server.url("/v1/scenes"))
        .bearer_auth("wrong")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 401);
    let r = http
        .get(server.url("/v1/scenes"))
        .bearer_auth("other")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let (status, _) = server
        .post_json("/v1/scenes/lab/batches", &batch_json(0, 1, 1))
        .await;
    assert_eq!(status, 401);
    for open in ["/healthz", "/readyz", "/metrics"] {
        assert_eq!(
            http.get(server.url(open)).send().await.unwrap().status(),
            200,
            "{open}"
        );
    }

    let mut client = server.grpc().await;
    let e = client
        .list_scenes(pb::ListScenesRequest {})
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated);
    let mut req = tonic::Request::new(pb::ListScenesRequest {});
    req.metadata_mut()
        .insert("authorization", "Bearer bad".parse().unwrap());
    assert_eq!(
        client.list_scenes(req).await.unwrap_err().code(),
        Code::Unauthenticated
    );
    let mut req = tonic::Request::new(pb::ListScenesRequest {});
    req.metadata_mut()
        .insert("authorization", "Bearer s3cret".parse().unwrap());
    assert_eq!(
        client
            .list_scenes(req)
            .await
            .unwrap()
            .into_inner()
            .scenes
            .len(),
        1
    );

    // gRPC health is exempt.
    let ch = tonic::transport::Channel::from_shared(server.url(""))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(ch);
    assert!(
        health
            .check(tonic_health::pb::HealthCheckRequest {
                service: String::new()
            })
            .await
            .is_ok()
    );

    let m = server.metrics().await;
    assert!(
        metric(&m, "crossview_errors_total{kind=\"unauthenticated\"}") >= 5.0,
        "{m}"
    );
    server.shutdown().await.unwrap();
}

/// With no room in the inference queue, work is shed: RESOURCE_EXHAUSTED over gRPC, 429 over
/// HTTP, and nothing is accepted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_queue_sheds_load() {
    let server = start(|c| c.limits.queue_capacity = 0).await;
    let mut client = server.grpc().await;
    let ack = push_one(&mut client, batch(0, 1, 1)).await;
    assert_eq!(ack.code, Code::ResourceExhausted as i32, "{ack:?}");
    let e = client
        .associate(pb::AssociateRequest {
            scene: "lab".into(),
            frame_id: 1,
            time: None,
            views: vec![],
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted);
    let (status, _) = server
        .post_json("/v1/scenes/lab/batches", &batch_json(0, 1, 1))
        .await;
    assert_eq!(status, 429);
    let m = server.metrics().await;
    assert_eq!(metric(&m, "crossview_batches_total{scene=\"lab\"}"), 0.0);
    assert_eq!(
        metric(&m, "crossview_errors_total{kind=\"resource_exhausted\"}"),
        3.0,
        "{m}"
    );
    server.shutdown().await.unwrap();
}
