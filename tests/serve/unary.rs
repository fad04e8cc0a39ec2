//! Unary association over gRPC and HTTP against a real server with a real exported ONNX model:
//! both transports give the same identities; scene listing, health and metrics answer.

use crossview_api::pb;
use crossview_testing::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unary_association_over_grpc_and_http() {
    let server = start(|_| {}).await;
    let mut client = server.grpc().await;

    let sizes = [3usize, 2, 0];
    let req = pb::AssociateRequest {
        scene: "lab".into(),
        frame_id: 42,
        time: None,
        views: (0..3)
            .map(|c| pb::CameraView {
                camera: CAMERAS[c].into(),
                detections: dets(c, 42, sizes[c]),
            })
            .collect(),
    };
    let g = guard("gRPC Associate", client.associate(req))
        .await
        .expect("Associate")
        .into_inner();
    assert_eq!(g.scene, "lab");
    assert_eq!(g.frame_id, 42);
    assert!(g.complete);
    assert!(g.missing_cameras.is_empty());
    assert!(g.error.is_empty());
    assert!(g.latency_ms >= 0.0);
    check_identities(&g, &sizes);
    // Every box is accounted for by some identity (singletons included).
    let members: usize = g.identities.iter().map(|i| i.members.len()).sum();
    assert_eq!(members, sizes.iter().sum::<usize>());

    // The same frame over HTTP JSON: same identities.
    let body = serde_json::json!({
        "frame_id": 42,
        "views": (0..3).map(|c| {
            let mut b = batch_json(c, 42, sizes[c]);
            b.as_object_mut().unwrap().remove("frame_id");
            b
        }).collect::<Vec<_>>(),
    });
    let http = reqwest::Client::new();
    let resp = guard(
        "HTTP associate",
        http.post(server.url("/v1/scenes/lab/associate"))
            .json(&body)
            .send(),
    )
    .await
    .unwrap();
    assert_eq!(resp.status(), 200);
    let h: serde_json::Value = resp.json().await.unwrap();
    assert_eq!(h["frame_id"], 42);
    assert_eq!(h["complete"], true);
    let h_ids = h["identities"].as_array().unwrap();
    assert_eq!(h_ids.len(), g.identities.len());
    for (a, b) in g.identities.iter().zip(h_ids) {
        let hm: Vec<(String, u64)> = b["members"]
            .as_array()
            .unwrap()
            .iter()
            .map(|m| {
                (
                    m["camera"].as_str().unwrap().to_string(),
                    m["index"].as_u64().unwrap(),
                )
            })
            .collect();
        let gm: Vec<(String, u64)> = a
            .members
            .iter()
            .map(|m| (m.camera.clone(), m.index as u64))
            .collect();
        assert_eq!(gm, hm);
        assert!((a.confidence as f64 - b["confidence"].as_f64().unwrap()).abs() < 1e-5);
    }

    // A partial unary frame names its missing camera.
    let partial = client
        .associate(pb::AssociateRequest {
            scene: "lab".into(),
            frame_id: 43,
            time: None,
            views: vec![pb::CameraView {
                camera: "c1".into(),
                detections: dets(1, 43, 2),
            }],
        })
        .await
        .unwrap()
        .into_inner();
    assert!(!partial.complete);
    assert_eq!(partial.missing_cameras, vec!["c0", "c2"]);

    // Scenes over both transports.
    let scenes = client
        .list_scenes(pb::ListScenesRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(scenes.scenes.len(), 1);
    let s = client
        .get_scene(pb::GetSceneRequest {
            scene: "lab".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(s.cameras.len(), 3);
    assert_eq!(s.cameras[1].width, 1280);
    // The metadata's version and the file's content hash: `test-1@` + 12 hex digits.
    let hash = s
        .model_version
        .strip_prefix("test-1@")
        .expect("VERSION@HASH");
    assert!(
        hash.len() == 12 && hash.chars().all(|c| c.is_ascii_hexdigit()),
        "{}",
        s.model_version
    );
    assert!((s.threshold - 0.1).abs() < 1e-6);
    let list: serde_json::Value = http
        .get(server.url("/v1/scenes"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(list["scenes"][0]["name"], "lab");
    let one: serde_json::Value = http
        .get(server.url("/v1/scenes/lab"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(one["cameras"][2]["height"], 480);

    // Health: HTTP and grpc.health.v1.
    assert_eq!(
        http.get(server.url("/healthz"))
            .send()
            .await
            .unwrap()
            .status(),
        200
    );
    let ch = tonic::transport::Channel::from_shared(server.url(""))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(ch);
    let st = health
        .check(tonic_health::pb::HealthCheckRequest {
            service: "crossview.v1.Association".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        st.status,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );

    // Server reflection lists the service (what grpcurl uses).
    {
        use tonic_reflection::pb::v1::ServerReflectionRequest;
        use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
        use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
        use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
        let ch = tonic::transport::Channel::from_shared(server.url(""))
            .unwrap()
            .connect()
            .await
            .unwrap();
        let req = ServerReflectionRequest {
            host: String::new(),
            message_request: Some(MessageRequest::ListServices(String::new())),
        };
        let mut answers = ServerReflectionClient::new(ch)
            .server_reflection_info(futures::stream::iter(vec![req]))
            .await
            .unwrap()
            .into_inner();
        let answer = guard("reflection", answers.message())
            .await
            .unwrap()
            .unwrap();
        let Some(MessageResponse::ListServicesResponse(list)) = answer.message_response else {
            panic!("unexpected reflection answer {answer:?}");
        };
        let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
        assert!(
            names.contains(&"crossview.v1.Association".to_string()),
            "{names:?}"
        );
    }

    // Metrics count the requests of both transports.
    let m = server.metrics().await;
    assert!(
        metric(
            &m,
            "crossview_requests_total{transport=\"grpc\",method=\"/crossview.v1.Association/Associate\",status=\"0\"}"
        ) >= 2.0,
        "{m}"
    );
    assert!(
        m.contains("crossview_requests_total{transport=\"http\""),
        "{m}"
    );
    assert!(m.contains("crossview_inference_seconds_bucket"), "{m}");
    server.shutdown().await.unwrap();
}
