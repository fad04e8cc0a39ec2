//! TLS (rustls): the same port serves HTTP/1.1, HTTP/2 and gRPC over TLS with a certificate
//! generated for the test by openssl; a plain-text client is refused.
mod common;

use std::process::Command;

use common::*;
use crossview::serve::TlsConfig;
use crossview::serve::pb;
use crossview::serve::pb::association_client::AssociationClient;
use tonic::transport::{Certificate, Channel, ClientTlsConfig};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_and_http_over_tls() {
    let certs = tempfile::tempdir().unwrap();
    let (cert, key) = (certs.path().join("cert.pem"), certs.path().join("key.pem"));
    let made = Command::new("openssl")
        .args([
            "req",
            "-x509",
            "-newkey",
            "ec",
            "-pkeyopt",
            "ec_paramgen_curve:prime256v1",
        ])
        .args(["-nodes", "-days", "1", "-subj", "/CN=localhost"])
        .args(["-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"])
        // A leaf certificate (webpki refuses a CA certificate as server certificate).
        .args(["-addext", "basicConstraints=critical,CA:FALSE"])
        .args(["-addext", "extendedKeyUsage=serverAuth"])
        .arg("-keyout")
        .arg(&key)
        .arg("-out")
        .arg(&cert)
        .output();
    match made {
        Err(e) => {
            eprintln!("SKIPPED: openssl is needed to make a test certificate: {e}");
            return;
        }
        Ok(o) => assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr)),
    }
    let tls = TlsConfig {
        cert: cert.clone(),
        key,
    };
    let server = start(move |c| c.tls = Some(tls)).await;
    let port = server.addr.port();

    // gRPC over TLS (HTTP/2 via ALPN).
    let pem = std::fs::read(&cert).unwrap();
    let ch = Channel::from_shared(format!("https://localhost:{port}"))
        .unwrap()
        .tls_config(
            ClientTlsConfig::new()
                .ca_certificate(Certificate::from_pem(pem))
                .domain_name("localhost"),
        )
        .unwrap();
    let ch = guard("TLS connect", async {
        for attempt in 0.. {
            match ch.clone().connect().await {
                Ok(c) => return c,
                Err(e) if attempt > 100 => panic!("TLS connect: {e:?}"),
                Err(_) => tokio::time::sleep(std::time::Duration::from_millis(50)).await,
            }
        }
        unreachable!()
    })
    .await;
    let mut client = AssociationClient::new(ch);
    let scenes = guard(
        "ListScenes over TLS",
        client.list_scenes(pb::ListScenesRequest {}),
    )
    .await
    .unwrap()
    .into_inner();
    assert_eq!(scenes.scenes[0].name, "lab");

    // HTTP/1.1 and HTTP/2 over TLS with curl.
    let resolve = format!("localhost:{port}:127.0.0.1");
    let url = format!("https://localhost:{port}/v1/scenes/lab");
    for version in ["--http1.1", "--http2"] {
        let out = tokio::task::block_in_place(|| {
            Command::new("curl")
                .args([
                    "-sS",
                    "--max-time",
                    "30",
                    version,
                    "--resolve",
                    &resolve,
                    "--cacert",
                ])
                .arg(&cert)
                .arg(&url)
                .output()
                .expect("curl")
        });
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(v["name"], "lab", "{version}");
    }

    // Plain HTTP to the TLS port does not get an answer.
    let plain = reqwest::Client::new()
        .get(format!("http://127.0.0.1:{port}/healthz"))
        .timeout(std::time::Duration::from_secs(10))
        .send()
        .await;
    assert!(plain.is_err() || !plain.unwrap().status().is_success());
    server.shutdown().await.unwrap();
}
