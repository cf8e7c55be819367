//! Bearer-token authentication, one implementation for both servers: the shard server
//! (`slag-encoder serve` / `slag-shards serve`) and the robot's server (`slag-edge serve`).
//!
//! Convention (RFC 6750): the client sends `Authorization: Bearer <token>`. Surrounding white
//! space of the presented token and of the configured one is ignored (a token file's trailing
//! newline, a header written by hand); everything else must match byte for byte, compared in
//! constant time.

use std::path::Path;

use crate::{Error, Result};

/// The token a client presented in an `Authorization` header value: the part after `Bearer `,
/// trimmed; `""` when the header is absent or uses another scheme (never matches a configured
/// token, which is never empty).
pub fn presented_token(authorization: Option<&str>) -> &str {
    authorization
        .and_then(|v| v.strip_prefix("Bearer "))
        .map(str::trim)
        .unwrap_or("")
}

/// `true` when the `Authorization` header value carries `expected` (trimmed) as its bearer token.
/// Constant time in the token's content: every byte of `expected` is compared whatever the
/// presented token holds.
pub fn authorized(authorization: Option<&str>, expected: &str) -> bool {
    token_matches(
        presented_token(authorization).as_bytes(),
        expected.trim().as_bytes(),
    )
}

/// Constant-time comparison of the presented and configured tokens (byte strings).
pub fn token_matches(presented: &[u8], expected: &[u8]) -> bool {
    // Lengths compared in full (a `as u8` truncation would accept a token with 256 extra bytes).
    let mut diff = u8::from(presented.len() != expected.len());
    for (i, b) in expected.iter().enumerate() {
        diff |= b ^ presented.get(i).copied().unwrap_or(0);
    }
    diff == 0
}

/// Reads a bearer token from a file: its first line, trimmed.
///
/// Errors: [`Error::Io`] when the file cannot be read; [`Error::Format`] when the first line is
/// empty (write the token on it).
pub fn read_token_file(path: &Path) -> Result<String> {
    let t = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let t = t.lines().next().unwrap_or("").trim().to_string();
    if t.is_empty() {
        return Err(Error::format(
            path,
            "the token file is empty; write the token on its first line",
        ));
    }
    Ok(t)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn token_comparison_needs_the_exact_token() {
        let t = b"s3cret";
        assert!(token_matches(t, t));
        for bad in [&b""[..], b"s3cre", b"s3cret!", b"S3cret", b"x3cret"] {
            assert!(!token_matches(bad, t), "{bad:?}");
        }
        // Regression: the token followed by 256 more bytes was accepted (length difference
        // truncated to u8).
        let long = [&t[..], &[b'a'; 256][..]].concat();
        assert!(!token_matches(&long, t));
    }

    #[test]
    fn header_parsing_trims_and_needs_the_bearer_scheme() {
        assert!(authorized(Some("Bearer s3cret"), "s3cret"));
        assert!(authorized(Some("Bearer  s3cret \t"), "s3cret\n"));
        assert!(!authorized(Some("Basic s3cret"), "s3cret"));
        assert!(!authorized(Some("bearer s3cret"), "s3cret"));
        assert!(!authorized(None, "s3cret"));
        assert!(!authorized(Some("Bearer "), "s3cret"));
        assert_eq!(presented_token(Some("Token x")), "");
    }

    #[test]
    fn token_file_first_line_trimmed_and_never_empty() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t");
        std::fs::write(&p, "  abc \nsecond line\n").unwrap();
        assert_eq!(read_token_file(&p).unwrap(), "abc");
        std::fs::write(&p, "\nabc\n").unwrap();
        let e = read_token_file(&p).unwrap_err().to_string();
        assert!(e.contains("first line"), "{e}");
        assert!(matches!(
            read_token_file(&dir.path().join("absent")),
            Err(Error::Io { .. })
        ));
    }
}
