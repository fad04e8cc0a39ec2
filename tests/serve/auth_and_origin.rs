//! Authentication fails closed and web pages of other origins cannot write: a blank key
//! never means "authentication off"; the bearer scheme is matched case-insensitively;
//! write routes take only JSON (or JSON Lines) bodies, so a page cannot post the "simple"
//! requests browsers send without a CORS preflight; and a state-changing request a browser
//! marks as cross-origin is refused.

use crossview_serve::ServeConfig;
use crossview_testing::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_blank_key_is_a_start_up_error_not_authentication_off() {
    for keys in [
        vec![String::new()],
        vec![" ".to_string()],
        vec!["k".into(), "".into()],
    ] {
        let dir = tempfile::tempdir().unwrap();
        let model = export_model(dir.path(), "lab");
        let config = ServeConfig {
            models: vec![crossview_serve::ModelSpec::parse(model.to_str().unwrap()).unwrap()],
            api_keys: keys.clone(),
            ..ServeConfig::default()
        };
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let r = guard(
            "start-up refused",
            crossview_serve::run(config, listener, async {}),
        )
        .await;
        let e = r.expect_err("a blank key must stop the start");
        assert!(e.to_string().contains("blank"), "{keys:?}: {e}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_bearer_scheme_is_case_insensitive() {
    let server = start(|c| c.api_keys = vec!["s3cret".into()]).await;
    let http = reqwest::Client::new();
    for (header, want) in [
        ("Bearer s3cret", 200),
        ("BEARER s3cret", 200),
        ("bearer s3cret", 200),
        ("bEaReR s3cret", 200),
        ("Basic s3cret", 401),
        ("Bearer ", 401),
        ("BEARER wrong", 401),
    ] {
        let r = http
            .get(server.url("/v1/scenes"))
            .header("authorization", header)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), want, "{header}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn write_routes_take_only_json_bodies() {
    let server = start(|_| {}).await;
    let http = reqwest::Client::new();
    for (frame, (ct, want)) in (1..).zip([
        (None, 415),
        (Some("text/plain"), 415),
        (Some("application/x-www-form-urlencoded"), 415),
        (Some("multipart/form-data; boundary=x"), 415),
        (Some("application/json"), 202),
        (Some("Application/JSON; charset=utf-8"), 202),
    ]) {
        let line = batch_json(0, frame, 1).to_string();
        let mut r = http.post(server.url("/v1/scenes/lab/batches")).body(line);
        if let Some(ct) = ct {
            r = r.header("content-type", ct);
        }
        let r = r.send().await.unwrap();
        let status = r.status();
        let body: serde_json::Value = r.json().await.unwrap();
        assert_eq!(status, want, "{ct:?}: {body}");
        if want == 415 {
            assert_eq!(body["error"]["kind"], "unsupported_media_type", "{body}");
        }
    }
    // JSON Lines still go in as JSON Lines.
    let r = http
        .post(server.url("/v1/scenes/lab/batches"))
        .header("content-type", "application/x-ndjson")
        .body(format!("{}\n", batch_json(1, 20, 1)))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let frame = serde_json::json!({"frame_id": 9, "views": [{"camera": "c0", "detections": []}]});
    let r = http
        .post(server.url("/v1/scenes/lab/associate"))
        .header("content-type", "text/plain")
        .body(frame.to_string())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 415);
    let m = server.metrics().await;
    assert!(
        metric(
            &m,
            "crossview_errors_total{kind=\"unsupported_media_type\"}"
        ) >= 5.0,
        "{m}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pages_of_other_origins_cannot_write() {
    let server = start(|_| {}).await;
    let http = reqwest::Client::new();
    let host = server.addr.to_string();
    let same = format!("http://{host}");
    for (headers, want) in [
        (vec![], 200),
        (vec![("origin", same.as_str())], 200),
        (vec![("sec-fetch-site", "same-origin")], 200),
        (vec![("origin", "http://evil.example")], 403),
        (vec![("origin", "null")], 403),
        (vec![("sec-fetch-site", "cross-site")], 403),
    ] {
        let mut r = http.post(server.url("/v1/admin/reload"));
        for (k, v) in &headers {
            r = r.header(*k, *v);
        }
        let r = r.send().await.unwrap();
        assert_eq!(r.status(), want, "{headers:?}");
    }
    // A cross-origin push is refused before it is read; reads stay open (the viewer's).
    let r = http
        .post(server.url("/v1/scenes/lab/batches"))
        .header("origin", "http://evil.example")
        .json(&batch_json(0, 1, 1))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 403);
    let r = http
        .get(server.url("/v1/scenes"))
        .header("origin", "http://evil.example")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let m = server.metrics().await;
    assert_eq!(metric(&m, "crossview_batches_total{scene=\"lab\"}"), 0.0);
}
