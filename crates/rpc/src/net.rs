//! Endpoints and TLS.
//!
//! An endpoint is `grpc://HOST:PORT` (plain), `grpcs://HOST:PORT` (TLS,
//! checked against a CA file) or bare `HOST:PORT` (plain).

use std::path::{Path, PathBuf};
use std::time::Duration;

use tonic::transport::{Certificate, Channel, ClientTlsConfig, Identity, ServerTlsConfig};

use crate::RpcError;

/// TLS files: a CA bundle to check servers with (clients), a certificate
/// and key to present (servers).
#[derive(Clone, Debug, Default)]
pub struct TlsFiles {
    pub ca: Option<PathBuf>,
    pub cert: Option<PathBuf>,
    pub key: Option<PathBuf>,
}

fn read(p: &Path, what: &'static str) -> Result<Vec<u8>, RpcError> {
    std::fs::read(p).map_err(|source| RpcError::TlsFile {
        what,
        path: p.to_path_buf(),
        source,
    })
}

fn endpoint_error(endpoint: &str, reason: impl Into<String>) -> RpcError {
    RpcError::Endpoint {
        endpoint: endpoint.to_string(),
        reason: reason.into(),
    }
}

/// `grpc://h:p` → (`http://h:p`, false); `grpcs://h:p` → (`https://h:p`, true).
pub fn parse_endpoint(s: &str) -> Result<(String, bool), RpcError> {
    let (rest, tls) = if let Some(r) = s.strip_prefix("grpcs://") {
        (r, true)
    } else if let Some(r) = s.strip_prefix("grpc://") {
        (r, false)
    } else if s.contains("://") {
        return Err(endpoint_error(
            s,
            "use grpc://HOST:PORT or grpcs://HOST:PORT",
        ));
    } else {
        (s, false)
    };
    let rest = rest.trim_end_matches('/');
    match rest.rsplit_once(':') {
        Some((h, p)) if !h.is_empty() && p.parse::<u16>().is_ok() => {}
        _ => return Err(endpoint_error(s, "expected HOST:PORT")),
    }
    Ok((
        format!("{}://{rest}", if tls { "https" } else { "http" }),
        tls,
    ))
}

/// A channel to `endpoint` (connected on first use).
pub fn channel(endpoint: &str, tls: &TlsFiles) -> Result<Channel, RpcError> {
    let (uri, secure) = parse_endpoint(endpoint)?;
    let mut ep = Channel::from_shared(uri)
        .map_err(|e| endpoint_error(endpoint, e.to_string()))?
        .connect_timeout(Duration::from_secs(5))
        .tcp_nodelay(true)
        .http2_keep_alive_interval(Duration::from_secs(10))
        .keep_alive_timeout(Duration::from_secs(10))
        .keep_alive_while_idle(true);
    if secure {
        let ca = tls.ca.as_deref().ok_or_else(|| {
            endpoint_error(endpoint, "a grpcs:// endpoint needs a CA file (--tls-ca)")
        })?;
        let mut cfg =
            ClientTlsConfig::new().ca_certificate(Certificate::from_pem(read(ca, "CA file")?));
        if let (Some(c), Some(k)) = (&tls.cert, &tls.key) {
            cfg = cfg.identity(Identity::from_pem(read(c, "certificate")?, read(k, "key")?));
        }
        ep = ep
            .tls_config(cfg)
            .map_err(|e| endpoint_error(endpoint, format!("TLS: {e}")))?;
    }
    Ok(ep.connect_lazy())
}

/// The server side of TLS, when a certificate and key are given.
pub fn server_tls(tls: &TlsFiles) -> Result<Option<ServerTlsConfig>, RpcError> {
    match (&tls.cert, &tls.key) {
        (Some(c), Some(k)) => {
            let mut cfg = ServerTlsConfig::new()
                .identity(Identity::from_pem(read(c, "certificate")?, read(k, "key")?));
            if let Some(ca) = &tls.ca {
                cfg = cfg.client_ca_root(Certificate::from_pem(read(ca, "CA file")?));
            }
            Ok(Some(cfg))
        }
        (None, None) => Ok(None),
        _ => Err(RpcError::TlsSetup(
            "TLS needs both --tls-cert and --tls-key".into(),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_parse() {
        assert_eq!(
            parse_endpoint("grpc://127.0.0.1:9092").unwrap(),
            ("http://127.0.0.1:9092".into(), false)
        );
        assert_eq!(
            parse_endpoint("grpcs://cache.lab:443").unwrap(),
            ("https://cache.lab:443".into(), true)
        );
        assert_eq!(parse_endpoint("w1:7000").unwrap().0, "http://w1:7000");
        assert!(parse_endpoint("http://x:1").is_err());
        assert!(parse_endpoint("grpc://x").is_err());
        assert!(parse_endpoint("grpc://x:99999").is_err());
    }
}
