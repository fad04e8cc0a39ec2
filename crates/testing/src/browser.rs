//! A real headless Chromium for browser tests, driven over the DevTools protocol on a pipe
//! (`--remote-debugging-pipe`: NUL-terminated JSON on the browser's fds 3 and 4), so no
//! WebSocket client, no port and no extra crate are needed.
//!
//! [`Browser::launch`] finds Chromium (`$CROSSVIEW_CHROMIUM`, else `chromium`,
//! `chromium-browser` or `google-chrome` on `PATH`; `scripts/setup.sh` installs Debian's
//! `chromium`) and returns `None` after [`crate::skip`] when there is none — a failure under
//! `CI=true`. Every wait is bounded by [`crate::HANG_GUARD`]; nothing measures time.
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use serde_json::{Value, json};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::process::{Child, ChildStdin, ChildStdout, Command};

use crate::{guard, skip};

/// The Chromium executable: `$CROSSVIEW_CHROMIUM` (when it names a file), else the first of
/// `chromium`, `chromium-browser`, `google-chrome` on `PATH`.
pub fn find_chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("CROSSVIEW_CHROMIUM") {
        return Some(PathBuf::from(p)).filter(|p| p.is_file());
    }
    let path = std::env::var_os("PATH")?;
    ["chromium", "chromium-browser", "google-chrome"]
        .iter()
        .flat_map(|name| std::env::split_paths(&path).map(move |d| d.join(name)))
        .find(|p| p.is_file())
}

/// A headless Chromium with one page, killed on drop.
pub struct Browser {
    child: Child,
    to_browser: ChildStdin,
    from_browser: BufReader<ChildStdout>,
    next_id: u64,
    session: Option<String>,
    profile: tempfile::TempDir,
}

impl Browser {
    /// Starts headless Chromium with a `width` × `height` window, or `None` (after
    /// [`skip`]) when no Chromium is installed.
    pub async fn launch(width: u32, height: u32) -> Option<Browser> {
        let Some(exe) = find_chromium() else {
            skip(
                "Chromium not found: run scripts/setup.sh (installs Debian's chromium) or set CROSSVIEW_CHROMIUM",
            );
            return None;
        };
        let profile = tempfile::tempdir().expect("tempdir for the Chromium profile");
        let log = std::fs::File::create(profile.path().join("chromium.log")).expect("log file");
        // The shell hands our stdin/stdout pipes to Chromium as fds 3 and 4.
        let mut child = Command::new("sh")
            .arg("-c")
            .arg(r#"exec "$0" "$@" 3<&0 4>&1 0</dev/null 1>&2"#)
            .arg(&exe)
            .args([
                "--headless",
                "--remote-debugging-pipe",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-dev-shm-usage",
                "--no-first-run",
                "--no-default-browser-check",
                "--no-proxy-server",
                "--disable-extensions",
                "--disable-sync",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-background-timer-throttling",
                "--disable-renderer-backgrounding",
                "--disable-backgrounding-occluded-windows",
                "--hide-scrollbars",
                "--mute-audio",
                "--password-store=basic",
            ])
            .arg(format!("--window-size={width},{height}"))
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .arg("about:blank")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::from(log))
            .kill_on_drop(true)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", exe.display()));
        let to_browser = child.stdin.take().expect("piped stdin");
        let from_browser = BufReader::new(child.stdout.take().expect("piped stdout"));
        let mut browser = Browser {
            child,
            to_browser,
            from_browser,
            next_id: 0,
            session: None,
            profile,
        };
        browser.call(None, "Browser.getVersion", json!({})).await;
        Some(browser)
    }

    /// What Chromium wrote to its stderr so far (for failure messages).
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.profile.path().join("chromium.log")).unwrap_or_default()
    }

    /// Sends one DevTools command (to the page's session when `session`) and returns its
    /// result, or the protocol error as `Err`. Events on the way are skipped.
    async fn send(
        &mut self,
        session: Option<String>,
        method: &str,
        params: Value,
    ) -> Result<Value, Value> {
        self.next_id += 1;
        let id = self.next_id;
        let mut msg = json!({ "id": id, "method": method, "params": params });
        if let Some(s) = session {
            msg["sessionId"] = s.into();
        }
        let mut bytes = serde_json::to_vec(&msg).expect("JSON");
        bytes.push(0);
        let what = format!("DevTools {method}");
        guard(&what, async {
            self.to_browser
                .write_all(&bytes)
                .await
                .expect("write to Chromium");
            self.to_browser.flush().await.expect("flush to Chromium");
            loop {
                let mut buf = Vec::new();
                let n = self
                    .from_browser
                    .read_until(0, &mut buf)
                    .await
                    .expect("read from Chromium");
                assert!(n > 0, "Chromium closed its DevTools pipe:\n{}", self.log());
                if buf.last() == Some(&0) {
                    buf.pop();
                }
                let reply: Value = serde_json::from_slice(&buf).expect("DevTools JSON");
                if reply["id"].as_u64() == Some(id) {
                    return match reply.get("error") {
                        Some(e) => Err(e.clone()),
                        None => Ok(reply["result"].clone()),
                    };
                }
            }
        })
        .await
    }

    /// [`Self::send`], panicking on a protocol error.
    async fn call(&mut self, session: Option<String>, method: &str, params: Value) -> Value {
        self.send(session, method, params)
            .await
            .unwrap_or_else(|e| panic!("DevTools {method} failed: {e}"))
    }

    /// Opens `url` in a new page (the one later calls talk to) with a `width` × `height`
    /// viewport, and waits for its document to be loaded.
    pub async fn open(&mut self, url: &str, width: u32, height: u32) {
        let target = self
            .call(None, "Target.createTarget", json!({ "url": "about:blank" }))
            .await;
        let attached = self
            .call(
                None,
                "Target.attachToTarget",
                json!({ "targetId": target["targetId"], "flatten": true }),
            )
            .await;
        let session = attached["sessionId"]
            .as_str()
            .expect("a session id")
            .to_string();
        self.session = Some(session.clone());
        self.call(
            Some(session.clone()),
            "Emulation.setDeviceMetricsOverride",
            json!({ "width": width, "height": height, "deviceScaleFactor": 1, "mobile": false }),
        )
        .await;
        self.call(Some(session), "Page.navigate", json!({ "url": url }))
            .await;
        self.wait_for(
            "the page to load",
            &format!(
                "location.href === {} && document.readyState === 'complete'",
                json!(url)
            ),
        )
        .await;
    }

    /// Evaluates `expression` in the page (promises awaited) and returns its value; a thrown
    /// exception is `Err` with its description.
    pub async fn try_eval(&mut self, expression: &str) -> Result<Value, String> {
        let session = self.session.clone().expect("open a page first");
        let r = self
            .send(
                Some(session),
                "Runtime.evaluate",
                json!({ "expression": expression, "returnByValue": true, "awaitPromise": true }),
            )
            .await
            .map_err(|e| e.to_string())?;
        if let Some(ex) = r.get("exceptionDetails") {
            return Err(ex["exception"]["description"]
                .as_str()
                .map_or_else(|| ex.to_string(), str::to_string));
        }
        Ok(r["result"]["value"].clone())
    }

    /// [`Self::try_eval`], panicking on an exception.
    pub async fn eval(&mut self, expression: &str) -> Value {
        self.try_eval(expression)
            .await
            .unwrap_or_else(|e| panic!("{expression}: {e}"))
    }

    /// Polls `expression` until it is truthy (an exception counts as not yet) and returns its
    /// value; fails the test after [`crate::HANG_GUARD`], naming `what`.
    pub async fn wait_for(&mut self, what: &str, expression: &str) -> Value {
        let probe = format!(
            "(() => {{ try {{ return ({expression}); }} catch (_) {{ return null; }} }})()"
        );
        let what = format!("browser: {what} ({expression})");
        guard(&what, async {
            loop {
                let v = self.eval(&probe).await;
                let truthy = match &v {
                    Value::Null => false,
                    Value::Bool(b) => *b,
                    Value::Number(n) => n.as_f64() != Some(0.0),
                    Value::String(s) => !s.is_empty(),
                    _ => true,
                };
                if truthy {
                    return v;
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        })
        .await
    }

    /// Saves a PNG screenshot of the page's viewport to `path`.
    pub async fn screenshot(&mut self, path: &Path) {
        let session = self.session.clone().expect("open a page first");
        let shot = self
            .call(
                Some(session),
                "Page.captureScreenshot",
                json!({ "format": "png" }),
            )
            .await;
        let png = decode_base64(shot["data"].as_str().expect("screenshot data"));
        std::fs::write(path, png)
            .unwrap_or_else(|e| panic!("cannot write {}: {e}", path.display()));
    }

    /// Closes the browser and waits for it to exit.
    pub async fn close(mut self) {
        let _ = self.send(None, "Browser.close", json!({})).await;
        let _ = guard("Chromium to exit", self.child.wait()).await;
    }
}

/// Standard base64 (with or without padding) to bytes; other characters are skipped.
fn decode_base64(text: &str) -> Vec<u8> {
    let value = |c: u8| match c {
        b'A'..=b'Z' => Some(c - b'A'),
        b'a'..=b'z' => Some(c - b'a' + 26),
        b'0'..=b'9' => Some(c - b'0' + 52),
        b'+' => Some(62),
        b'/' => Some(63),
        _ => None,
    };
    let mut out = Vec::with_capacity(text.len() / 4 * 3);
    let (mut acc, mut bits) = (0u32, 0u32);
    for v in text.bytes().filter_map(value) {
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn base64_decodes() {
        assert_eq!(super::decode_base64("aGVsbG8gd29ybGQ="), b"hello world");
        assert_eq!(super::decode_base64("AAEC/w=="), [0, 1, 2, 255]);
    }
}
