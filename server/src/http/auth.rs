//! Scene tokens: random, shown once, stored as SHA-256 hashes, compared in constant time.

use axum::http::HeaderMap;
use sha2::{Digest, Sha256};

/// Random bytes in a token (64 hex digits).
pub const TOKEN_BYTES: usize = 32;

/// A fresh token from the operating system's random source.
pub fn new_token() -> Result<String, getrandom::Error> {
    let mut raw = [0u8; TOKEN_BYTES];
    getrandom::fill(&mut raw)?;
    Ok(crate::store::assets::hex(&raw))
}

/// What the store keeps of a token.
pub fn hash_token(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

/// Constant-time equality of two hashes: the time does not depend on where they differ.
pub fn ct_eq(a: &[u8; 32], b: &[u8; 32]) -> bool {
    let diff = a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y));
    std::hint::black_box(diff) == 0
}

/// True when `token` hashes to `stored`.
pub fn matches(token: Option<&str>, stored: &[u8; 32]) -> bool {
    token.is_some_and(|t| ct_eq(&hash_token(t), stored))
}

/// The token a request presents: `Authorization: Bearer <token>`, else a `token` query parameter
/// (browsers cannot set headers on WebSockets).
pub fn presented(headers: &HeaderMap, query: Option<&str>) -> Option<String> {
    if let Some(v) = headers
        .get(axum::http::header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
    {
        let mut parts = v.splitn(2, ' ');
        if parts.next().is_some_and(|s| s.eq_ignore_ascii_case("bearer")) {
            return parts.next().map(|t| t.trim().to_string());
        }
    }
    query?
        .split('&')
        .find_map(|kv| kv.strip_prefix("token="))
        .map(str::to_string)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_hash_and_compare() {
        let t = new_token().expect("random");
        assert_eq!(t.len(), 64);
        assert_ne!(t, new_token().expect("random"));
        let h = hash_token(&t);
        assert!(matches(Some(&t), &h));
        assert!(!matches(Some("nope"), &h));
        assert!(!matches(None, &h));
        let mut other = h;
        other[31] ^= 1;
        assert!(!ct_eq(&h, &other));
        let mut headers = HeaderMap::new();
        headers.insert("authorization", format!("Bearer {t}").parse().expect("header"));
        assert_eq!(presented(&headers, None).as_deref(), Some(t.as_str()));
        assert_eq!(
            presented(&HeaderMap::new(), Some("a=1&token=xyz")).as_deref(),
            Some("xyz")
        );
        assert_eq!(presented(&HeaderMap::new(), Some("a=1")), None);
    }
}
