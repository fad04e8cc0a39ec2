//! NDJSON amplification: a hostile 4 MiB JSON Lines body costs bounded memory and gets a
//! bounded answer (the body stops early once mostly invalid), lines are processed in bounded
//! steps so `/healthz` stays responsive meanwhile, and a valid body still gets every line's
//! result.

use crossview_testing::*;

/// A 4 MiB body of `line` repeated.
fn hostile(line: &str) -> Vec<u8> {
    line.repeat((4 << 20) / line.len()).into_bytes()
}

async fn post_lines(server: &TestServer, body: Vec<u8>) -> (u16, Vec<u8>) {
    let r = reqwest::Client::new()
        .post(server.url("/v1/scenes/lab/batches"))
        .header("content-type", "application/x-ndjson")
        .body(body)
        .send()
        .await
        .unwrap();
    (r.status().as_u16(), r.bytes().await.unwrap().to_vec())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_json_lines_bodies_cost_bounded_memory_and_answer() {
    let server = start(|_| {}).await;
    let before = vm_hwm_bytes();
    // Two at once, each of the two worst shapes the probe found, with /healthz probed meanwhile.
    let a = post_lines(&server, hostile("{}\n"));
    let b = post_lines(&server, hostile("1\n"));
    let health = async {
        let r = reqwest::get(server.url("/healthz")).await.unwrap();
        assert_eq!(r.status(), 200);
    };
    let ((sa, ba), (sb, bb), ()) =
        guard("hostile bodies", async { tokio::join!(a, b, health) }).await;
    for (status, body) in [(sa, ba), (sb, bb)] {
        assert_eq!(status, 200);
        // Bounded answer: ~100 rejected lines, not 1.4 million.
        assert!(body.len() < 64 << 10, "answer of {} bytes", body.len());
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(v["accepted"], 0);
        assert_eq!(v["rejected"], 101, "{v}");
        assert!(v["stopped_at_line"].as_u64().unwrap() > 100, "{v}");
        assert!(
            v["stopped"]
                .as_str()
                .unwrap()
                .contains("--max-rejected-lines")
        );
    }
    let growth = vm_hwm_bytes().saturating_sub(before);
    assert!(growth < 512 << 20, "peak RSS grew by {} MB", growth >> 20);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_valid_recording_body_gets_every_result_streamed() {
    // Frames complete faster than inference here; do not shed them.
    let server = start(|c| c.limits.queue_capacity = 4096).await;
    // A recording: header line, then 3 cameras × 400 frames, one bad line in the middle.
    let mut body = String::from(
        "{\"scene\": {\"name\": \"lab\", \"cameras\": [{\"name\": \"c0\", \"width\": 1920, \"height\": 1080}]}}\n",
    );
    let mut n = 0;
    for f in 0..400u64 {
        for c in 0..3 {
            body.push_str(&batch_json(c, f, 2).to_string());
            body.push('\n');
            n += 1;
        }
        if f == 200 {
            body.push_str("{\"camera\": \"c0\", \"frame_id\": 9}\n");
        }
    }
    let (status, answer) = guard("recording", post_lines(&server, body.into_bytes())).await;
    assert_eq!(status, 200);
    let v: serde_json::Value = serde_json::from_slice(&answer).unwrap();
    assert_eq!(
        v["accepted"],
        n,
        "{}",
        &v["results"].as_array().unwrap().len()
    );
    assert_eq!(v["rejected"], 1);
    assert!(v.get("stopped").is_none());
    let results = v["results"].as_array().unwrap();
    assert_eq!(results.len(), n + 1);
    let bad = results.iter().find(|r| r["accepted"] == false).unwrap();
    assert_eq!(bad["error"]["kind"], "invalid_argument");
    // Line numbers count the header line.
    assert_eq!(results[0]["line"], 2);
    server.shutdown().await.unwrap();
}
