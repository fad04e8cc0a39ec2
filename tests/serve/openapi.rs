//! The OpenAPI 3.1 description of the HTTP API: the server serves it at `/openapi.json`,
//! behind the API key like every route but health, readiness and metrics; `crossview openapi`
//! prints the same document; and `docs/openapi.json` is a copy of it that must stay equal
//! (regenerate it with `cargo run -q -- openapi > docs/openapi.json`).

use crossview_testing::*;

const KEY: &str = "openapi-key";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_committed_description_is_what_the_server_serves() {
    let server = start(|c| c.api_keys = vec![KEY.into()]).await;
    let http = reqwest::Client::new();
    let url = server.url("/openapi.json");

    let anonymous = http.get(&url).send().await.unwrap();
    assert_eq!(anonymous.status(), 401, "/openapi.json without the key");
    let body: serde_json::Value = anonymous.json().await.unwrap();
    assert_eq!(body["error"]["kind"], "unauthenticated");

    let r = http.get(&url).bearer_auth(KEY).send().await.unwrap();
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "application/json");
    let served = r.text().await.unwrap();
    let doc: serde_json::Value = serde_json::from_str(&served).expect("the document is JSON");
    assert_eq!(doc["openapi"], "3.1.0");
    for path in [
        "/healthz",
        "/readyz",
        "/metrics",
        "/openapi.json",
        "/v1/scenes",
        "/v1/scenes/{scene}",
        "/v1/scenes/{scene}/associate",
        "/v1/scenes/{scene}/batches",
        "/v1/scenes/{scene}/events",
        "/v1/admin/reload",
    ] {
        assert!(doc["paths"][path].is_object(), "{path} is not described");
    }

    let printed = run_crossview(env!("CARGO_BIN_EXE_crossview"), &["openapi"], &[]);
    assert_eq!(
        printed.trim_end(),
        served,
        "`crossview openapi` prints another document than the server serves"
    );
    let committed_path = repo_root().join("docs/openapi.json");
    let committed = std::fs::read_to_string(&committed_path).unwrap_or_default();
    assert!(
        committed.trim_end() == served,
        "{} is not the description the server serves (the HTTP API or its types changed); \
         regenerate it with `cargo run -q -- openapi > docs/openapi.json` and commit it",
        committed_path.display()
    );
    server.shutdown().await.unwrap();
}
