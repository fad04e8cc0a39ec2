//! Metrics cardinality: label values come from a closed set, so made-up gRPC method names
//! (authenticated or answered 401), made-up HTTP verbs and paths do not grow `/metrics`.

use crossview_testing::*;

/// Sends `n` requests with client-made names, starting at `from`.
async fn junk(server: &TestServer, from: usize, n: usize) {
    let h2 = reqwest::Client::builder()
        .http2_prior_knowledge()
        .build()
        .unwrap();
    let h1 = reqwest::Client::new();
    for i in from..from + n {
        let mut grpc = h2
            .post(server.url(&format!("/crossview.v1.Association/x{i}")))
            .header("content-type", "application/grpc")
            .header("te", "trailers");
        if i % 2 == 0 {
            grpc = grpc.header("authorization", "Bearer k");
        }
        let r = grpc.body(Vec::new()).send().await.unwrap();
        assert_eq!(r.status(), 200);
        let verb = reqwest::Method::from_bytes(format!("FOO{i}").as_bytes()).unwrap();
        h1.request(verb, server.url("/healthz"))
            .send()
            .await
            .unwrap();
        h1.get(server.url(&format!("/nowhere/{i}")))
            .send()
            .await
            .unwrap();
    }
}

/// The metric series (name and labels, without values) of `/metrics`, sorted.
async fn series(server: &TestServer) -> std::collections::BTreeSet<String> {
    server
        .metrics()
        .await
        .lines()
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(|l| l.rsplit_once(' ').map_or(l, |(k, _)| k).to_string())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn made_up_names_do_not_grow_metrics() {
    let server = start(|c| c.api_keys = vec!["k".into()]).await;
    junk(&server, 0, 10).await;
    // The first scrape adds its own series (GET /metrics); count from the second.
    series(&server).await;
    let before = series(&server).await;
    junk(&server, 10, 1000).await;
    let after = series(&server).await;
    assert_eq!(before, after, "new series appeared");
    let text = server.metrics().await;
    assert!(text.contains("method=\"other\""), "{text}");
    assert!(!text.contains("x12"), "a client-made name became a label");
    assert!(!text.contains("FOO"), "a client-made verb became a label");
    server.shutdown().await.unwrap();
}
