//! Step 2 of a fetch: the disc on the manifest's ground plane (in the map or the scene frame)
//! and the tiles whose footprint meets it.

use slag_common::shards::{MAP_FRAME, Manifest, SCENE_FRAME, TileInfo};
use slag_common::{Error, Result};

use crate::query::{FrameChoice, answer_frame};

/// The disc to select, on the manifest's ground plane: `(centre (g0, g1), radius in scene
/// units, frame name)`. In the map frame (module doc of [`Center`]) the centre is mapped back by
/// the inverse scene-to-map transform and the radius divided by its scale (`r` metres =
/// `r / s` scene units).
///
/// Errors: [`Error::Param`] `radius` for a negative or non-finite radius, [`Error::Query`]
/// `frame` for `frame` map when the manifest has no transform.
pub fn selection_disc(
    manifest: &Manifest,
    center: Center,
    radius: f64,
    frame: FrameChoice,
) -> Result<([f64; 2], f64, &'static str)> {
    let map = answer_frame(frame, manifest.frames.scene_to_map.as_ref())?;
    if !(radius.is_finite() && radius >= 0.0) {
        return Err(Error::param(
            "radius",
            radius,
            format!(
                "a finite number ≥ 0 ({})",
                if map.is_some() {
                    "metres of the map frame"
                } else {
                    "scene units"
                }
            ),
        ));
    }
    let ground = |w: [f64; 3]| {
        let g = manifest
            .ground
            .to_ground([w[0] as f32, w[1] as f32, w[2] as f32]);
        [g[0], g[1]]
    };
    Ok(match map {
        None => {
            let c = match center {
                Center::Ground(g) => g,
                Center::World(w) => ground(w),
            };
            (c, radius, SCENE_FRAME)
        }
        Some(t) => {
            let m = match center {
                Center::Ground([x, y]) => [x, y, 0.0],
                Center::World(w) => w,
            };
            // The ground projection in f64 (to_ground takes f32 points): far-away map origins
            // (UTM) would lose centimetres in f32.
            let s = t.to_scene(m);
            let r = manifest
                .ground
                .world_to_ground
                .map(|row| row.map(f64::from));
            let g = [0, 1].map(|i| r[i][0] * s[0] + r[i][1] * s[1] + r[i][2] * s[2]);
            (g, t.map_to_scene_distance(radius), MAP_FRAME)
        }
    })
}

/// The manifest's tiles whose footprint meets the disc of [`selection_disc`] (ascending id):
/// what a fetch downloads.
///
/// Errors: as [`selection_disc`].
pub fn select_tiles(
    manifest: &Manifest,
    center: Center,
    radius: f64,
    frame: FrameChoice,
) -> Result<Vec<TileInfo>> {
    let (c, r, _) = selection_disc(manifest, center, radius, frame)?;
    Ok(manifest
        .tile_index()
        .select_tiles(c, r)
        .into_iter()
        .filter_map(|id| manifest.tiles.iter().find(|t| t.id == id).cloned())
        .collect())
}

/// Where the disc is centred.
///
/// In the **map frame** (metres) when the manifest has a scene-to-map transform and the fetch's
/// [`super::FetchParams::frame`] is auto or map: `X,Y` is the map point `(X, Y, 0)` and `X,Y,Z` the map
/// point itself; either is taken back to the scene with the inverse transform and projected onto
/// the manifest's ground plane (partitions with a transform tile on the map's ground, whose up is
/// the map's z, so the height of a map point then does not change the disc). In the **scene
/// frame** otherwise, as below.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Center {
    /// Scene frame: ground-plane coordinates `(g0, g1)` of the manifest's
    /// [`slag_common::shards::GroundFrame`]. Map frame: the map point `(X, Y, 0)`.
    Ground([f64; 2]),
    /// Scene frame: a world point, projected onto the ground plane with
    /// [`slag_common::shards::GroundFrame::to_ground`]. Map frame: a map point.
    World([f64; 3]),
}

impl std::str::FromStr for Center {
    type Err = String;
    /// `"X,Y"` (ground) or `"X,Y,Z"` (world); finite numbers.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let v: Vec<f64> = s
            .split(',')
            .map(|p| p.trim().parse::<f64>())
            .collect::<std::result::Result<_, _>>()
            .map_err(|e| format!("center {s:?}: {e}; use X,Y (ground) or X,Y,Z (world)"))?;
        if !v.iter().all(|x| x.is_finite()) {
            return Err(format!("center {s:?} has a non-finite coordinate"));
        }
        match v[..] {
            [x, y] => Ok(Center::Ground([x, y])),
            [x, y, z] => Ok(Center::World([x, y, z])),
            _ => Err(format!(
                "center {s:?}: expected 2 (ground X,Y) or 3 (world X,Y,Z) numbers"
            )),
        }
    }
}
