//! Signed manifests (module doc of [`super`], "Signed manifests"): the manifest with its
//! signature, checked with the trusted key before anything is downloaded.

use slag_common::shards::Manifest;
use slag_common::shards::signature::{self, MAX_SIGNATURE_BYTES, TrustedKey};
use slag_common::{Error, Result};

use super::FetchParams;
use super::client::{fetch_manifest_bytes, get_capped, status_error, url_join};
use crate::store::{EdgeStore, SignedManifest};

/// The scene's manifest, and with [`FetchParams::trusted_key`] its verified signature (module
/// doc, "Signed manifests"): the signature file is fetched, checked against the manifest's
/// exact bytes, the manifest must name every file's SHA-256, and its generation must not be
/// older than the one `store` holds.
///
/// Errors: as [`fetch_manifest`]; [`Error::Untrusted`] naming the failed check.
pub async fn fetch_trusted_manifest(
    client: &reqwest::Client,
    store: &EdgeStore,
    p: &FetchParams,
) -> Result<(Manifest, Option<SignedManifest>)> {
    let Some(key) = &p.trusted_key else {
        let token = p.token.as_deref();
        let (_, manifest) = fetch_manifest_bytes(client, &p.server, &p.scene, token).await?;
        return Ok((manifest, None));
    };
    // The publisher may commit a generation between the two requests, so that the signature
    // is of the other generation's bytes: one more pair settles it.
    let (manifest, signed) = match fetch_signed_manifest(client, p, key).await {
        Err(Error::Untrusted {
            what: slag_common::Untrusted::BadSignature,
            ..
        }) => fetch_signed_manifest(client, p, key).await?,
        r => r?,
    };
    let origin = url_join(&p.server, &format!("v1/scenes/{}/manifest", p.scene));
    signature::check_hashes(&manifest, &origin)?;
    // A stored manifest that no longer parses (a damaged store) does not block the fetch that
    // repairs it.
    if let Ok(Some(held)) = store.manifest(&p.scene) {
        signature::check_generation(&p.scene, held.generation, manifest.generation, &origin)?;
    }
    Ok((manifest, Some(signed)))
}

/// One request for the manifest and one for its signature
/// (`GET {server}/v1/scenes/{scene}/manifest.sig`), the signature checked with `key` against the
/// manifest's exact bytes.
///
/// Errors: as [`fetch_manifest`]; [`Error::Untrusted`] for no signature (404), another key's,
/// or one that does not hold.
async fn fetch_signed_manifest(
    client: &reqwest::Client,
    p: &FetchParams,
    key: &TrustedKey,
) -> Result<(Manifest, SignedManifest)> {
    let token = p.token.as_deref();
    let (bytes, manifest) = fetch_manifest_bytes(client, &p.server, &p.scene, token).await?;
    let origin = url_join(&p.server, &format!("v1/scenes/{}/manifest", p.scene));
    let sig_url = format!("{origin}.sig");
    let (status, sig) = get_capped(client, &sig_url, token, MAX_SIGNATURE_BYTES, |n| {
        Error::untrusted(
            slag_common::Untrusted::BadSignature,
            &sig_url,
            format!("{n} bytes, more than a signature file ({MAX_SIGNATURE_BYTES})"),
        )
    })
    .await?;
    if status == reqwest::StatusCode::NOT_FOUND {
        return Err(Error::untrusted(
            slag_common::Untrusted::Unsigned,
            &origin,
            format!(
                "the server has no signature for generation {} ({sig_url} answered 404), and a \
                 trusted key is required: the publisher has to sign the scene with its key; to \
                 accept an unsigned map, fetch without a trusted key",
                manifest.generation
            ),
        ));
    }
    if !status.is_success() {
        return Err(status_error(&sig_url, status, &String::from_utf8_lossy(&sig)).error);
    }
    key.verify(&bytes, &sig, &origin)?;
    Ok((
        manifest,
        SignedManifest {
            bytes,
            signature: sig,
        },
    ))
}
