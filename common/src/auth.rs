//! Bearer-token authentication, one implementation for both servers: the shard server
//! (`slag-encoder serve` / `slag-shards serve`) and the robot's server (`slag-edge serve`).
//!
//! Convention (RFC 6750): the client sends `Authorization: Bearer <token>`; the scheme name is
//! matched case-insensitively (RFC 9110 §11.1: `bearer`, `BEARER` are the same scheme).
//! Surrounding white space of the presented token and of the configured one is ignored (a token
//! file's trailing newline, a header written by hand); everything else must match byte for byte,
//! compared in constant time. A configured token is never blank: [`configured_token`],
//! [`env_token`] and [`read_token_file`] refuse one, so a blank setting cannot start a server
//! open by mistake.

use std::path::Path;

use crate::{Error, Result};

/// The token a client presented in an `Authorization` header value: the part after `Bearer `,
/// trimmed; `""` when the header is absent or uses another scheme (never matches a configured
/// token, which is never empty).
pub fn presented_token(authorization: Option<&str>) -> &str {
    let Some(v) = authorization.map(str::trim_start) else {
        return "";
    };
    match v.split_once([' ', '\t']) {
        Some((scheme, token)) if scheme.eq_ignore_ascii_case("bearer") => token.trim(),
        _ => "",
    }
}

/// A token given in `source` (an environment variable's or a flag's name, for the message),
/// trimmed.
///
/// Errors: [`Error::Param`] `token` when it is empty or only white space: set a real token, or
/// unset it to run without one.
pub fn configured_token(value: &str, source: &str) -> Result<String> {
    let t = value.trim();
    if t.is_empty() {
        return Err(Error::param(
            "token",
            format!("{source} = {value:?}"),
            format!(
                "a non-blank token; {source} is set but blank: set a real token, or unset it \
                 to serve without one"
            ),
        ));
    }
    Ok(t.to_string())
}

/// The token in the environment variable `var`: `None` when unset, else [`configured_token`].
///
/// Errors: [`Error::Param`] `token` when it is set but blank or not UTF-8.
pub fn env_token(var: &str) -> Result<Option<String>> {
    match std::env::var(var) {
        Err(std::env::VarError::NotPresent) => Ok(None),
        Err(std::env::VarError::NotUnicode(_)) => Err(Error::param(
            "token",
            format!("{var} = (not UTF-8)"),
            "a token of UTF-8 text",
        )),
        Ok(v) => configured_token(&v, var).map(Some),
    }
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

/// `true` when the request's `Authorization` header values (every one, in order: e.g.
/// `HeaderMap::get_all`) are exactly one, of visible ASCII, that carries `expected`
/// ([`authorized`]). Two headers are refused whatever they hold: which one a proxy or a server
/// reads first differs, so accepting either would let a request pass one check and be judged by
/// another value.
pub fn authorized_once<V: AsRef<[u8]>>(
    values: impl IntoIterator<Item = V>,
    expected: &str,
) -> bool {
    let mut values = values.into_iter();
    let (Some(only), None) = (values.next(), values.next()) else {
        // None, or two or more: still one comparison's time for a uniform answer.
        token_matches(b"", expected.trim().as_bytes());
        return false;
    };
    let visible = only
        .as_ref()
        .iter()
        .all(|&b| b == b'\t' || (b' '..=b'~').contains(&b));
    let text = std::str::from_utf8(only.as_ref()).ok().filter(|_| visible);
    authorized(text, expected)
}

/// Where the user information of `url` (`user:password` in `scheme://user:password@host/…`) is:
/// the byte range before the authority's last `@`, or `None` when it has none.
fn userinfo_range(url: &str) -> Option<std::ops::Range<usize>> {
    let start = url.find("://").map_or(0, |i| i + 3);
    let rest = &url[start..];
    let end = rest.find(['/', '?', '#']).unwrap_or(rest.len());
    let at = rest[..end].rfind('@')?;
    Some(start..start + at)
}

/// `url` with its user information (`user:password@`), if any, replaced by `***`:
/// `http://robot:secret@host:8090/x` → `http://***@host:8090/x`. For showing a URL that came
/// from outside (a message, a log line, a record written by an older version).
pub fn redact_url(url: &str) -> std::borrow::Cow<'_, str> {
    match userinfo_range(url) {
        None => std::borrow::Cow::Borrowed(url),
        Some(r) => std::borrow::Cow::Owned(format!("{}***{}", &url[..r.start], &url[r.end..])),
    }
}

/// Refuses a server URL that carries a user name or password (`http://robot:secret@host:port`):
/// a secret in a URL ends up in logs, status pages and saved records, so the shard server's
/// token travels as a bearer token (a token file or variable) instead. `name` is the parameter's
/// name for the error (`server`).
///
/// Errors: [`Error::Param`] `name`, its value the URL with the user information redacted
/// ([`redact_url`]), never the secret.
pub fn refuse_credentials_in_url(url: &str, name: &'static str) -> Result<()> {
    if userinfo_range(url).is_none() {
        return Ok(());
    }
    Err(Error::param(
        name,
        redact_url(url),
        "a URL without a user name or password (http://host:port); give the server's token \
         as a bearer token instead",
    ))
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
        // The scheme is case-insensitive (RFC 9110 §11.1).
        assert!(authorized(Some("bearer s3cret"), "s3cret"));
        assert!(authorized(Some("BEARER\ts3cret"), "s3cret"));
        assert!(!authorized(Some("Bearers3cret"), "s3cret"));
        assert!(!authorized(Some("Bearer S3cret"), "s3cret"));
        assert!(!authorized(None, "s3cret"));
        assert!(!authorized(Some("Bearer "), "s3cret"));
        assert_eq!(presented_token(Some("Token x")), "");
    }

    #[test]
    fn exactly_one_authorization_header_is_accepted() {
        assert!(authorized_once(["Bearer s3cret"], "s3cret"));
        assert!(!authorized_once(
            ["Bearer s3cret", "Bearer s3cret"],
            "s3cret"
        ));
        assert!(!authorized_once(
            ["Bearer wrong", "Bearer s3cret"],
            "s3cret"
        ));
        assert!(!authorized_once(Vec::<&str>::new(), "s3cret"));
        assert!(!authorized_once([&b"Bearer s3cret\xff"[..]], "s3cret"));
    }

    #[test]
    fn credentials_in_a_url_are_refused_and_never_shown() {
        for ok in [
            "http://127.0.0.1:8090",
            "https://host/path@not-userinfo",
            "http://host:1/?q=a@b",
        ] {
            assert!(refuse_credentials_in_url(ok, "server").is_ok(), "{ok}");
            assert_eq!(redact_url(ok), ok);
        }
        for bad in [
            "http://robot:secret@127.0.0.1:8090",
            "http://secret@host/",
            "HTTP://robot:secret@host:1/v1?x=y",
            "http://robot:se@cret@host",
        ] {
            let e = refuse_credentials_in_url(bad, "server").unwrap_err();
            assert!(matches!(e, Error::Param { name: "server", .. }), "{e}");
            let m = e.to_string();
            assert!(!m.contains("secret") && !m.contains("cret"), "{m}");
            assert!(m.contains("***@") && m.contains("token"), "{m}");
        }
        assert_eq!(
            redact_url("http://robot:secret@host:8090/x"),
            "http://***@host:8090/x"
        );
    }

    #[test]
    fn a_blank_configured_token_is_refused() {
        assert_eq!(configured_token(" t0k \n", "X").unwrap(), "t0k");
        for blank in ["", "   ", "\t\n"] {
            let e = configured_token(blank, "SLAG_EDGE_TOKEN").unwrap_err();
            assert!(matches!(e, Error::Param { name: "token", .. }), "{e}");
            assert!(e.to_string().contains("SLAG_EDGE_TOKEN"), "{e}");
        }
    }

    #[test]
    fn token_file_first_line_trimmed_and_never_empty() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t");
        std::fs::write(&p, "  abc \nsecond line\n").unwrap();
        assert_eq!(read_token_file(&p).unwrap(), "abc");
        std::fs::write(&p, "  \t\nabc\n").unwrap();
        assert!(read_token_file(&p).is_err());
        std::fs::write(&p, "\nabc\n").unwrap();
        let e = read_token_file(&p).unwrap_err().to_string();
        assert!(e.contains("first line"), "{e}");
        assert!(matches!(
            read_token_file(&dir.path().join("absent")),
            Err(Error::Io { .. })
        ));
    }
}
