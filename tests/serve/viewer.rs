//! The live viewer at `/`, in a real headless Chromium (DevTools over a pipe,
//! `crossview_testing::browser`) against the real server on 127.0.0.1:0 with the shipped
//! `models/demo.onnx` (4 cameras) while simulated `square4` frames are pushed over HTTP: the
//! page loads from the server, lays out one canvas per camera at the camera's aspect ratio,
//! receives the frames and draws every pushed box of the latest frame (its DOM counters match
//! what was pushed, and the canvases hold coloured pixels). Behind `--api-key` the page asks
//! for the key and shows no data until it has it, and the key never appears in a URL.
//! `?boxes=true` on the events route adds each camera's boxes and changes nothing else.
//!
//! `CROSSVIEW_VIEWER_SCREENSHOT=docs/viewer.png cargo test --test serve viewer` also saves a
//! 1400×900 screenshot of the live page (the one in the README).
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crossview_data::sim::SimConfig;
use crossview_serve::ServeConfig;
use crossview_testing::browser::Browser;
use crossview_testing::*;
use futures::StreamExt;
use serde_json::Value;
use tokio::sync::watch;

const WIDTH: u32 = 1400;
const HEIGHT: u32 = 900;
const KEY: &str = "viewer-s3cret-key";

/// A sync timeout no loaded machine reaches between a frame's four batches (a frame leaves
/// as soon as all four arrived, so this slows nothing down).
fn patient(c: &mut ServeConfig) {
    c.sync_timeout = Duration::from_secs(30);
}

/// Pushes simulated `square4` frames (ground-truth ids stripped) to scene `demo` over HTTP,
/// one frame every 40 ms, until stopped; remembers each frame's box count per camera.
struct Pusher {
    stop: watch::Sender<bool>,
    task: tokio::task::JoinHandle<u64>,
    pushed: Arc<Mutex<BTreeMap<u64, Vec<usize>>>>,
}

impl Pusher {
    fn start(server: &TestServer, key: Option<&str>) -> Pusher {
        let url = server.url("/v1/scenes/demo/batches");
        let key = key.map(str::to_string);
        let (stop, mut stopped) = watch::channel(false);
        let pushed = Arc::new(Mutex::new(BTreeMap::new()));
        let seen = pushed.clone();
        let task = tokio::spawn(async move {
            let mut cfg = SimConfig::preset("square4").unwrap();
            cfg.frames = 100_000;
            cfg.seed = 3;
            cfg.ids = false;
            let mut sim = crossview_data::sim::Simulator::new(&cfg).unwrap();
            let cameras: Vec<String> = sim.scene().cameras.iter().map(|c| c.name.clone()).collect();
            let http = reqwest::Client::new();
            let mut last = 0;
            while !*stopped.borrow() {
                let frame = sim.next_frame().expect("frames left");
                let mut counts = Vec::new();
                for (camera, view) in cameras.iter().zip(&frame.views) {
                    let dets = view.as_deref().unwrap_or_default();
                    counts.push(dets.len());
                    let batch = crossview_core::Batch {
                        camera: camera.clone(),
                        frame_id: frame.frame_id,
                        time: None,
                        detections: dets.to_vec(),
                    };
                    let mut req = http.post(&url).json(&batch);
                    if let Some(k) = &key {
                        req = req.bearer_auth(k);
                    }
                    let r = req.send().await.unwrap();
                    assert_eq!(r.status(), 202, "{}", r.text().await.unwrap());
                }
                seen.lock().unwrap().insert(frame.frame_id, counts);
                last = frame.frame_id;
                tokio::select! {
                    _ = tokio::time::sleep(Duration::from_millis(40)) => {}
                    _ = stopped.changed() => {}
                }
            }
            last
        });
        Pusher { stop, task, pushed }
    }

    /// Stops pushing; returns the last frame id pushed.
    async fn stop(self) -> (u64, BTreeMap<u64, Vec<usize>>) {
        let _ = self.stop.send(true);
        let last = guard("the pusher to stop", self.task).await.unwrap();
        let pushed = self.pushed.lock().unwrap().clone();
        (last, pushed)
    }
}

/// Per panel: camera, canvas size, frames drawn, last frame, boxes drawn, matched, unmatched,
/// and the canvas's pixels that are not background (`ink`) and that are coloured (`colour`).
const PANELS: &str = r#"[...document.querySelectorAll('.panel')].map((p) => {
  const c = p.querySelector('canvas');
  const px = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let ink = 0, colour = 0;
  for (let i = 0; i < px.length; i += 4) {
    const [r, g, b] = [px[i], px[i + 1], px[i + 2]];
    if (Math.abs(r - 0x15) + Math.abs(g - 0x18) + Math.abs(b - 0x1c) > 30) ink++;
    if (Math.max(r, g, b) - Math.min(r, g, b) > 60) colour++;
  }
  return { camera: p.dataset.camera, width: c.width, height: c.height,
           frames: +p.dataset.frames, last: p.dataset.lastFrame === undefined ? null : +p.dataset.lastFrame,
           drawn: +p.dataset.boxesDrawn, matched: +p.dataset.matched, unmatched: +p.dataset.unmatched,
           ink, colour };
})"#;

async fn scene_cameras(server: &TestServer, key: Option<&str>) -> Vec<(String, u32, u32)> {
    let mut req = reqwest::Client::new().get(server.url("/v1/scenes/demo"));
    if let Some(k) = key {
        req = req.bearer_auth(k);
    }
    let scene: Value = req.send().await.unwrap().json().await.unwrap();
    scene["cameras"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let n = |k: &str| c[k].as_u64().unwrap() as u32;
            (
                c["name"].as_str().unwrap().to_string(),
                n("width"),
                n("height"),
            )
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_viewer_draws_the_live_frames_of_the_real_server() {
    let server = start_with(demo_model(), |c| {
        patient(c);
        // A clock estimate within the test's few seconds of frames.
        c.limits.clock_watch.window = 40;
        c.limits.clock_watch.interval = Duration::ZERO;
    })
    .await;
    // The page and its assets, with their security headers.
    for (path, kind) in [
        ("/", "text/html"),
        ("/viewer.js", "text/javascript"),
        ("/viewer.css", "text/css"),
    ] {
        let r = reqwest::get(server.url(path)).await.unwrap();
        assert_eq!(r.status(), 200, "{path}");
        let h = r.headers();
        assert!(
            h["content-type"].to_str().unwrap().starts_with(kind),
            "{path}"
        );
        let csp = h["content-security-policy"].to_str().unwrap();
        assert!(csp.contains("default-src 'self'"), "{path}: {csp}");
    }
    let cameras = scene_cameras(&server, None).await;
    assert_eq!(cameras.len(), 4);

    let Some(mut browser) = Browser::launch(WIDTH, HEIGHT).await else {
        return;
    };
    browser.open(&server.url("/"), WIDTH, HEIGHT).await;
    browser
        .wait_for(
            "the page to subscribe",
            "document.body.dataset.state === 'live'",
        )
        .await;
    // One canvas per camera, in scene order, at the camera's aspect ratio.
    let panels = browser.eval(PANELS).await;
    let panels = panels.as_array().unwrap();
    assert_eq!(panels.len(), cameras.len(), "{panels:?}");
    for (p, (name, w, h)) in panels.iter().zip(&cameras) {
        assert_eq!(p["camera"], name.as_str());
        let (cw, ch) = (p["width"].as_f64().unwrap(), p["height"].as_f64().unwrap());
        let aspect = f64::from(*w) / f64::from(*h);
        assert!((cw / ch - aspect).abs() < 0.01 * aspect, "{p} vs {w}x{h}");
        assert_eq!(p["frames"], 0);
    }

    // Frames pushed while the page is open arrive and are drawn.
    let pusher = Pusher::start(&server, None);
    browser
        .wait_for(
            "five frames drawn in every panel",
            "[...document.querySelectorAll('.panel')].every((p) => +p.dataset.frames >= 5)",
        )
        .await;
    // Each camera's live clock estimate shows next to its name (while frames still arrive).
    let clocks = browser
        .wait_for(
            "the clock estimate in every panel",
            "(() => { const ps = [...document.querySelectorAll('.panel')]; \
               return ps.every((p) => p.dataset.clock !== 'none') && \
                 ps.map((p) => [p.dataset.clock, p.querySelector('.clock').textContent]); })()",
        )
        .await;
    for c in clocks.as_array().unwrap() {
        let state = c[0].as_str().unwrap();
        assert!(["unknown", "in-sync", "off"].contains(&state), "{clocks}");
        assert!(c[1].as_str().unwrap().starts_with("clock"), "{clocks}");
    }
    // And whether it still fits the model, from the same poll.
    let fits = browser
        .wait_for(
            "the camera fit in every panel",
            "(() => { const ps = [...document.querySelectorAll('.panel')]; \
               return ps.every((p) => p.dataset.fit !== 'none') && \
                 ps.map((p) => p.dataset.fit); })()",
        )
        .await;
    for state in fits.as_array().unwrap() {
        let state = state.as_str().unwrap();
        assert!(
            ["fits", "drifting", "does_not_fit", "silent", "unknown"].contains(&state),
            "{fits}"
        );
    }
    if let Some(path) = std::env::var_os("CROSSVIEW_VIEWER_SCREENSHOT") {
        // A few seconds of frames, so the rate has a full window.
        browser
            .wait_for(
                "frames for the screenshot",
                "+document.getElementById('status').dataset.frames >= 150",
            )
            .await;
        browser.screenshot(std::path::Path::new(&path)).await;
    }
    let (last, pushed) = pusher.stop().await;
    // The page ends on the last frame pushed, with exactly its boxes.
    browser
        .wait_for(
            "the last frame to be drawn",
            &format!(
                "[...document.querySelectorAll('.panel')].every((p) => p.dataset.lastFrame === '{last}')"
            ),
        )
        .await;
    let panels = browser.eval(PANELS).await;
    let panels = panels.as_array().unwrap();
    let counts = &pushed[&last];
    let mut matched = 0;
    for (c, p) in panels.iter().enumerate() {
        assert_eq!(p["drawn"].as_u64().unwrap() as usize, counts[c], "{p}");
        assert_eq!(
            p["matched"].as_u64().unwrap() + p["unmatched"].as_u64().unwrap(),
            p["drawn"].as_u64().unwrap(),
            "{p}"
        );
        if counts[c] > 0 {
            assert!(
                p["ink"].as_u64().unwrap() > 0,
                "boxes drawn but no ink: {p}"
            );
        }
        if p["matched"].as_u64().unwrap() > 0 {
            assert!(
                p["colour"].as_u64().unwrap() > 0,
                "matched boxes are coloured: {p}"
            );
        }
        matched += p["matched"].as_u64().unwrap();
    }
    assert!(
        matched > 0,
        "the demo model matches people across cameras: {panels:?}"
    );
    let status = browser
        .eval(
            "({ frames: +document.getElementById('status').dataset.frames, \
                frame: document.getElementById('frame-id').textContent, \
                state: document.getElementById('frame-state').textContent, \
                latency: document.getElementById('latency').textContent, \
                model: document.getElementById('model').textContent, \
                rate: document.getElementById('rate').textContent })",
        )
        .await;
    assert!(status["frames"].as_u64().unwrap() >= 5, "{status}");
    assert_eq!(status["frame"], last.to_string(), "{status}");
    assert_eq!(status["state"], "complete", "{status}");
    assert!(
        status["latency"].as_str().unwrap().ends_with(" ms"),
        "{status}"
    );
    assert!(
        status["rate"].as_str().unwrap().contains("frames/s"),
        "{status}"
    );
    // The version of the model that produced the frame, `crossview.version@hash`.
    assert!(status["model"].as_str().unwrap().contains('@'), "{status}");
    browser.close().await;
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn behind_an_api_key_the_viewer_asks_for_it_and_shows_nothing_without_it() {
    let server = start_with(demo_model(), |c| {
        patient(c);
        c.api_keys = vec![KEY.into()];
    })
    .await;
    // The page needs no key, the data does.
    let r = reqwest::get(server.url("/")).await.unwrap();
    assert_eq!(r.status(), 200);
    for path in [
        "/v1/scenes",
        "/v1/scenes/demo",
        "/v1/scenes/demo/events?boxes=true",
    ] {
        let r = reqwest::get(server.url(path)).await.unwrap();
        assert_eq!(r.status(), 401, "{path}");
    }
    let Some(mut browser) = Browser::launch(WIDTH, HEIGHT).await else {
        return;
    };
    browser.open(&server.url("/"), WIDTH, HEIGHT).await;
    browser
        .wait_for(
            "the key prompt",
            "document.body.dataset.state === 'need-token'",
        )
        .await;
    // Frames flow, but the page without the key shows none of them.
    let pusher = Pusher::start(&server, Some(KEY));
    guard("frames published", async {
        while metric(
            &server.metrics().await,
            "crossview_frames_total{scene=\"demo\",state=\"complete\"}",
        ) < 3.0
        {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    let hidden = browser
        .eval(
            "({ form: document.getElementById('token-form').hidden, \
                status: document.getElementById('status').hidden, \
                panels: document.querySelectorAll('.panel').length, \
                frames: +document.getElementById('status').dataset.frames, \
                state: document.body.dataset.state })",
        )
        .await;
    assert_eq!(
        hidden,
        serde_json::json!({ "form": false, "status": true, "panels": 0, "frames": 0, "state": "need-token" })
    );
    // A wrong key is refused and asked for again.
    let submit = |k: &str| {
        format!(
            "(() => {{ document.getElementById('token').value = {}; \
               document.getElementById('token-form').requestSubmit(); return true; }})()",
            serde_json::json!(k)
        )
    };
    browser.eval(&submit("not-the-key")).await;
    browser
        .wait_for(
            "the wrong key to be refused",
            "document.body.dataset.state === 'need-token' && !document.getElementById('token-error').hidden",
        )
        .await;
    assert_eq!(
        browser
            .eval("document.querySelectorAll('.panel').length")
            .await,
        0
    );
    // The right key: frames arrive and are drawn.
    browser.eval(&submit(KEY)).await;
    browser
        .wait_for(
            "frames drawn with the key",
            "[...document.querySelectorAll('.panel')].length === 4 && \
             [...document.querySelectorAll('.panel')].every((p) => +p.dataset.frames >= 3 && +p.dataset.boxesDrawn >= 0)",
        )
        .await;
    let key = serde_json::json!(KEY);
    let leaks = browser
        .eval(&format!(
            "({{ stored: sessionStorage.getItem('crossview.apiKey') === {key}, \
                inUrl: location.href.includes({key}), \
                inRequests: performance.getEntriesByType('resource').some((e) => e.name.includes({key})) }})"
        ))
        .await;
    assert_eq!(
        leaks,
        serde_json::json!({ "stored": true, "inUrl": false, "inRequests": false })
    );
    pusher.stop().await;
    browser.close().await;
    server.shutdown().await.unwrap();
}

/// The data of `response`'s first `n` frame events (an SSE stream), as JSON.
async fn frame_events(response: reqwest::Response, n: usize) -> Vec<Value> {
    let mut sse = response.bytes_stream();
    let mut text = String::new();
    guard("SSE frame events", async {
        while text.matches("event: frame").count() < n || !text.ends_with("\n\n") {
            let chunk = sse.next().await.unwrap().unwrap();
            text.push_str(&String::from_utf8_lossy(&chunk));
        }
    })
    .await;
    text.lines()
        .filter_map(|l| l.strip_prefix("data: "))
        .map(|d| serde_json::from_str(d).unwrap())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn boxes_true_adds_each_cameras_boxes_and_changes_nothing_else() {
    let server = start(|_| {}).await;
    // Both subscribed before anything is pushed.
    let with = reqwest::get(server.url("/v1/scenes/lab/events?boxes=true"))
        .await
        .unwrap();
    let plain = reqwest::get(server.url("/v1/scenes/lab/events"))
        .await
        .unwrap();
    // Frame 1: every camera; frame 2: c1 missing (partial, after the sync timeout).
    for (frame, cams) in [(1u64, vec![0, 1, 2]), (2, vec![0, 2])] {
        for cam in cams {
            let (status, _) = server
                .post_json("/v1/scenes/lab/batches", &batch_json(cam, frame, 3))
                .await;
            assert_eq!(status, 202);
        }
    }
    let with = frame_events(with, 2).await;
    let plain = frame_events(plain, 2).await;
    assert_eq!((with.len(), plain.len()), (2, 2));
    for (w, p) in with.iter().zip(&plain) {
        assert!(p.get("views").is_none(), "{p}");
        let mut stripped = w.clone();
        let views = stripped.as_object_mut().unwrap().remove("views").unwrap();
        // Otherwise the same result (latency included: one published result, two forms).
        assert_eq!(&stripped, p);
        let frame = w["frame_id"].as_u64().unwrap();
        let views = views.as_array().unwrap();
        let reported: Vec<u64> = views
            .iter()
            .map(|v| v["camera_index"].as_u64().unwrap())
            .collect();
        assert_eq!(
            reported,
            if frame == 1 {
                vec![0, 1, 2]
            } else {
                vec![0, 2]
            }
        );
        for v in views {
            let c = v["camera_index"].as_u64().unwrap() as usize;
            assert_eq!(v["camera"], CAMERAS[c]);
            let sent: Vec<Value> = batch_json(c, frame, 3)["detections"]
                .as_array()
                .unwrap()
                .iter()
                .map(|d| d["bbox"].clone())
                .collect();
            assert_eq!(
                v["boxes"].as_array().unwrap(),
                &sent,
                "frame {frame} camera {c}"
            );
        }
    }
    // A bad value is refused like any bad input.
    let r = reqwest::get(server.url("/v1/scenes/lab/events?boxes=maybe"))
        .await
        .unwrap();
    assert_eq!(r.status(), 422);
    let e: Value = r.json().await.unwrap();
    assert_eq!(e["error"]["field"], "boxes", "{e}");
    server.shutdown().await.unwrap();
}
