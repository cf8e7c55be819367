//! The store reads only regular files, and never more of one than it expects.
//!
//! Every file the store reads (shards, codebooks, partial downloads being committed, the manifest
//! and fetch-record copies) is opened with `O_NOFOLLOW | O_NONBLOCK`: a symbolic link in the
//! file's place is not followed (it fails with `ELOOP`, so a link to `/dev/zero` or out of the
//! store is never opened), and opening a FIFO does not wait for a writer. What was opened is then
//! checked with `fstat` (on the open descriptor, so nothing can be swapped in between) to be a
//! regular file; FIFOs, devices, sockets and folders are refused. Reads are bounded: at most one
//! byte more than the caller's limit (the manifest's stated length) is read, and a longer file is
//! refused, so no file can make the store read until memory runs out.

use std::io::Read;
use std::os::unix::fs::{FileTypeExt, OpenOptionsExt};
use std::path::Path;

use slag_common::{Error, Result};

/// What [`open_regular`] found at a path.
pub(crate) enum Opened {
    /// A regular file, open for reading, and its length in bytes.
    File(std::fs::File, u64),
    /// Nothing at the path.
    Missing,
    /// Something that is not a regular file; what it is, in words ("a FIFO", "a symbolic
    /// link", …).
    NotRegular(&'static str),
}

/// Names a file type for a message: "a folder", "a FIFO", "a symbolic link", …
pub(crate) fn kind_of(t: std::fs::FileType) -> &'static str {
    use std::fs::FileType;
    /// A test of a file type and the name it gives.
    type Kind = (fn(&FileType) -> bool, &'static str);
    const KINDS: [Kind; 7] = [
        (FileType::is_file, "a regular file"),
        (FileType::is_dir, "a folder"),
        (FileType::is_symlink, "a symbolic link"),
        (FileType::is_fifo, "a FIFO"),
        (FileType::is_char_device, "a character device"),
        (FileType::is_block_device, "a block device"),
        (FileType::is_socket, "a socket"),
    ];
    KINDS
        .iter()
        .find(|(is, _)| is(&t))
        .map_or("not a regular file", |&(_, name)| name)
}

/// Opens `path` for reading without following a symbolic link in its last component and
/// without blocking on a FIFO, then checks (`fstat` of the descriptor) that it is a regular file
/// (module doc).
///
/// Errors: the open or `fstat` failing for another reason than "nothing there" or "a link"
/// (permissions, I/O).
pub(crate) fn open_regular(path: &Path) -> std::io::Result<Opened> {
    let opened = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_CLOEXEC)
        .open(path);
    let f = match opened {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Opened::Missing),
        // O_NOFOLLOW on a symbolic link (dangling or not).
        Err(e) if e.raw_os_error() == Some(libc::ELOOP) => {
            return Ok(Opened::NotRegular(
                "a symbolic link (the store follows none)",
            ));
        }
        // Opening a Unix socket.
        Err(e) if e.raw_os_error() == Some(libc::ENXIO) => {
            return Ok(Opened::NotRegular("a socket"));
        }
        Err(e) => return Err(e),
    };
    let meta = f.metadata()?;
    if meta.is_file() {
        Ok(Opened::File(f, meta.len()))
    } else {
        Ok(Opened::NotRegular(kind_of(meta.file_type())))
    }
}

/// Reads at most `max + 1` bytes of `f` (the extra byte tells a file longer than `max`).
///
/// Errors: read errors.
pub(crate) fn read_bounded(f: std::fs::File, max: u64) -> std::io::Result<Vec<u8>> {
    let mut out = Vec::new();
    f.take(max.saturating_add(1)).read_to_end(&mut out)?;
    Ok(out)
}

/// Reads `f` to its end, but never more than `max + 1` bytes, 1 MiB at a time (a smaller
/// buffer for a smaller `max`): the CRC-32 of every byte read, its first `head_bytes` bytes, and
/// how many bytes were read. With `sha256`, the same bytes are hashed in the same pass (for a
/// trusted key: one read of the file gives both digests).
pub(crate) fn crc_and_head(
    f: std::fs::File,
    max: u64,
    head_bytes: usize,
    mut sha256: Option<&mut sha2::Sha256>,
) -> std::io::Result<(u32, Vec<u8>, u64)> {
    use sha2::Digest;
    let mut f = f.take(max.saturating_add(1));
    let mut crc = crc32fast::Hasher::new();
    let mut head: Vec<u8> = Vec::new();
    let mut buf = vec![0u8; max.saturating_add(1).min(1 << 20) as usize];
    let mut total = 0u64;
    loop {
        let n = match f.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        crc.update(&buf[..n]);
        if let Some(h) = sha256.as_deref_mut() {
            h.update(&buf[..n]);
        }
        if head.len() < head_bytes {
            let take = n.min(head_bytes - head.len());
            head.extend_from_slice(&buf[..take]);
        }
        total += n as u64;
    }
    Ok((crc.finalize(), head, total))
}

/// Lowercase hex of a digest (64 digits for a SHA-256), as manifests write it.
pub(crate) fn hex_digest(digest: &[u8]) -> String {
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

/// The refusal of something at `path` that is not a regular file (`what`: the file's role,
/// e.g. "shard 3 of scene s").
pub(crate) fn not_regular(path: &Path, what: &str, kind: &str) -> Error {
    Error::format(
        path,
        format!(
            "{what}: {kind} where a regular file belongs; the store reads only regular files: \
             run `slag-edge fetch` again to replace it (or remove it)"
        ),
    )
}

/// Reads the regular file at `path` (`what` names it in messages), at most `max` bytes;
/// `None` when nothing is there (module doc).
///
/// Errors: [`Error::Format`] naming `path` for a symbolic link, FIFO, device, socket or folder in
/// the file's place, or a file longer than `max` bytes (the length a manifest states);
/// [`Error::Io`] when it cannot be opened or read.
pub fn read_regular(path: &Path, max: u64, what: &str) -> Result<Option<Vec<u8>>> {
    let (f, _) = match open_regular(path).map_err(|e| Error::io(path, e))? {
        Opened::File(f, len) => (f, len),
        Opened::Missing => return Ok(None),
        Opened::NotRegular(kind) => return Err(not_regular(path, what, kind)),
    };
    let bytes = read_bounded(f, max).map_err(|e| Error::io(path, e))?;
    if bytes.len() as u64 > max {
        return Err(Error::format(
            path,
            format!(
                "{what}: longer than the {max} bytes expected; run `slag-edge fetch` again to \
                 replace it"
            ),
        ));
    }
    Ok(Some(bytes))
}

/// Why the store's database folder `db` cannot be handed to sled: the folder itself, or
/// something under it, is not a folder or a regular file (a symbolic link, FIFO, device,
/// socket); `None` when all are, or when there is no folder yet.
pub(crate) fn db_not_regular(db: &Path) -> Option<String> {
    let mut stack = vec![db.to_path_buf()];
    while let Some(dir) = stack.pop() {
        let meta = match std::fs::symlink_metadata(&dir) {
            Ok(m) => m,
            Err(_) => continue,
        };
        if !meta.is_dir() {
            return Some(format!(
                "{} is {}, not a folder",
                dir.display(),
                kind_of(meta.file_type())
            ));
        }
        let Ok(rd) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in rd.flatten() {
            let Ok(t) = e.file_type() else {
                continue;
            };
            if t.is_dir() {
                stack.push(e.path());
            } else if !t.is_file() {
                return Some(format!("{} is {}", e.path().display(), kind_of(t)));
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One pass gives the CRC-32, the head and, when asked, the SHA-256 of the bytes read;
    /// never more than `max + 1` of them, over several reads of the buffer.
    #[test]
    fn one_read_gives_the_crc_the_head_and_the_sha256() {
        use sha2::Digest;
        let d = tempfile::tempdir().expect("tempdir");
        let file = d.path().join("f");
        let bytes: Vec<u8> = (0..(3 << 20) + 17)
            .map(|i: u32| (i * 7 + i / 251) as u8)
            .collect();
        std::fs::write(&file, &bytes).expect("write");
        let open = || std::fs::File::open(&file).expect("open");
        let len = bytes.len() as u64;
        let mut h = sha2::Sha256::new();
        let (crc, head, total) = crc_and_head(open(), len, 64, Some(&mut h)).expect("read");
        assert_eq!(
            (crc, &head[..], total),
            (crc32fast::hash(&bytes), &bytes[..64], len)
        );
        assert_eq!(
            hex_digest(&h.finalize()),
            slag_common::shards::signature::sha256_hex(&bytes)
        );
        let (crc_alone, _, _) = crc_and_head(open(), len, 64, None).expect("read");
        assert_eq!(crc_alone, crc);
        // A file longer than `max`: `max + 1` bytes read and hashed, no more.
        let mut h = sha2::Sha256::new();
        let (_, _, total) = crc_and_head(open(), 1000, 64, Some(&mut h)).expect("read");
        assert_eq!(total, 1001);
        assert_eq!(
            hex_digest(&h.finalize()),
            slag_common::shards::signature::sha256_hex(&bytes[..1001])
        );
    }

    #[test]
    fn only_regular_files_are_read_and_never_past_the_limit() {
        let d = tempfile::tempdir().expect("tempdir");
        let file = d.path().join("f");
        std::fs::write(&file, b"0123456789").expect("write");
        assert_eq!(
            read_regular(&file, 10, "f").expect("read").as_deref(),
            Some(&b"0123456789"[..])
        );
        let long = read_regular(&file, 9, "f").expect_err("longer");
        assert!(
            long.to_string().contains("longer than the 9 bytes"),
            "{long}"
        );
        assert!(
            read_regular(&d.path().join("none"), 10, "f")
                .expect("missing")
                .is_none()
        );
        /// A kind of entry that is not a regular file, and how to make one at a path.
        type Case<'a> = (&'a str, &'a dyn Fn(&Path));
        let cases: [Case<'_>; 4] = [
            ("symbolic link", &|p| {
                std::os::unix::fs::symlink("/dev/zero", p).expect("link")
            }),
            ("symbolic link", &|p| {
                std::os::unix::fs::symlink("/nonexistent/x", p).expect("link")
            }),
            ("folder", &|p| std::fs::create_dir(p).expect("dir")),
            ("FIFO", &|p| {
                let s = std::process::Command::new("mkfifo")
                    .arg(p)
                    .status()
                    .expect("mkfifo");
                assert!(s.success());
            }),
        ];
        for (i, (kind, make)) in cases.iter().enumerate() {
            let p = d.path().join(format!("x{i}"));
            make(&p);
            // Returns at once (a FIFO without a writer would block a plain open).
            let e = read_regular(&p, 1 << 20, "shard 3").expect_err(kind);
            assert!(matches!(e, Error::Format { .. }), "{e}");
            let m = e.to_string();
            assert!(m.contains(kind) && m.contains("shard 3"), "{m}");
            assert!(m.contains("slag-edge fetch"), "{m}");
        }
        // The database check names a link inside the folder.
        let db = d.path().join("db");
        std::fs::create_dir(&db).expect("db");
        std::fs::write(db.join("conf"), b"x").expect("conf");
        assert_eq!(db_not_regular(&db), None);
        std::os::unix::fs::symlink("/dev/zero", db.join("snap.0")).expect("link");
        let why = db_not_regular(&db).expect("a link");
        assert!(
            why.contains("snap.0") && why.contains("symbolic link"),
            "{why}"
        );
    }
}
