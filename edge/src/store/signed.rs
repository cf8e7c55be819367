//! Signed manifests in the edge store ([`slag_common::shards::signature`]).
//!
//! A fetch with a trusted key commits, with the generation and in the same transaction, the
//! manifest bytes exactly as the server sent them (in the `manifests` tree, instead of their
//! re-serialisation) and the signature file that covers them (tree `signatures`, key `scene`),
//! and writes a copy of the signature beside the manifest copy (`manifest.sig` in the scene's
//! shard folder) for a rebuild of the database. A fetch without one removes both, so a stored
//! signature always belongs to the stored manifest bytes. `slag-edge check` re-verifies offline
//! ([`EdgeStore::verify_signed`]): the signature with the trusted key, then the SHA-256 of every
//! stored file of the committed generation.

use std::path::Path;
use std::sync::atomic::Ordering;

use slag_common::fault::boundary;
use slag_common::shards::signature::{
    ManifestSignature, TrustedKeys, check_hashes, compare_sha256, sha256_reader,
};
use slag_common::shards::{Manifest, TileInfo};
use slag_common::{Error, Result};

use super::{
    EdgeStore, FETCH_COPY, FetchRecord, MANIFEST_COPY, Stored, codebook_tile, read_regular,
    regular, sync_dir, write_atomic, write_durably,
};

/// Name of the signature copy in a scene's shard folder (module doc).
const SIGNATURE_COPY: &str = "manifest.sig";
/// The sled tree of stored signatures (module doc).
const SIGNATURES_TREE: &str = "signatures";

/// A manifest exactly as the server sent it, and the signature file that covers it, verified
/// with the trusted key by the fetch that holds it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SignedManifest {
    /// The manifest JSON bytes as served.
    pub bytes: Vec<u8>,
    /// The signature file ([`ManifestSignature`]).
    pub signature: Vec<u8>,
}

/// What [`EdgeStore::verify_signed`] found for a scene.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct SignatureCheck {
    /// The committed generation carries a signature.
    pub signed: bool,
    /// The key id the signature names (not itself trusted), when signed.
    pub key_id: Option<String>,
    /// The signature was checked with a trusted key and holds.
    pub verified: bool,
    /// Stored files of the committed generation whose SHA-256 was checked against the signed
    /// manifest (0 unless `verified`).
    pub files_hashed: usize,
}

/// The SHA-256 check of downloaded `bytes` of `tile` (a shard, or the codebook's pseudo tile)
/// against the signed `manifest`, before they are committed.
///
/// Errors: [`Error::Untrusted`] [`slag_common::Untrusted::ContentHash`] (or `Unhashed`).
pub(super) fn check_download(manifest: &Manifest, tile: &TileInfo, bytes: &[u8]) -> Result<()> {
    slag_common::shards::signature::check_sha256(
        tile.sha256.as_deref(),
        bytes,
        &file_name(manifest, tile),
        &format!("scene {}", manifest.scene_id),
    )
}

/// [`check_download`] for a digest already computed (`sha256`, 64 hex digits) of the bytes.
///
/// Errors: as [`check_download`].
pub(super) fn compare_download(manifest: &Manifest, tile: &TileInfo, sha256: &str) -> Result<()> {
    slag_common::shards::signature::compare_sha256(
        tile.sha256.as_deref(),
        sha256,
        &file_name(manifest, tile),
        &format!("scene {}", manifest.scene_id),
    )
}

/// "tile N" or "the codebook", for messages.
/// A stored file `what` whose SHA-256 (`got`) differs from the signed manifest's, as
/// [`EdgeStore::verify_signed`] reports it: the file was changed in the store after its commit
/// (not on the way, as for a download), so the message says what serves it and what repairs
/// it. Any other error `e` stays as it is.
fn stored_file_changed(e: Error, what: &str, got: &str, origin: &str) -> Error {
    match e {
        Error::Untrusted {
            what: slag_common::Untrusted::ContentHash,
            ..
        } => Error::untrusted(
            slag_common::Untrusted::ContentHash,
            origin,
            format!(
                "{what} has SHA-256 {got}, not the signed manifest's: the stored file was \
                 changed after its commit (its CRC-32s may still match). A server with the \
                 trusted key does not serve it; `slag-edge fetch --trusted-key` sets it aside \
                 and downloads it again when its disc covers the tile (the codebook: always), \
                 and drops it from a disc that does not"
            ),
        ),
        e => e,
    }
}

fn file_name(manifest: &Manifest, tile: &TileInfo) -> String {
    if manifest.mixture.is_some() && tile.id == slag_common::shards::CODEBOOK_TILE {
        "the codebook".into()
    } else {
        format!("tile {}", tile.id)
    }
}

impl EdgeStore {
    pub(super) fn signatures(&self) -> Result<sled::Tree> {
        self.db.open_tree(SIGNATURES_TREE).map_err(|e| self.err(e))
    }

    /// The signature file stored with `scene`'s committed generation; `None` when it was
    /// fetched without a trusted key (unsigned).
    ///
    /// Errors: store I/O.
    pub fn signature(&self, scene: &str) -> Result<Option<Vec<u8>>> {
        Ok(self
            .signatures()?
            .get(scene.as_bytes())
            .map_err(|e| self.err(e))?
            .map(|v| v.to_vec()))
    }

    /// The committed manifest's stored bytes (exactly as served for a signed generation).
    ///
    /// Errors: store I/O.
    pub fn manifest_bytes(&self, scene: &str) -> Result<Option<Vec<u8>>> {
        Ok(self
            .manifests
            .get(scene.as_bytes())
            .map_err(|e| self.err(e))?
            .map(|v| v.to_vec()))
    }

    /// [`Self::commit_fetch`] of a manifest fetched with a trusted key (`signed`: its bytes as
    /// served and their signature, which the caller verified): those bytes are stored as the
    /// manifest, the signature with them in the same transaction (module `signed`). `None`
    /// stores `manifest` re-serialised and removes any signature of the scene.
    ///
    /// Errors: as [`Self::commit_fetch`].
    pub fn commit_fetch_signed(
        &self,
        manifest: &Manifest,
        signed: Option<&SignedManifest>,
        record: &FetchRecord,
    ) -> Result<()> {
        use sled::Transactional;
        let m = signed.map_or_else(|| manifest.to_json(), |s| s.bytes.clone());
        let r = serde_json::to_vec(record).unwrap_or_default();
        let dir = self.ensure_scene_dir(&manifest.scene_id)?;
        write_atomic(&dir.join(MANIFEST_COPY), "store.manifest_copy", &m)?;
        self.write_signature_copy(&dir, signed)?;
        write_atomic(&dir.join(FETCH_COPY), "store.fetch_record_copy", &r)?;
        let key = manifest.scene_id.as_bytes();
        let signatures = self.signatures()?;
        (&self.manifests, &self.fetches, &signatures)
            .transaction(|(tm, tf, ts)| {
                tm.insert(key, m.as_slice())?;
                tf.insert(key, r.as_slice())?;
                match signed {
                    Some(s) => ts.insert(key, s.signature.as_slice())?,
                    None => ts.remove(key)?,
                };
                Ok::<(), sled::transaction::ConflictableTransactionError<()>>(())
            })
            .map_err(|e| match e {
                sled::transaction::TransactionError::Storage(e) => self.err(e),
                sled::transaction::TransactionError::Abort(()) => {
                    Error::internal("store transaction aborted")
                }
            })?;
        boundary("store.commit_fetch:transaction");
        self.db.flush().map_err(|e| self.err(e))?;
        boundary("store.commit_fetch:flush");
        self.commits.fetch_add(1, Ordering::SeqCst);
        Ok(())
    }

    /// The signature's part of a commit (module doc): writes the signature copy into the scene's
    /// folder `dir`, or removes a stale one for an unsigned commit.
    ///
    /// Errors: [`Error::Io`].
    pub(super) fn write_signature_copy(
        &self,
        dir: &Path,
        signed: Option<&SignedManifest>,
    ) -> Result<()> {
        let copy = dir.join(SIGNATURE_COPY);
        match signed {
            Some(s) => write_durably(
                &copy,
                &dir.join("manifest.sig.tmp"),
                "store.signature_copy",
                &s.signature,
            ),
            None => match std::fs::remove_file(&copy) {
                Ok(()) => {
                    boundary("store.signature_copy:remove");
                    sync_dir(dir)?;
                    boundary("store.signature_copy:dir_sync");
                    Ok(())
                }
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
                Err(e) => Err(Error::io(&copy, e)),
            },
        }
    }

    /// Rebuild of the database (module doc of the store): restores the signature of the scene
    /// stored under `key` from the copy in its shard folder `folder`, when there is one.
    ///
    /// Errors: store I/O.
    pub(super) fn restore_signature(&self, folder: &Path, key: &[u8]) -> Result<()> {
        let copy = folder.join(SIGNATURE_COPY);
        if let Ok(Some(sig)) = read_regular(
            &copy,
            slag_common::shards::signature::MAX_SIGNATURE_BYTES,
            "signature copy",
        ) {
            self.signatures()?
                .insert(key, sig)
                .map_err(|e| self.err(e))?;
            boundary("store.rebuild:insert_signature");
        }
        Ok(())
    }

    /// [`Self::check_stored`], and for a fetch with a trusted key (`signed`) also the SHA-256 of
    /// a file that passes it against the signed manifest: a file that differs (one stored by an
    /// unsigned fetch whose CRC-32 was made to match) is reported [`Stored::Damaged`], so the
    /// fetch sets it aside and downloads the tile again. The file is read once: its SHA-256 is
    /// computed in the same pass as its CRC-32.
    ///
    /// Errors: as [`Self::check_stored`].
    pub fn check_stored_signed(
        &self,
        manifest: &Manifest,
        tile: &TileInfo,
        signed: bool,
    ) -> Result<Stored> {
        use sha2::Digest;
        let mut hasher = sha2::Sha256::new();
        let state = self.check_stored_read(manifest, tile, signed.then_some(&mut hasher))?;
        if !signed || state != Stored::Verified {
            return Ok(state);
        }
        let got = regular::hex_digest(&hasher.finalize());
        Ok(match tile.sha256.as_deref() {
            Some(want) if want == got => Stored::Verified,
            want => Stored::Damaged {
                path: self.stored_path(manifest, tile)?,
                why: format!(
                    "SHA-256 {got}, the signed manifest says {}",
                    want.unwrap_or("none")
                ),
            },
        })
    }

    /// SHA-256 of the regular file at `path` (not through a link).
    fn file_sha256(&self, path: &Path) -> Result<String> {
        match regular::open_regular(path).map_err(|e| Error::io(path, e))? {
            regular::Opened::File(f, _) => sha256_reader(f).map_err(|e| Error::io(path, e)),
            _ => Err(Error::format(path, "not a regular file")),
        }
    }

    /// Re-verifies `scene`'s committed generation offline (module doc): without `key` it only
    /// reports whether the generation is signed and by which key id; with it, checks the
    /// signature against the stored manifest bytes, that the manifest names every file's
    /// SHA-256, and the SHA-256 of every stored file of the committed generation (missing
    /// files are `check`'s other report).
    ///
    /// Errors: [`Error::Untrusted`] for a signature that does not hold (another key, changed
    /// bytes) or a stored file whose SHA-256 differs; [`Error::Param`] `scene` for a scene never
    /// fetched; store I/O.
    pub fn verify_signed(&self, scene: &str, key: Option<&TrustedKeys>) -> Result<SignatureCheck> {
        let _generation = self.lock_generation();
        let committed = self.committed(scene)?;
        let Some(sig) = self.signature(scene)? else {
            return Ok(SignatureCheck {
                signed: false,
                key_id: None,
                verified: false,
                files_hashed: 0,
            });
        };
        let origin = format!("the store's manifest of scene {scene}");
        let key_id = ManifestSignature::from_json(&sig, &origin)?.key_id;
        let Some(key) = key else {
            return Ok(SignatureCheck {
                signed: true,
                key_id: Some(key_id),
                verified: false,
                files_hashed: 0,
            });
        };
        let bytes = self.manifest_bytes(scene)?.unwrap_or_default();
        key.verify(&bytes, &sig, &origin)?;
        let manifest = &committed.manifest;
        check_hashes(manifest, &origin)?;
        let mut files: Vec<TileInfo> = codebook_tile(manifest).into_iter().collect();
        files.extend(committed.tiles().into_iter().cloned());
        let mut files_hashed = 0;
        for t in &files {
            let path = self.stored_path(manifest, t)?;
            if std::fs::symlink_metadata(&path).is_err() {
                continue;
            }
            let got = self.file_sha256(&path)?;
            let what = format!("{} ({})", file_name(manifest, t), path.display());
            compare_sha256(t.sha256.as_deref(), &got, &what, &origin)
                .map_err(|e| stored_file_changed(e, &what, &got, &origin))?;
            files_hashed += 1;
        }
        Ok(SignatureCheck {
            signed: true,
            key_id: Some(key_id),
            verified: true,
            files_hashed,
        })
    }
}
