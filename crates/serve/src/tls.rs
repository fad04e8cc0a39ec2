//! Optional TLS (rustls): certificate chain and key from PEM files, ALPN `h2` + `http/1.1` so
//! gRPC and HTTP share the TLS port too.
use std::sync::Arc;

use tokio_rustls::TlsAcceptor;
use tokio_rustls::rustls::ServerConfig;

use super::config::TlsConfig;
use crate::error::{Error, Result};

/// Builds the acceptor; any unreadable or invalid file is an error naming it.
pub(crate) fn acceptor(cfg: &TlsConfig) -> Result<TlsAcceptor> {
    let read = |p: &std::path::Path| std::fs::read(p).map_err(|e| crossview_core::Error::io(p, e));
    let cert_pem = read(&cfg.cert)?;
    let key_pem = read(&cfg.key)?;
    let bad = |p: &std::path::Path, m: String| crossview_core::Error::Format {
        source_name: p.display().to_string(),
        line: 0,
        message: m,
    };
    let certs = rustls_pemfile::certs(&mut cert_pem.as_slice())
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|e| bad(&cfg.cert, format!("bad certificate PEM: {e}")))?;
    if certs.is_empty() {
        return Err(bad(&cfg.cert, "no certificate found".into()).into());
    }
    let key = rustls_pemfile::private_key(&mut key_pem.as_slice())
        .map_err(|e| bad(&cfg.key, format!("bad key PEM: {e}")))?
        .ok_or_else(|| bad(&cfg.key, "no private key found".into()))?;
    let provider = Arc::new(tokio_rustls::rustls::crypto::ring::default_provider());
    let mut config = ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| Error::invalid("tls", e.to_string()))?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .map_err(|e| bad(&cfg.key, format!("certificate/key rejected: {e}")))?;
    config.alpn_protocols = vec![b"h2".to_vec(), b"http/1.1".to_vec()];
    Ok(TlsAcceptor::from(Arc::new(config)))
}
