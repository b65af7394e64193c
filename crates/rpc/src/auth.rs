//! Shared-token authentication: the submitter sends `authorization:
//! Bearer TOKEN` with every call; workers and the store server compare it
//! in constant time. A token is read from a file or an environment
//! variable — never from the command line, never logged.

use std::path::Path;
use std::sync::Arc;

use subtle::ConstantTimeEq;
use tonic::metadata::MetadataValue;
use tonic::{Request, Status};

/// The environment variable a token may come from.
pub const TOKEN_ENV: &str = "MATFLOW_TOKEN";

/// A secret; its Debug form does not show it.
#[derive(Clone)]
pub struct Token(Arc<Vec<u8>>);

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Token(<{} bytes>)", self.0.len())
    }
}

impl Token {
    /// Reads `file` (surrounding whitespace ignored), else `$MATFLOW_TOKEN`;
    /// `None` when neither is given. A token must be at least 16 bytes of
    /// printable ASCII.
    pub fn load(file: Option<&Path>) -> Result<Option<Token>, String> {
        let raw = match file {
            Some(f) => std::fs::read_to_string(f)
                .map_err(|e| format!("token file {}: {e}", f.display()))?,
            None => match std::env::var(TOKEN_ENV) {
                Ok(v) if !v.trim().is_empty() => v,
                _ => return Ok(None),
            },
        };
        let t = raw.trim();
        let from = file
            .map(|f| format!("token file {}", f.display()))
            .unwrap_or_else(|| format!("${TOKEN_ENV}"));
        if t.len() < 16 {
            return Err(format!("{from}: a token must have at least 16 characters"));
        }
        if !t.bytes().all(|c| c.is_ascii_graphic()) {
            return Err(format!("{from}: a token is printable ASCII without spaces"));
        }
        Ok(Some(Token(Arc::new(t.as_bytes().to_vec()))))
    }

    pub fn from_bytes(b: &[u8]) -> Token {
        Token(Arc::new(b.to_vec()))
    }

    fn header(&self) -> MetadataValue<tonic::metadata::Ascii> {
        let mut v = b"Bearer ".to_vec();
        v.extend_from_slice(&self.0);
        let mut m = MetadataValue::try_from(v.as_slice()).expect("printable ASCII");
        m.set_sensitive(true);
        m
    }

    /// Constant-time comparison with a presented header value
    /// (`Bearer TOKEN`).
    pub fn accepts(&self, presented: &[u8]) -> bool {
        let Some(t) = presented.strip_prefix(b"Bearer ") else {
            return false;
        };
        // Length is not secret; the bytes are compared in constant time.
        t.len() == self.0.len() && bool::from(t.ct_eq(&self.0))
    }
}

/// Client side: adds the token to every request (if there is one).
#[derive(Clone, Default)]
pub struct AddToken(pub Option<Token>);

impl tonic::service::Interceptor for AddToken {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(t) = &self.0 {
            req.metadata_mut().insert("authorization", t.header());
        }
        Ok(req)
    }
}

/// Server side: refuses calls without the right token (when one is set).
#[derive(Clone, Default)]
pub struct CheckToken(pub Option<Token>);

impl tonic::service::Interceptor for CheckToken {
    fn call(&mut self, req: Request<()>) -> Result<Request<()>, Status> {
        let Some(t) = &self.0 else { return Ok(req) };
        match req.metadata().get("authorization") {
            Some(v) if t.accepts(v.as_bytes()) => Ok(req),
            Some(_) => Err(Status::unauthenticated("wrong token")),
            None => Err(Status::unauthenticated(
                "this worker needs a token (authorization: Bearer ...)",
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_compare_whole_and_hide_in_debug() {
        let t = Token::from_bytes(b"0123456789abcdef");
        assert!(t.accepts(b"Bearer 0123456789abcdef"));
        assert!(!t.accepts(b"Bearer 0123456789abcdeg"));
        assert!(!t.accepts(b"Bearer 0123456789abcde"));
        assert!(!t.accepts(b"0123456789abcdef"));
        assert!(!format!("{t:?}").contains("0123"));
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("t");
        std::fs::write(&f, "short\n").unwrap();
        assert!(Token::load(Some(&f)).unwrap_err().contains("16"));
        std::fs::write(&f, " 0123456789abcdef \n").unwrap();
        assert!(Token::load(Some(&f))
            .unwrap()
            .unwrap()
            .accepts(b"Bearer 0123456789abcdef"));
    }
}
