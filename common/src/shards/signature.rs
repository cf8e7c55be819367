//! Signed shard manifests: the publisher's Ed25519 key pair, the detached signature of a
//! manifest, and the SHA-256 of every file a manifest lists.
//!
//! # What is signed
//!
//! The exact bytes of the manifest as served (`GET /v1/scenes/{scene}/manifest`, `manifest.json`
//! of an export). They name the scene id, the generation, and every tile's length, CRC-32 and
//! SHA-256 ([`super::TileInfo::sha256`]; a mixture scene's codebook too,
//! [`super::MixtureInfo::codebook_sha256`]), so one signature over a few kilobytes vouches for
//! every byte of the scene, and for which generation it is.
//!
//! # Files
//!
//! - private key: PKCS#8 v1 PEM (RFC 5208, `-----BEGIN PRIVATE KEY-----`, the public key not
//!   embedded, file mode 0600), [`PRIVATE_KEY_FILE`]; a key of `openssl genpkey -algorithm
//!   ed25519` reads the same;
//! - public key: SubjectPublicKeyInfo PEM (`-----BEGIN PUBLIC KEY-----`), [`PUBLIC_KEY_FILE`];
//!   OpenSSL 3.0 and later read both (`openssl pkey -in manifest-key.pem -noout`,
//!   `openssl pkey -pubin -in manifest-key.pub.pem -noout`);
//! - trusted keys: a robot trusts one or more public keys ([`TrustedKeys`]: several PEM blocks in
//!   one file, or several files), so a publisher can rotate its key (docs/guide/security.md);
//! - signature (`manifest.sig` beside an exported `manifest.json`,
//!   `GET /v1/scenes/{scene}/manifest.sig`): JSON [`ManifestSignature`], format
//!   [`SIGNATURE_FORMAT`] version [`SIGNATURE_VERSION`]: `algorithm` `"ed25519"`, `key_id` (16
//!   hex digits: the first 8 bytes of the SHA-256 of the raw 32-byte public key) and `signature`
//!   (128 hex digits: the 64-byte Ed25519 signature of the manifest bytes). The key id only names
//!   the key in messages; what is trusted is the signature checked with the trusted key. With
//!   OpenSSL: `jq -r .signature manifest.sig | xxd -r -p > sig.bin` then
//!   `openssl pkeyutl -verify -pubin -inkey manifest-key.pub.pem -rawin -in manifest.json
//!   -sigfile sig.bin`.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use ed25519_dalek::pkcs8::spki::der::pem::LineEnding;
use ed25519_dalek::pkcs8::{DecodePrivateKey, DecodePublicKey, EncodePrivateKey, EncodePublicKey};
use ed25519_dalek::{Signer, Verifier};
use sha2::Digest;

use super::Manifest;
use crate::{Error, Result, Untrusted};

/// `format` of a signature file.
pub const SIGNATURE_FORMAT: &str = "slag-manifest-signature";
/// Version of the signature file's layout.
pub const SIGNATURE_VERSION: u32 = 1;
/// The one signature algorithm.
pub const ALGORITHM: &str = "ed25519";
/// Largest signature file read (bytes); a real one is about 250.
pub const MAX_SIGNATURE_BYTES: u64 = 4096;
/// File name of the private key `keygen` writes.
pub const PRIVATE_KEY_FILE: &str = "manifest-key.pem";
/// File name of the public key `keygen` writes (what robots trust).
pub const PUBLIC_KEY_FILE: &str = "manifest-key.pub.pem";
/// Largest key file read (bytes).
const MAX_KEY_FILE_BYTES: u64 = 16 * 1024;

/// SHA-256 of `bytes` as 64 lowercase hex digits (the manifest's `sha256` fields).
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&sha2::Sha256::digest(bytes))
}

/// SHA-256 of everything `r` yields, as [`sha256_hex`], read 1 MiB at a time.
///
/// Errors: the reader's.
pub fn sha256_reader(mut r: impl Read) -> std::io::Result<String> {
    let mut h = sha2::Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        match r.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => h.update(&buf[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(hex(&h.finalize()))
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(s: &str) -> Option<Vec<u8>> {
    if !s.len().is_multiple_of(2) || !s.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).ok())
        .collect()
}

/// True for 64 lowercase hex digits.
fn is_sha256_hex(s: &str) -> bool {
    s.len() == 64 && s.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'))
}

/// The key id of a public key: hex of the first 8 bytes of the SHA-256 of its 32 raw bytes.
fn key_id_of(key: &ed25519_dalek::VerifyingKey) -> String {
    sha256_hex(key.as_bytes())[..16].to_string()
}

/// A key file's text, at most [`MAX_KEY_FILE_BYTES`].
fn read_key_text(path: &Path, what: &str) -> Result<String> {
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut text = String::new();
    f.take(MAX_KEY_FILE_BYTES + 1)
        .read_to_string(&mut text)
        .map_err(|e| match e.kind() {
            std::io::ErrorKind::InvalidData => {
                Error::format(path, format!("not a PEM {what} (not text)"))
            }
            _ => Error::io(path, e),
        })?;
    if text.len() as u64 > MAX_KEY_FILE_BYTES {
        return Err(Error::format(
            path,
            format!("larger than {MAX_KEY_FILE_BYTES} bytes: not a PEM {what}"),
        ));
    }
    Ok(text)
}

/// The publisher's private key: signs manifests ([`SigningKey::sign`]).
pub struct SigningKey(ed25519_dalek::SigningKey);

impl std::fmt::Debug for SigningKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SigningKey")
            .field("key_id", &self.key_id())
            .finish_non_exhaustive()
    }
}

impl SigningKey {
    /// A new random key from the operating system's generator.
    pub fn generate() -> SigningKey {
        SigningKey(ed25519_dalek::SigningKey::generate(&mut rand_core::OsRng))
    }

    /// Reads an Ed25519 private key from a PKCS#8 PEM file (as [`keygen`] and
    /// `openssl genpkey -algorithm ed25519` write). See [`readable_by_others`] for a file that
    /// others may read.
    ///
    /// Errors: [`Error::Io`] when it cannot be read; [`Error::Format`] when it is not an Ed25519
    /// private key in PEM (a public key, another algorithm, garbage), naming what was found.
    pub fn read_pem(path: &Path) -> Result<SigningKey> {
        let text = read_key_text(path, "private key")?;
        let key = ed25519_dalek::SigningKey::from_pkcs8_pem(&text).map_err(|e| {
            let found = if text.contains("BEGIN PUBLIC KEY") {
                "this is a public key; signing needs the private key file of the pair".into()
            } else {
                format!("{e}")
            };
            Error::format(
                path,
                format!(
                    "not an Ed25519 private key in PKCS#8 PEM (-----BEGIN PRIVATE KEY-----): \
                     {found}; make a key pair with the keygen subcommand"
                ),
            )
        })?;
        Ok(SigningKey(key))
    }

    /// The public half, what robots trust.
    pub fn public(&self) -> TrustedKey {
        TrustedKey(self.0.verifying_key())
    }

    /// The key id ([`ManifestSignature::key_id`]).
    pub fn key_id(&self) -> String {
        key_id_of(&self.0.verifying_key())
    }

    /// Signs `manifest_bytes`, the exact bytes that are served.
    pub fn sign(&self, manifest_bytes: &[u8]) -> ManifestSignature {
        ManifestSignature {
            format: SIGNATURE_FORMAT.into(),
            version: SIGNATURE_VERSION,
            algorithm: ALGORITHM.into(),
            key_id: self.key_id(),
            signature: hex(&self.0.sign(manifest_bytes).to_bytes()),
        }
    }
}

/// The permission bits of `path` when users other than its owner may read or write it (a private
/// key should be mode 0600); `None` when they may not, or on systems without Unix modes.
pub fn readable_by_others(path: &Path) -> Option<u32> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(path).ok()?.permissions().mode() & 0o777;
        (mode & 0o077 != 0).then_some(mode)
    }
    #[cfg(not(unix))]
    {
        let _ = path;
        None
    }
}

/// A publisher's public key that a robot trusts: what it checks signatures with.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TrustedKey(ed25519_dalek::VerifyingKey);

impl TrustedKey {
    /// Reads an Ed25519 public key from a SubjectPublicKeyInfo PEM file (as [`keygen`] and
    /// `openssl pkey -pubout` write).
    ///
    /// Errors: [`Error::Io`] when it cannot be read; [`Error::Format`] when it is not an Ed25519
    /// public key in PEM (a private key, another algorithm, garbage).
    pub fn read_pem(path: &Path) -> Result<TrustedKey> {
        let text = read_key_text(path, "public key")?;
        TrustedKey::from_pem_text(&text, path)
    }

    /// [`Self::read_pem`] of the PEM `text` read from `path`.
    fn from_pem_text(text: &str, path: &Path) -> Result<TrustedKey> {
        let key = ed25519_dalek::VerifyingKey::from_public_key_pem(text).map_err(|e| {
            let found = if text.contains("PRIVATE KEY") {
                "this is a private key; a robot trusts the public key file of the pair \
                 (keep the private one on the publisher)"
                    .into()
            } else {
                format!("{e}")
            };
            Error::format(
                path,
                format!("not an Ed25519 public key in PEM (-----BEGIN PUBLIC KEY-----): {found}"),
            )
        })?;
        Ok(TrustedKey(key))
    }

    /// The key id ([`ManifestSignature::key_id`]).
    pub fn key_id(&self) -> String {
        key_id_of(&self.0)
    }

    /// Checks that `signature` (the bytes of a signature file) is this key's signature of
    /// exactly `manifest_bytes`; `origin` names where the manifest came from in errors.
    ///
    /// Errors: [`Error::Untrusted`] [`Untrusted::OtherKey`] when the signature names another
    /// key, [`Untrusted::BadSignature`] when it is not a signature file or does not verify.
    pub fn verify(&self, manifest_bytes: &[u8], signature: &[u8], origin: &str) -> Result<()> {
        let sig = ManifestSignature::from_json(signature, origin)?;
        if sig.key_id != self.key_id() {
            return Err(Error::untrusted(
                Untrusted::OtherKey,
                origin,
                format!(
                    "the manifest is signed by key {}, the trusted key is {}: trust the \
                     publisher's public key, or have the publisher sign with the key you trust",
                    sig.key_id,
                    self.key_id()
                ),
            ));
        }
        let bytes: [u8; 64] = unhex(&sig.signature)
            .and_then(|b| b.try_into().ok())
            .ok_or_else(|| {
                Error::untrusted(
                    Untrusted::BadSignature,
                    origin,
                    "the signature is not 128 hex digits: the signature file is damaged",
                )
            })?;
        self.0
            .verify(
                manifest_bytes,
                &ed25519_dalek::Signature::from_bytes(&bytes),
            )
            .map_err(|_| {
                Error::untrusted(
                    Untrusted::BadSignature,
                    origin,
                    format!(
                        "the signature of key {} does not match these manifest bytes: the \
                         manifest was changed after it was signed; do not use this server's \
                         copy, fetch from the publisher again",
                        sig.key_id
                    ),
                )
            })
    }
}

/// The public keys a robot trusts (module doc, "Files"): a manifest signed by any of them is
/// accepted. One key normally; two while a publisher rotates (the old key kept until every
/// generation is signed by the new one).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TrustedKeys(Vec<TrustedKey>);

impl From<TrustedKey> for TrustedKeys {
    fn from(key: TrustedKey) -> TrustedKeys {
        TrustedKeys(vec![key])
    }
}

impl TrustedKeys {
    /// The keys of `keys`, in order, each once.
    ///
    /// Errors: [`Error::Param`] `trusted_key` for an empty list.
    pub fn new(keys: Vec<TrustedKey>) -> Result<TrustedKeys> {
        let mut unique: Vec<TrustedKey> = Vec::with_capacity(keys.len());
        for k in keys {
            if !unique.contains(&k) {
                unique.push(k);
            }
        }
        if unique.is_empty() {
            return Err(Error::param(
                "trusted_key",
                "no key",
                "at least one Ed25519 public key (PEM)",
            ));
        }
        Ok(TrustedKeys(unique))
    }

    /// Every `-----BEGIN PUBLIC KEY-----` block of each file of `paths` (a file may hold several
    /// keys, one PEM block after the other).
    ///
    /// Errors: as [`TrustedKey::read_pem`] for a file or a block; [`Error::Format`] for a file
    /// without a public key block; [`Error::Param`] `trusted_key` for no file.
    pub fn read_pem_files(paths: &[PathBuf]) -> Result<TrustedKeys> {
        let mut keys = Vec::new();
        for path in paths {
            keys.extend(read_public_key_blocks(path)?);
        }
        TrustedKeys::new(keys)
    }

    /// The trusted keys' ids ([`TrustedKey::key_id`]), in order.
    pub fn key_ids(&self) -> Vec<String> {
        self.0.iter().map(TrustedKey::key_id).collect()
    }

    /// Checks that `signature` (a signature file's bytes) is the signature of exactly
    /// `manifest_bytes` by the trusted key it names ([`TrustedKey::verify`]); `origin` names
    /// where the manifest came from in errors.
    ///
    /// Errors: [`Error::Untrusted`] [`Untrusted::OtherKey`] when the signature names a key that is
    /// not trusted (the message lists the trusted ones), [`Untrusted::BadSignature`] when it is
    /// not a signature file or does not verify.
    pub fn verify(&self, manifest_bytes: &[u8], signature: &[u8], origin: &str) -> Result<()> {
        let sig = ManifestSignature::from_json(signature, origin)?;
        match self.0.iter().find(|k| k.key_id() == sig.key_id) {
            Some(k) => k.verify(manifest_bytes, signature, origin),
            None => Err(Error::untrusted(
                Untrusted::OtherKey,
                origin,
                format!(
                    "the manifest is signed by key {}, the trusted key(s) are {}: trust the \
                     publisher's public key, or have the publisher sign with a key you trust",
                    sig.key_id,
                    self.key_ids().join(", ")
                ),
            )),
        }
    }
}

/// The public keys of the PEM blocks of `path` (module doc, "Files").
///
/// Errors: as [`TrustedKey::read_pem`]; [`Error::Format`] for a file without a public key block.
fn read_public_key_blocks(path: &Path) -> Result<Vec<TrustedKey>> {
    const END: &str = "-----END PUBLIC KEY-----";
    let text = read_key_text(path, "public key")?;
    let mut keys = Vec::new();
    let mut rest = text.as_str();
    while let Some(start) = rest.find("-----BEGIN PUBLIC KEY-----") {
        let Some(end) = rest[start..].find(END).map(|e| start + e + END.len()) else {
            break;
        };
        keys.push(TrustedKey::from_pem_text(&rest[start..end], path)?);
        rest = &rest[end..];
    }
    if keys.is_empty() {
        // What the single-key reader says of the file (a private key, garbage, ...).
        keys.push(TrustedKey::from_pem_text(&text, path)?);
    }
    Ok(keys)
}

/// A detached manifest signature (module doc, "Files").
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ManifestSignature {
    /// Always [`SIGNATURE_FORMAT`].
    pub format: String,
    /// [`SIGNATURE_VERSION`].
    pub version: u32,
    /// Always [`ALGORITHM`].
    pub algorithm: String,
    /// 16 hex digits naming the signing key (module doc); not itself trusted.
    pub key_id: String,
    /// The 64-byte Ed25519 signature of the manifest bytes, 128 lowercase hex digits.
    pub signature: String,
}

impl ManifestSignature {
    /// The signature file's bytes (pretty JSON and a newline).
    pub fn to_json(&self) -> Vec<u8> {
        let mut v = serde_json::to_vec_pretty(self).unwrap_or_default();
        v.push(b'\n');
        v
    }

    /// Parses a signature file.
    ///
    /// Errors: [`Error::Untrusted`] [`Untrusted::BadSignature`] for more than
    /// [`MAX_SIGNATURE_BYTES`], JSON that is not a signature, another format, version or
    /// algorithm.
    pub fn from_json(bytes: &[u8], origin: &str) -> Result<ManifestSignature> {
        let bad = |m: String| Error::untrusted(Untrusted::BadSignature, origin, m);
        if bytes.len() as u64 > MAX_SIGNATURE_BYTES {
            return Err(bad(format!(
                "the signature file has {} bytes, more than {MAX_SIGNATURE_BYTES}: not a slag \
                 manifest signature",
                bytes.len()
            )));
        }
        let s: ManifestSignature = serde_json::from_slice(bytes)
            .map_err(|e| bad(format!("not a slag manifest signature: {e}")))?;
        if s.format != SIGNATURE_FORMAT
            || s.version != SIGNATURE_VERSION
            || s.algorithm != ALGORITHM
        {
            return Err(bad(format!(
                "signature {} v{} ({}), expected {SIGNATURE_FORMAT} v{SIGNATURE_VERSION} \
                 ({ALGORITHM}): upgrade slag, or have the publisher sign again",
                s.format, s.version, s.algorithm
            )));
        }
        Ok(s)
    }
}

/// The two files [`keygen`] wrote.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct KeyPairFiles {
    /// The private key (mode 0600): stays with the publisher.
    pub private: PathBuf,
    /// The public key: what robots trust.
    pub public: PathBuf,
    /// The pair's key id.
    pub key_id: String,
}

/// Writes a new key pair into `dir` (created if missing): [`PRIVATE_KEY_FILE`] (mode 0600) and
/// [`PUBLIC_KEY_FILE`], each synced. Existing key files are never overwritten.
///
/// Errors: [`Error::Param`] `key_out` when either file exists already (nothing is written);
/// [`Error::Io`] when the folder or a file cannot be written (a private key written before a
/// failing public one is removed again).
pub fn keygen(dir: &Path) -> Result<KeyPairFiles> {
    let (private, public) = (dir.join(PRIVATE_KEY_FILE), dir.join(PUBLIC_KEY_FILE));
    for p in [&private, &public] {
        if std::fs::symlink_metadata(p).is_ok() {
            return Err(Error::param(
                "key_out",
                p.display(),
                "a folder without a key pair: key files are never overwritten (move the old \
                 pair away first, or write the new one elsewhere)",
            ));
        }
    }
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let key = SigningKey::generate();
    let private_pem = private_key_pem(&key)?;
    let public_pem = key
        .0
        .verifying_key()
        .to_public_key_pem(LineEnding::LF)
        .map_err(|e| Error::internal(format!("encoding the public key: {e}")))?;
    write_new(&private, private_pem.as_bytes(), 0o600)?;
    if let Err(e) = write_new(&public, public_pem.as_bytes(), 0o644) {
        let _ = std::fs::remove_file(&private);
        return Err(e);
    }
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
    Ok(KeyPairFiles {
        private,
        public,
        key_id: key.key_id(),
    })
}

/// The private key as PKCS#8 v1 PEM (RFC 5208 `PrivateKeyInfo`: the 32-byte seed, no public key
/// embedded), the form `openssl genpkey -algorithm ed25519` writes and every OpenSSL 3 reads;
/// the v2 form with the public key embedded (RFC 5958) is refused by OpenSSL 3.0 ("unsupported").
///
/// Errors: [`Error::Internal`] when the encoder fails.
fn private_key_pem(key: &SigningKey) -> Result<impl std::ops::Deref<Target = String>> {
    let v1 = ed25519_dalek::pkcs8::KeypairBytes {
        secret_key: key.0.to_bytes(),
        public_key: None,
    };
    v1.to_pkcs8_pem(LineEnding::LF)
        .map_err(|e| Error::internal(format!("encoding the private key: {e}")))
}

/// Creates `path` (failing if anything is there) with `mode`, writes `bytes` and syncs it.
fn write_new(path: &Path, bytes: &[u8], mode: u32) -> Result<()> {
    let mut o = std::fs::OpenOptions::new();
    o.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        o.mode(mode);
    }
    #[cfg(not(unix))]
    let _ = mode;
    let mut f = o.open(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::AlreadyExists => Error::param(
            "key_out",
            path.display(),
            "a folder without a key pair: key files are never overwritten",
        ),
        _ => Error::io(path, e),
    })?;
    f.write_all(bytes).and_then(|_| f.sync_all()).map_err(|e| {
        let _ = std::fs::remove_file(path);
        Error::io(path, e)
    })
}

/// Checks that a signed manifest names the SHA-256 of every file it lists (each tile, and a
/// mixture scene's codebook), so that its signature covers their content.
///
/// Errors: [`Error::Untrusted`] [`Untrusted::Unhashed`] naming the first file without one (or
/// with one that is not 64 lowercase hex digits).
pub fn check_hashes(manifest: &Manifest, origin: &str) -> Result<()> {
    let missing = |what: String| {
        Err(Error::untrusted(
            Untrusted::Unhashed,
            origin,
            format!(
                "{what} has no SHA-256 (64 hex digits) in the signed manifest, so the signature \
                 does not cover its bytes: the publisher has to partition again with a slag \
                 that writes them"
            ),
        ))
    };
    for t in &manifest.tiles {
        if !t.sha256.as_deref().is_some_and(is_sha256_hex) {
            return missing(format!("tile {}", t.id));
        }
    }
    if let Some(x) = &manifest.mixture
        && !x.codebook_sha256.as_deref().is_some_and(is_sha256_hex)
    {
        return missing("the codebook".into());
    }
    Ok(())
}

/// Checks `bytes` (file `what` of scene `scene`) against the SHA-256 its signed manifest names.
///
/// Errors: [`Error::Untrusted`] [`Untrusted::ContentHash`] naming both digests;
/// [`Untrusted::Unhashed`] when the manifest names none.
pub fn check_sha256(expected: Option<&str>, bytes: &[u8], what: &str, origin: &str) -> Result<()> {
    compare_sha256(expected, &sha256_hex(bytes), what, origin)
}

/// [`check_sha256`] for a digest already computed (`got`, 64 hex digits), e.g. by
/// [`sha256_reader`].
///
/// Errors: as [`check_sha256`].
pub fn compare_sha256(expected: Option<&str>, got: &str, what: &str, origin: &str) -> Result<()> {
    let Some(want) = expected else {
        return Err(Error::untrusted(
            Untrusted::Unhashed,
            origin,
            format!("{what} has no SHA-256 in the signed manifest"),
        ));
    };
    if got == want {
        return Ok(());
    }
    Err(Error::untrusted(
        Untrusted::ContentHash,
        origin,
        format!(
            "{what} has SHA-256 {got}, the signed manifest says {want}: its bytes are not the \
             ones the publisher signed (changed on the way, or another file); nothing of this \
             generation was used, fetch again from a server you trust"
        ),
    ))
}

/// Refuses a signed manifest of generation `offered` for `scene` when the store already holds
/// generation `held` > `offered`: a replay of an older signed manifest.
///
/// Errors: [`Error::Untrusted`] [`Untrusted::Replay`].
pub fn check_generation(scene: &str, held: u64, offered: u64, origin: &str) -> Result<()> {
    if offered >= held {
        return Ok(());
    }
    Err(Error::untrusted(
        Untrusted::Replay,
        origin,
        format!(
            "the server offers generation {offered} of scene {scene}, older than generation \
             {held} this store holds: an old signed manifest replayed; the store keeps \
             generation {held}. If the publisher really started over (a new shard store), \
             fetch into a new store folder"
        ),
    ))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn keygen_sign_verify_round_trip_and_refusals() {
        let dir = tempfile::tempdir().unwrap();
        let files = keygen(dir.path()).unwrap();
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(&files.private)
                .unwrap()
                .permissions()
                .mode();
            assert_eq!(mode & 0o777, 0o600);
        }
        let key = SigningKey::read_pem(&files.private).unwrap();
        let trusted = TrustedKey::read_pem(&files.public).unwrap();
        assert_eq!(key.public(), trusted);
        assert_eq!(trusted.key_id(), files.key_id);
        let manifest = br#"{"scene_id": "lab", "generation": 3}"#;
        let sig = key.sign(manifest).to_json();
        trusted.verify(manifest, &sig, "m").unwrap();
        // One byte changed: a bad signature.
        let mut changed = manifest.to_vec();
        changed[30] ^= 1;
        let e = trusted.verify(&changed, &sig, "m").unwrap_err();
        assert!(
            matches!(
                e,
                Error::Untrusted {
                    what: Untrusted::BadSignature,
                    ..
                }
            ),
            "{e}"
        );
        // Another key's signature: named as such.
        let other = SigningKey::generate().sign(manifest).to_json();
        let e = trusted.verify(manifest, &other, "m").unwrap_err();
        assert!(
            matches!(
                e,
                Error::Untrusted {
                    what: Untrusted::OtherKey,
                    ..
                }
            ),
            "{e}"
        );
        // Another key claiming the trusted key's id still fails the signature.
        let mut forged = SigningKey::generate().sign(manifest);
        forged.key_id = trusted.key_id();
        let e = trusted
            .verify(manifest, &forged.to_json(), "m")
            .unwrap_err();
        assert!(
            matches!(
                e,
                Error::Untrusted {
                    what: Untrusted::BadSignature,
                    ..
                }
            ),
            "{e}"
        );
        // Not a signature file.
        let e = trusted.verify(manifest, b"garbage", "m").unwrap_err();
        assert!(
            matches!(
                e,
                Error::Untrusted {
                    what: Untrusted::BadSignature,
                    ..
                }
            ),
            "{e}"
        );
        // Never overwritten.
        let before = std::fs::read(&files.private).unwrap();
        let e = keygen(dir.path()).unwrap_err();
        assert!(
            matches!(
                e,
                Error::Param {
                    name: "key_out",
                    ..
                }
            ),
            "{e}"
        );
        assert_eq!(std::fs::read(&files.private).unwrap(), before);
    }

    #[test]
    fn key_file_errors_say_what_was_found() {
        let dir = tempfile::tempdir().unwrap();
        let files = keygen(dir.path()).unwrap();
        let e = SigningKey::read_pem(&files.public).unwrap_err();
        assert!(
            matches!(&e, Error::Format { .. }) && e.to_string().contains("public key"),
            "{e}"
        );
        let e = TrustedKey::read_pem(&files.private).unwrap_err();
        assert!(
            matches!(&e, Error::Format { .. }) && e.to_string().contains("private key"),
            "{e}"
        );
        let garbage = dir.path().join("garbage.pem");
        std::fs::write(&garbage, "not a key\n").unwrap();
        for e in [
            SigningKey::read_pem(&garbage).unwrap_err(),
            TrustedKey::read_pem(&garbage).unwrap_err(),
        ] {
            assert!(matches!(e, Error::Format { .. }), "{e}");
        }
        let missing = dir.path().join("none.pem");
        assert!(matches!(
            SigningKey::read_pem(&missing),
            Err(Error::Io { .. })
        ));
        assert!(matches!(
            TrustedKey::read_pem(&missing),
            Err(Error::Io { .. })
        ));
    }

    /// The system's `openssl` on PATH, if any.
    fn system_openssl() -> bool {
        std::process::Command::new("openssl")
            .arg("version")
            .output()
            .is_ok_and(|o| o.status.success())
    }

    /// Runs `openssl args…`; its success and stderr.
    fn openssl(args: &[&std::ffi::OsStr]) -> (bool, String) {
        let o = std::process::Command::new("openssl")
            .args(args)
            .output()
            .unwrap();
        (
            o.status.success(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    }

    /// `openssl pkeyutl -verify` of the signature file `sig` (its hex decoded) over `manifest`.
    fn openssl_verifies(
        dir: &Path,
        public: &Path,
        manifest: &[u8],
        sig: &ManifestSignature,
    ) -> bool {
        let (m, s) = (dir.join("manifest.json"), dir.join("sig.bin"));
        std::fs::write(&m, manifest).unwrap();
        std::fs::write(&s, unhex(&sig.signature).unwrap()).unwrap();
        let args = ["pkeyutl", "-verify", "-pubin", "-inkey"].map(std::ffi::OsStr::new);
        let mut all: Vec<&std::ffi::OsStr> = args.to_vec();
        all.extend([
            public.as_os_str(),
            "-rawin".as_ref(),
            "-in".as_ref(),
            m.as_os_str(),
        ]);
        all.extend(["-sigfile".as_ref(), s.as_os_str()]);
        openssl(&all).0
    }

    #[test]
    fn the_system_openssl_reads_keygens_keys_and_verifies_its_signatures_and_slag_reads_openssls_keys()
     {
        if !system_openssl() {
            eprintln!("NOTICE: no `openssl` on PATH: the OpenSSL interoperability test is skipped");
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let files = keygen(dir.path()).unwrap();
        let pem = std::fs::read_to_string(&files.private).unwrap();
        assert!(pem.starts_with("-----BEGIN PRIVATE KEY-----"), "{pem}");
        let (ok, err) = openssl(
            &["pkey", "-noout", "-in"]
                .map(std::ffi::OsStr::new)
                .iter()
                .copied()
                .chain([files.private.as_os_str()])
                .collect::<Vec<_>>(),
        );
        assert!(ok, "openssl pkey cannot read keygen's private key: {err}");
        let (ok, err) = openssl(
            &["pkey", "-pubin", "-noout", "-in"]
                .map(std::ffi::OsStr::new)
                .iter()
                .copied()
                .chain([files.public.as_os_str()])
                .collect::<Vec<_>>(),
        );
        assert!(ok, "openssl pkey cannot read keygen's public key: {err}");
        let key = SigningKey::read_pem(&files.private).unwrap();
        let manifest = br#"{"scene_id": "lab", "generation": 7}"#;
        let sig = key.sign(manifest);
        assert!(openssl_verifies(dir.path(), &files.public, manifest, &sig));
        let mut changed = manifest.to_vec();
        changed[20] ^= 1;
        assert!(!openssl_verifies(dir.path(), &files.public, &changed, &sig));
        // A pair OpenSSL made: slag reads both halves, and OpenSSL verifies slag's signature.
        let (theirs, theirs_pub) = (dir.path().join("o.pem"), dir.path().join("o.pub.pem"));
        let os = |s: &'static str| std::ffi::OsStr::new(s);
        let (ok, err) = openssl(&[
            os("genpkey"),
            os("-algorithm"),
            os("ed25519"),
            os("-out"),
            theirs.as_os_str(),
        ]);
        assert!(ok, "{err}");
        let (ok, err) = openssl(&[
            os("pkey"),
            os("-in"),
            theirs.as_os_str(),
            os("-pubout"),
            os("-out"),
            theirs_pub.as_os_str(),
        ]);
        assert!(ok, "{err}");
        let key = SigningKey::read_pem(&theirs).unwrap();
        assert_eq!(key.public(), TrustedKey::read_pem(&theirs_pub).unwrap());
        let sig = key.sign(manifest);
        assert!(openssl_verifies(dir.path(), &theirs_pub, manifest, &sig));
    }

    #[test]
    fn several_trusted_keys_accept_either_signer_and_name_all_when_refusing() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a"), dir.path().join("b"));
        let old_files = keygen(&a).unwrap();
        let new_files = keygen(&b).unwrap();
        // Both public keys in one file, one PEM block after the other.
        let both = dir.path().join("trusted.pem");
        let text = std::fs::read_to_string(&old_files.public).unwrap()
            + &std::fs::read_to_string(&new_files.public).unwrap();
        std::fs::write(&both, text).unwrap();
        let keys = TrustedKeys::read_pem_files(std::slice::from_ref(&both)).unwrap();
        assert_eq!(
            keys.key_ids(),
            vec![old_files.key_id.clone(), new_files.key_id.clone()]
        );
        // The same keys from two files.
        let two =
            TrustedKeys::read_pem_files(&[old_files.public.clone(), new_files.public.clone()])
                .unwrap();
        assert_eq!(two, keys);
        let manifest = b"{}";
        for f in [&old_files, &new_files] {
            let sig = SigningKey::read_pem(&f.private)
                .unwrap()
                .sign(manifest)
                .to_json();
            keys.verify(manifest, &sig, "m").unwrap();
        }
        let stranger = SigningKey::generate();
        let e = keys
            .verify(manifest, &stranger.sign(manifest).to_json(), "m")
            .unwrap_err();
        assert!(
            matches!(
                e,
                Error::Untrusted {
                    what: Untrusted::OtherKey,
                    ..
                }
            ),
            "{e}"
        );
        let m = e.to_string();
        assert!(
            m.contains(&old_files.key_id) && m.contains(&new_files.key_id),
            "{m}"
        );
        // A file with a private key and no public one is refused as before.
        let e = TrustedKeys::read_pem_files(std::slice::from_ref(&old_files.private)).unwrap_err();
        assert!(
            matches!(e, Error::Format { .. }) && e.to_string().contains("private key"),
            "{e}"
        );
        assert!(TrustedKeys::read_pem_files(&[]).is_err());
    }

    #[test]
    fn hashes_generations_and_digests() {
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert_eq!(sha256_reader(&b"abc"[..]).unwrap(), sha256_hex(b"abc"));
        let want = sha256_hex(b"tile");
        check_sha256(Some(&want), b"tile", "tile 1", "o").unwrap();
        let e = check_sha256(Some(&want), b"tilf", "tile 1", "o").unwrap_err();
        assert!(
            matches!(
                e,
                Error::Untrusted {
                    what: Untrusted::ContentHash,
                    ..
                }
            ),
            "{e}"
        );
        assert!(e.to_string().contains("tile 1"), "{e}");
        check_generation("lab", 2, 2, "o").unwrap();
        check_generation("lab", 2, 3, "o").unwrap();
        let e = check_generation("lab", 3, 2, "o").unwrap_err();
        assert!(
            matches!(
                e,
                Error::Untrusted {
                    what: Untrusted::Replay,
                    ..
                }
            ),
            "{e}"
        );
    }
}
