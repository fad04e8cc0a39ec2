//! TLS (rustls): the same port serves HTTP/1.1, HTTP/2 and gRPC over TLS with a certificate
//! generated for the test (rcgen); a plain-text client is refused.

use crossview_testing::*;
use std::process::Command;

use crossview_api::pb;
use crossview_api::pb::association_client::AssociationClient;
use crossview_serve::TlsConfig;
use tonic::transport::{Certificate, Channel, ClientTlsConfig};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_and_http_over_tls() {
    let certs = tempfile::tempdir().unwrap();
    let (cert, key) = (certs.path().join("cert.pem"), certs.path().join("key.pem"));
    // A self-signed leaf certificate for localhost and 127.0.0.1 (rcgen, in process).
    let made = rcgen::generate_simple_self_signed(vec!["localhost".into(), "127.0.0.1".into()])
        .expect("generate a test certificate");
    std::fs::write(&cert, made.cert.pem()).unwrap();
    std::fs::write(&key, made.signing_key.serialize_pem()).unwrap();
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
