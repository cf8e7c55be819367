//! Partial files: what a previous run left of a tile, continued with a `Range` request (and
//! `If-Range`) or started over, and each received chunk appended.

use std::path::Path;

use slag_common::Error;
use slag_common::fault::boundary;
use slag_common::shards::TileInfo;
use tokio::io::AsyncWriteExt;

use super::client::{Attempt, permanent, transient};

/// Appends one received chunk to a partial file (through the disk-full hook,
/// [`slag_common::fault::enospc`]).
pub(super) async fn write_chunk(file: &mut tokio::fs::File, chunk: &[u8]) -> std::io::Result<()> {
    slag_common::fault::enospc()?;
    file.write_all(chunk).await
}

/// The bytes the partial file `part` already holds of `tile` (0 for none); a file longer than
/// the tile is removed and counts as none.
///
/// Errors: the removal ([`Error::Io`], not transient).
pub(super) async fn partial_prefix(
    part: &Path,
    tile: &TileInfo,
) -> std::result::Result<u64, Attempt> {
    match tokio::fs::symlink_metadata(part).await {
        Ok(m) if m.len() <= tile.bytes => Ok(m.len()),
        Ok(_) => {
            tokio::fs::remove_file(part)
                .await
                .map_err(|e| permanent(Error::io(part, e)))?;
            boundary("fetch.partial:remove_oversized");
            Ok(0)
        }
        Err(_) => Ok(0),
    }
}

/// Opens `to.part` for the body of `resp`: appending after its `have` bytes when the server
/// honoured the `Range` request (206 with the asked `Content-Range`), else created empty for a
/// whole body (2xx). Returns `(file, bytes already in it, resumed)`; `None` for a status that
/// is no success. Never through a link (`O_NOFOLLOW`).
///
/// Errors: a 206 with another `Content-Range` (the file is removed; transient: starting over),
/// opening the file ([`Error::Io`]).
pub(super) async fn open_partial(
    resp: &reqwest::Response,
    to: &TileFetch<'_>,
    have: u64,
) -> std::result::Result<Option<(tokio::fs::File, u64, bool)>, Attempt> {
    let (url, part) = (to.url, to.part);
    let io = |e: std::io::Error| permanent(Error::io(part, e));
    let status = resp.status();
    if status == reqwest::StatusCode::PARTIAL_CONTENT && have > 0 {
        let cr = resp
            .headers()
            .get(reqwest::header::CONTENT_RANGE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("");
        if !cr.starts_with(&format!("bytes {have}-")) {
            return Err(transient(Error::network(
                url,
                format!("asked for bytes {have}- but got Content-Range {cr:?}; starting over"),
            )))
            .inspect_err(|_| {
                let _ = std::fs::remove_file(part);
            });
        }
        // Never through a link (set aside above; O_NOFOLLOW closes the gap since).
        let f = tokio::fs::OpenOptions::new()
            .append(true)
            .custom_flags(libc::O_NOFOLLOW)
            .open(part)
            .await
            .map_err(io)?;
        Ok(Some((f, have, true)))
    } else if status.is_success() {
        let f = tokio::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .custom_flags(libc::O_NOFOLLOW)
            .open(part)
            .await
            .map_err(io)?;
        boundary("fetch.partial:create");
        Ok(Some((f, 0, false)))
    } else {
        Ok(None)
    }
}

/// One tile's download: where from, where to, what it must be.
pub(super) struct TileFetch<'a> {
    pub(super) url: &'a str,
    pub(super) part: &'a Path,
    pub(super) tile: &'a TileInfo,
}
