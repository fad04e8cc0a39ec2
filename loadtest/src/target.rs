//! The server address: a safety check that load only goes to this machine (or to hosts named
//! explicitly), and a readiness wait.
use std::net::IpAddr;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use crossview_core::SceneSpec;

/// Checks that `url` (http://HOST:PORT) points at a loopback address, unless HOST is in
/// `allowed` (e.g. a compose service name on a private container network).
pub async fn check_target(url: &str, allowed: &[String]) -> anyhow::Result<()> {
    let parsed = reqwest::Url::parse(url).with_context(|| format!("bad --target '{url}'"))?;
    if parsed.scheme() != "http" {
        bail!("--target '{url}': only http:// is supported (h2c for gRPC)");
    }
    let host = parsed
        .host_str()
        .with_context(|| format!("--target '{url}' has no host"))?;
    if allowed.iter().any(|a| a == host) {
        return Ok(());
    }
    let port = parsed.port_or_known_default().unwrap_or(80);
    let host_trimmed = host.trim_start_matches('[').trim_end_matches(']');
    let addrs: Vec<IpAddr> = match host_trimmed.parse::<IpAddr>() {
        Ok(ip) => vec![ip],
        Err(_) => tokio::net::lookup_host((host_trimmed, port))
            .await
            .with_context(|| format!("cannot resolve '{host}'"))?
            .map(|a| a.ip())
            .collect(),
    };
    if addrs.is_empty() || addrs.iter().any(|a| !a.is_loopback()) {
        bail!(
            "--target '{url}' resolves to {addrs:?}, not loopback; the load generator only \
             targets this machine unless the host is named with --allow-host"
        );
    }
    Ok(())
}

/// Polls `GET {base}/readyz` until it answers 200 or `wait` passes.
pub async fn wait_ready(base: &str, wait: Duration) -> anyhow::Result<()> {
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(2))
        .build()?;
    let url = format!("{}/readyz", base.trim_end_matches('/'));
    let deadline = Instant::now() + wait;
    loop {
        let last = match client.get(&url).send().await {
            Ok(r) if r.status().is_success() => return Ok(()),
            Ok(r) => format!("HTTP {}", r.status()),
            Err(e) => e.to_string(),
        };
        if Instant::now() >= deadline {
            bail!("server not ready after {wait:?}: GET {url}: {last}");
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

/// Checks that the server serves `scene` with every camera of `recording` (same names and
/// image sizes), so a mismatch fails at once with a clear message instead of as thousands
/// of rejected batches.
pub async fn check_scene(base: &str, scene: &str, recording: &SceneSpec) -> anyhow::Result<()> {
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(5))
        .build()?;
    let url = format!("{}/v1/scenes/{scene}", base.trim_end_matches('/'));
    let resp = client
        .get(&url)
        .send()
        .await
        .with_context(|| format!("GET {url}"))?;
    if resp.status() == reqwest::StatusCode::NOT_FOUND {
        bail!("the server does not serve scene '{scene}' (GET {url}: 404)");
    }
    let served: SceneSpec = resp
        .error_for_status()
        .with_context(|| format!("GET {url}"))?
        .json()
        .await
        .with_context(|| format!("GET {url}: not a scene description"))?;
    for cam in &recording.cameras {
        match served.cameras.iter().find(|c| c.name == cam.name) {
            Some(c) if c == cam => {}
            Some(c) => bail!(
                "scene '{scene}': camera '{}' is {}x{} on the server but {}x{} in the recording",
                cam.name,
                c.width,
                c.height,
                cam.width,
                cam.height
            ),
            None => bail!(
                "scene '{scene}' on the server has no camera '{}' (it has {:?})",
                cam.name,
                served.cameras.iter().map(|c| &c.name).collect::<Vec<_>>()
            ),
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn only_loopback_or_named_hosts() {
        check_target("http://127.0.0.1:8080", &[]).await.unwrap();
        check_target("http://[::1]:8080", &[]).await.unwrap();
        check_target("http://localhost:8080", &[]).await.unwrap();
        assert!(check_target("http://10.1.2.3:8080", &[]).await.is_err());
        assert!(check_target("https://127.0.0.1:8080", &[]).await.is_err());
        check_target("http://server:8080", &["server".to_string()])
            .await
            .unwrap();
    }
}
