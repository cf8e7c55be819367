//! The web routes of `slag-edge serve`: `GET /query.ply?text=…` (the same parameters and
//! validation as `GET /query`, plus `color=RRGGBB` and `dim=0..1`; the `.ply` is
//! [`crate::view::highlighted_ply_framed`]), and the page `GET /` with its script `GET /app.js`
//! and the vendored viewer bundles `GET /vendor/<file>`.
//!
//! Everything the page needs is compiled into the binary: the page, its script, and the viewer
//! ([`@mkkellogg/gaussian-splats-3d`](https://github.com/mkkellogg/GaussianSplats3D) on three.js)
//! when it was vendored before the build (`bash scripts/web-vendor.sh`: `npm ci` in `edge/web`,
//! bundles copied to `edge/web/vendor`, git-ignored; [`Vendored`]). `--web-dir DIR` overrides
//! them: `DIR/index.html` and `DIR/app.js` where present, and the viewer from `DIR/vendor` only.
//! A binary built without the vendored viewer serves the page, which says how to vendor; `cargo
//! build` never needs npm, and nothing is looked up in the build machine's source tree.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::Ordering;

use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use slag_common::{Error, Result};

use super::{AppState, busy, error, query_pairs, raw_from_pairs, status_of};
use crate::view::{HighlightStyle, object_colour, painted_ply_framed, parse_colour};

/// What `GET /query.ply` paints.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ColorBy {
    /// Every painted match in `color` (default).
    Match,
    /// The matches of the `k`-th returned object in [`crate::view::object_colour`]`(k)`, the
    /// other matches in `color`.
    Object,
}

/// Takes the highlight parameters (`color`, `dim`, `color_by`) out of a query string's pairs.
fn style_from_pairs(pairs: &mut HashMap<String, String>) -> Result<(HighlightStyle, ColorBy)> {
    let by = match pairs.remove("color_by").as_deref().map(str::trim) {
        None | Some("match") => ColorBy::Match,
        Some("object") => ColorBy::Object,
        Some(b) => {
            return Err(Error::query(
                "color_by",
                format!("color_by {b:?}: use match or object"),
            ));
        }
    };
    let mut style = HighlightStyle::default();
    if let Some(c) = pairs.remove("color") {
        style.colour = parse_colour(&c)?;
    }
    if let Some(d) = pairs.remove("dim") {
        let f: f32 = d
            .trim()
            .parse()
            .ok()
            .filter(|f: &f32| f.is_finite() && (0.0..=1.0).contains(f))
            .ok_or_else(|| Error::query("dim", format!("dim {d:?}: use a number in 0..=1")))?;
        style.dim = Some(f);
    }
    Ok((style, by))
}

/// `GET /query.ply?text=…[&color=RRGGBB][&dim=0..1][&color_by=match|object]` plus every
/// `GET /query` parameter. `color_by=object` paints the matches of the answer's `k`-th object in
/// [`crate::view::object_colour`]`(k)` (the page's box colours) and the other matches in `color`.
///
/// With a threshold (the default) every match is painted (`top_k` only limits `/query`'s list);
/// with `threshold=none` the `top_k` best are. Headers: `Content-Type: application/octet-stream`,
/// `Content-Disposition: attachment; filename="query.ply"`, `X-Slag-Matches` (painted ids),
/// `X-Slag-Objects` (objects in the answer), `X-Slag-Gaussians` (vertices), `X-Slag-Up` (up `x,y,z` of the manifest's ground frame),
/// `X-Slag-Frame` (`map` or `scene`: the frame of the vertices and of `X-Slag-Up`; the map frame
/// by default when the manifest has a scene-to-map transform, `frame=scene` for the stored one).
pub(crate) async fn query_ply(
    State(state): State<Arc<AppState>>,
    uri: axum::http::Uri,
) -> Response {
    let params = query_pairs(uri.query()).and_then(|mut p| {
        let style = style_from_pairs(&mut p)?;
        let params = raw_from_pairs(p)?.validate(state.opts.threshold)?;
        Ok((params, style))
    });
    let (mut params, (style, by)) = match params {
        Ok(p) => p,
        Err(e) => {
            state.rejected.fetch_add(1, Ordering::Relaxed);
            return error(status_of(&e), e.to_string());
        }
    };
    let engine = state.engine();
    if params.threshold.is_some() {
        params.top_k = engine.store.len().max(1);
    }
    let answer = match state.query_engine().query_one(params).await {
        Ok(Ok(a)) => a,
        Ok(Err(e)) => return error(status_of(&e), e.to_string()),
        Err(b) => return busy(&b),
    };
    let colours = match_colours(&answer, by, &style);
    let ids_n = colours.len();
    let in_map = answer.frame == slag_common::shards::MAP_FRAME;
    let e2 = engine.clone();
    let built = tokio::task::spawn_blocking(move || {
        let to_map = e2.manifest.frames.scene_to_map.as_ref().filter(|_| in_map);
        painted_ply_framed(&e2.display, &|id| colours.get(&id).copied(), &style, to_map)
    })
    .await;
    let bytes = match built {
        Ok(Ok(b)) => b,
        Ok(Err(e)) => return error(status_of(&e), e.to_string()),
        Err(e) => {
            return error(
                StatusCode::INTERNAL_SERVER_ERROR,
                format!("ply task failed: {e}"),
            );
        }
    };
    let up = answer_up(&engine, in_map);
    let named = |name: &'static str, value: String| (header::HeaderName::from_static(name), value);
    (
        [
            (header::CONTENT_TYPE, "application/octet-stream".to_string()),
            (
                header::CONTENT_DISPOSITION,
                "attachment; filename=\"query.ply\"".to_string(),
            ),
            named("x-slag-matches", ids_n.to_string()),
            named("x-slag-objects", answer.objects.len().to_string()),
            named("x-slag-gaussians", engine.display.len().to_string()),
            named("x-slag-up", format!("{},{},{}", up[0], up[1], up[2])),
            named("x-slag-frame", answer.frame.to_string()),
            named(
                "x-slag-tiles-pending-verification",
                answer.tiles_pending_verification.to_string(),
            ),
        ],
        bytes,
    )
        .into_response()
}

/// The colour of every returned match by Gaussian id: `style.colour`, or with
/// [`ColorBy::Object`] the colour of its object ([`object_colour`]) where it is in one.
fn match_colours(
    answer: &crate::query::QueryAnswer,
    by: ColorBy,
    style: &HighlightStyle,
) -> HashMap<u32, [f32; 3]> {
    answer
        .matches
        .iter()
        .enumerate()
        .map(|(i, m)| {
            let object = answer.match_objects.get(i).copied().flatten();
            let rgb = match (by, object) {
                (ColorBy::Object, Some(k)) => object_colour(k as usize),
                _ => style.colour,
            };
            (m.id, rgb)
        })
        .collect()
}

/// The up direction of the manifest's ground frame, rotated into the map frame when `in_map`
/// and the manifest has a scene-to-map transform (a unit vector either way).
fn answer_up(engine: &crate::engine::Engine, in_map: bool) -> [f32; 3] {
    let up = engine.manifest.ground.up;
    match engine
        .manifest
        .frames
        .scene_to_map
        .as_ref()
        .filter(|_| in_map)
    {
        Some(t) => {
            let r = t.rotation;
            let u = up.map(f64::from);
            [0, 1, 2].map(|i| (r[i][0] * u[0] + r[i][1] * u[1] + r[i][2] * u[2]) as f32)
        }
        None => up,
    }
}

/// The page (`GET /`), compiled in.
pub const INDEX_HTML: &str = include_str!("../../web/index.html");
/// The page's script (`GET /app.js`), compiled in.
pub const APP_JS: &str = include_str!("../../web/app.js");

/// True for the routes every visitor may load without the bearer token: the page, its script
/// and the vendored viewer (no scene data).
pub fn is_public_path(path: &str) -> bool {
    path == "/" || path == "/index.html" || path == "/app.js" || path.starts_with("/vendor/")
}

/// The viewer bundles of `edge/web/vendor` as they were when the binary was built (none when
/// `scripts/web-vendor.sh` had not run): served under `/vendor/<file>` unless `--web-dir` is
/// given.
#[derive(rust_embed::Embed)]
#[folder = "web/vendor/"]
#[allow_missing = true]
pub struct Vendored;

/// `<web_dir>/<name>` when `--web-dir` is set and the file is there, else the compiled-in text.
async fn page_file(state: &AppState, name: &str, compiled: &'static str) -> Vec<u8> {
    if let Some(dir) = &state.web_dir
        && let Ok(b) = tokio::fs::read(dir.join(name)).await
    {
        return b;
    }
    compiled.as_bytes().to_vec()
}

pub(crate) async fn index(State(state): State<Arc<AppState>>) -> Response {
    (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        page_file(&state, "index.html", INDEX_HTML).await,
    )
        .into_response()
}

pub(crate) async fn app_js(State(state): State<Arc<AppState>>) -> Response {
    (
        [
            (header::CONTENT_TYPE, "text/javascript; charset=utf-8"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        page_file(&state, "app.js", APP_JS).await,
    )
        .into_response()
}

/// Resolves `/vendor/<name>` inside `<web_dir>/vendor`: a single file name of
/// `[A-Za-z0-9._-]` not starting with `.` (no traversal).
pub fn vendor_file(web_dir: &Path, name: &str) -> Option<PathBuf> {
    let ok = !name.is_empty()
        && !name.starts_with('.')
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'.' || b == b'_' || b == b'-');
    ok.then(|| web_dir.join("vendor").join(name))
}

pub(crate) async fn vendor(
    State(state): State<Arc<AppState>>,
    axum::extract::Path(name): axum::extract::Path<String>,
) -> Response {
    let missing = || {
        error(
            StatusCode::NOT_FOUND,
            format!(
                "viewer file {name:?} is not vendored; run `bash scripts/web-vendor.sh` in the slag \
                 repository, then rebuild slag-edge (it embeds edge/web/vendor) or serve the web \
                 folder <repo>/edge/web instead of the embedded one"
            ),
        )
    };
    let Some(path) = vendor_file(Path::new(""), &name) else {
        return error(StatusCode::BAD_REQUEST, format!("bad file name {name:?}"));
    };
    let bytes = match &state.web_dir {
        Some(dir) => tokio::fs::read(dir.join(&path)).await.ok(),
        None => Vendored::get(&name).map(|f| f.data.into_owned()),
    };
    let Some(b) = bytes else {
        return missing();
    };
    let ct = match path.extension().and_then(|e| e.to_str()) {
        Some("js" | "mjs") => "text/javascript; charset=utf-8",
        Some("wasm") => "application/wasm",
        Some("json") => "application/json",
        Some("css") => "text/css",
        _ => "application/octet-stream",
    };
    ([(header::CONTENT_TYPE, ct)], b).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vendor_names_stay_inside_the_vendor_folder() {
        assert!(vendor_file(Path::new("/w"), "../x").is_none());
        assert!(vendor_file(Path::new("/w"), ".hidden").is_none());
        assert!(vendor_file(Path::new("/w"), "").is_none());
        assert_eq!(
            vendor_file(Path::new("/w"), "three.module.js"),
            Some(PathBuf::from("/w/vendor/three.module.js"))
        );
    }
}
