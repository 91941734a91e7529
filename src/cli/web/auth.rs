//! The gateway's access check: a random token made at start, asked of every request.
//!
//! - A page or file (GET) may carry it as `?token=` (the printed URL, `<img src>`, the
//!   WebSocket, which a browser cannot give headers) or in the `X-Rigd-Token` header.
//! - A request that changes anything (every other method) must carry it in the header:
//!   another site can make a browser send a URL, not a custom header.
//! - `Host` must be a loopback name (no DNS rebinding) and an `Origin`, when sent, this very
//!   host (no cross-site WebSocket).
//!
//! No cookies are set, and no CORS headers are ever sent.

use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::sync::Arc;

/// The header a changing request carries the token in.
pub const HEADER: &str = "x-rigd-token";

/// A secret of 32 random bytes from the OS, as 64 hex digits.
#[derive(Clone)]
pub struct Token(Arc<str>);

impl Token {
    pub fn random() -> anyhow::Result<Token> {
        let mut bytes = [0u8; 32];
        getrandom::getrandom(&mut bytes)
            .map_err(|e| anyhow::anyhow!("no randomness for the access token: {e}"))?;
        let hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
        Ok(Token(hex.into()))
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }

    /// Compared in time independent of where the strings differ.
    fn matches(&self, given: &str) -> bool {
        let (a, b) = (self.0.as_bytes(), given.as_bytes());
        a.len() == b.len() && a.iter().zip(b).fold(0u8, |d, (x, y)| d | (x ^ y)) == 0
    }
}

/// Why a request was refused, as the body says it.
fn refuse(status: StatusCode, why: &str) -> Response {
    (status, format!("rigctl web: {why}\n")).into_response()
}

/// The `token` query parameter, if any.
fn query_token(uri: &axum::http::Uri) -> Option<String> {
    let q = uri.query()?;
    q.split('&').find_map(|kv| {
        let (k, v) = kv.split_once('=')?;
        (k == "token").then(|| v.to_string())
    })
}

/// `Host` (and `Origin`, when sent) name this gateway on loopback.
fn loopback_host(headers: &HeaderMap) -> Result<(), &'static str> {
    let host = headers
        .get(header::HOST)
        .and_then(|h| h.to_str().ok())
        .ok_or("no Host header")?;
    let name = match host.rsplit_once(':') {
        Some((n, port)) if port.chars().all(|c| c.is_ascii_digit()) => n,
        _ => host,
    };
    if !matches!(name, "127.0.0.1" | "localhost" | "[::1]") {
        return Err("the Host header is not a loopback address");
    }
    if let Some(origin) = headers.get(header::ORIGIN) {
        let same = origin.to_str().is_ok_and(|o| o == format!("http://{host}"));
        if !same {
            return Err("a request from another origin");
        }
    }
    Ok(())
}

/// The middleware: 403 for a foreign host or origin, 401 without the right token.
pub async fn check(State(token): State<Token>, req: Request, next: Next) -> Response {
    if let Err(why) = loopback_host(req.headers()) {
        return refuse(StatusCode::FORBIDDEN, why);
    }
    let header = req.headers().get(HEADER).and_then(|v| v.to_str().ok());
    let reading = matches!(*req.method(), Method::GET | Method::HEAD);
    let given = match header {
        Some(h) => Some(h.to_string()),
        None if reading => query_token(req.uri()),
        None => {
            return refuse(
                StatusCode::UNAUTHORIZED,
                "a request that changes anything needs the token in the X-Rigd-Token header",
            )
        }
    };
    match given {
        Some(t) if token.matches(&t) => next.run(req).await,
        Some(_) => refuse(StatusCode::UNAUTHORIZED, "wrong token"),
        None => refuse(
            StatusCode::UNAUTHORIZED,
            "no token: open the URL `rigctl web` printed (it ends in ?token=...)",
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(*k, v.parse().unwrap());
        }
        h
    }

    #[test]
    fn tokens_are_random_and_compared_whole() {
        let (a, b) = (Token::random().unwrap(), Token::random().unwrap());
        assert_eq!(a.as_str().len(), 64);
        assert_ne!(a.as_str(), b.as_str());
        assert!(a.matches(a.as_str()));
        assert!(!a.matches(b.as_str()));
        assert!(!a.matches(&a.as_str()[..63]));
    }

    #[test]
    fn only_loopback_hosts_and_the_same_origin_pass() {
        assert!(loopback_host(&headers(&[("host", "127.0.0.1:8080")])).is_ok());
        assert!(loopback_host(&headers(&[("host", "[::1]:8080")])).is_ok());
        assert!(loopback_host(&headers(&[("host", "evil.example:8080")])).is_err());
        let same = [("host", "127.0.0.1:80"), ("origin", "http://127.0.0.1:80")];
        assert!(loopback_host(&headers(&same)).is_ok());
        let other = [("host", "127.0.0.1:80"), ("origin", "http://evil.example")];
        assert!(loopback_host(&headers(&other)).is_err());
    }

    #[test]
    fn the_token_is_found_among_query_parameters() {
        let uri: axum::http::Uri = "/x?a=1&token=abc".parse().unwrap();
        assert_eq!(query_token(&uri).as_deref(), Some("abc"));
        assert_eq!(query_token(&"/x?a=1".parse().unwrap()), None);
    }
}
