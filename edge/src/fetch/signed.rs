//! Signed manifests (module doc of [`super`], "Signed manifests"): the manifest with its
//! signature, checked with the trusted key before anything is downloaded.

use slag_common::shards::Manifest;
use slag_common::shards::signature::{self, MAX_SIGNATURE_BYTES, TrustedKeys};
use slag_common::{Error, Result};

use super::FetchParams;
use super::client::{
    Pace, fetch_manifest_paced, get_capped, get_manifest, parse_manifest, status_error, url_join,
};
use crate::store::{EdgeStore, SignedManifest};

/// The scene's manifest, and with [`FetchParams::trusted_keys`] its verified signature (module
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
    let Some(key) = &p.trusted_keys else {
        let token = p.token.as_deref();
        let pace = Pace::new(p.timeout, p.min_rate);
        let (_, manifest) = fetch_manifest_paced(client, &p.server, &p.scene, token, pace).await?;
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
/// manifest's exact bytes before they are parsed.
///
/// Errors: [`Error::Network`]; [`Error::Untrusted`] for no signature (404), another key's, one
/// that does not hold, or a manifest that fails a check of the format ([`refusal`]: too large,
/// not a manifest, sizes the format does not allow, another scene's).
async fn fetch_signed_manifest(
    client: &reqwest::Client,
    p: &FetchParams,
    key: &TrustedKeys,
) -> Result<(Manifest, SignedManifest)> {
    let token = p.token.as_deref();
    let pace = Pace::new(p.timeout, p.min_rate);
    let (origin, bytes) = get_manifest(client, &p.server, &p.scene, token, pace)
        .await
        .map_err(|e| refusal(e, "the manifest"))?;
    let sig_url = format!(
        "{}.sig",
        url_join(&p.server, &format!("v1/scenes/{}/manifest", p.scene))
    );
    let pace = Pace::new(p.timeout, p.min_rate);
    let answer = get_capped(client, &sig_url, token, MAX_SIGNATURE_BYTES, pace, |n| {
        Error::untrusted(
            slag_common::Untrusted::BadSignature,
            &sig_url,
            format!("{n} bytes, more than a signature file ({MAX_SIGNATURE_BYTES})"),
        )
    })
    .await?;
    let (status, sig, sig_url) = (answer.status, answer.body, answer.url);
    if status == reqwest::StatusCode::NOT_FOUND {
        return Err(Error::untrusted(
            slag_common::Untrusted::Unsigned,
            &origin,
            format!(
                "the server has no signature for the manifest ({sig_url} answered 404), and a \
                 trusted key is required: the publisher has to sign the scene with its key; to \
                 accept an unsigned map, fetch without a trusted key"
            ),
        ));
    }
    if !status.is_success() {
        return Err(status_error(&sig_url, status, &String::from_utf8_lossy(&sig)).error);
    }
    // The signature first, over the bytes as they came: a manifest changed on the way is named
    // as such, whichever of the format's checks it would also fail.
    key.verify(&bytes, &sig, &origin)?;
    let manifest =
        parse_manifest(&bytes, &origin, &p.scene).map_err(|e| refusal(e, "the signed manifest"))?;
    Ok((
        manifest,
        SignedManifest {
            bytes,
            signature: sig,
        },
    ))
}

/// A failed check of `what` (the manifest, a tile) while a key is trusted, as the refusal it is
/// ([`slag_common::Untrusted::Malformed`]), naming what happened: the format's refusals
/// ([`Error::Format`], [`Error::Limit`], [`Error::Shard`]) become [`Error::Untrusted`]; a network
/// failure, a refusal already and every other error stay as they are.
pub(super) fn refusal(e: Error, what: &str) -> Error {
    match e {
        Error::Format { path, message } => Error::untrusted(
            slag_common::Untrusted::Malformed,
            path.display().to_string(),
            format!("{what} fails a check of the shard format: {message}"),
        ),
        e @ (Error::Limit { .. } | Error::Shard(_)) => Error::untrusted(
            slag_common::Untrusted::Malformed,
            what,
            format!("{what} fails a check of the shard format: {e}"),
        ),
        e => e,
    }
}
