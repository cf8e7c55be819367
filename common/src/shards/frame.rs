//! The robot's map frame: a similarity transform (Sim(3)) from the scene's frame to the map.
//!
//! A 3DGS scene lives in the frame of its reconstruction (COLMAP: arbitrary scale, orientation
//! and origin); a robot localises in its own map frame, in metres. Partitioning records
//!
//! ```text
//! x_map = s · R · x_scene + t        (s > 0, R a rotation, t in metres)
//! ```
//!
//! in the manifest ([`Frames::scene_to_map`]). Everything else the manifest holds (tile
//! footprints, AABBs, the ground plane) and the shards' means stay in the **scene** frame
//! ([`Frames::data`]); readers convert at the edges: `slag-edge fetch` maps its centre back with
//! [`SceneToMap::to_scene`] and its radius with `r / s`, answers are mapped forward with
//! [`SceneToMap::to_map`].
//!
//! Sources ([`MapSource`]): a JSON file ([`SceneToMap::from_json`]: `scale`, `rotation` as a 3×3
//! row-major matrix or `quaternion_wxyz`, `translation`), three or more surveyed point pairs
//! ([`SceneToMap::from_point_pairs`]: Umeyama's closed-form least-squares similarity, with the RMS
//! residual), or `identity` for a geo-registered model whose scene frame already is the map frame
//! (metres, e.g. ENU after `colmap model_aligner`).

use glam::DVec3;

use crate::{Error, Result};

/// Name of the scene frame in manifests and answers.
pub const SCENE_FRAME: &str = "scene";
/// Name of the map frame in manifests and answers.
pub const MAP_FRAME: &str = "map";

/// Largest deviation from orthonormality accepted for a given rotation matrix (it is then
/// projected onto the nearest rotation).
pub const ROTATION_TOLERANCE: f64 = 1e-4;

/// Where a scene-to-map transform came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MapSource {
    /// A JSON file (`partition --to-map FILE`).
    File,
    /// Estimated from surveyed point pairs (`partition --to-map-points FILE`).
    Points,
    /// The scene frame is the map frame (a geo-registered, metric model; `--to-map identity`).
    Identity,
}

/// `x_map = scale · rotation · x_scene + translation` (module doc).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SceneToMap {
    /// Map units (metres) per scene unit, > 0.
    pub scale: f64,
    /// Rotation `R`, row-major, orthonormal with determinant +1.
    pub rotation: [[f64; 3]; 3],
    /// Translation `t`, map frame (metres).
    pub translation: [f64; 3],
    /// Where it came from.
    pub source: MapSource,
    /// RMS of `|x_map − T(x_scene)|` over the surveyed points (metres); [`MapSource::Points`] only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rms_residual: Option<f64>,
    /// Number of surveyed point pairs; [`MapSource::Points`] only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub points: Option<usize>,
}

/// Which frame the manifest's coordinates are in, and the map frame if there is one.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Frames {
    /// Frame of the tile footprints, AABBs, ground plane and shard means: always
    /// [`SCENE_FRAME`] (the reconstruction's frame, scene units).
    pub data: String,
    /// Scene → map transform; absent (manifests written before it existed, or partitions without
    /// `--to-map`): no map frame, fetch radii and answers are in scene units.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene_to_map: Option<SceneToMap>,
}

impl Default for Frames {
    fn default() -> Self {
        Frames {
            data: SCENE_FRAME.into(),
            scene_to_map: None,
        }
    }
}

/// The JSON file of `partition --to-map FILE`.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Sim3File {
    #[serde(default)]
    scale: Option<f64>,
    #[serde(default)]
    rotation: Option<[[f64; 3]; 3]>,
    #[serde(default)]
    quaternion_wxyz: Option<[f64; 4]>,
    #[serde(default)]
    translation: Option<[f64; 3]>,
}

/// One surveyed pair of `--to-map-points FILE`.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct PointPair {
    scene: [f64; 3],
    map: [f64; 3],
    #[serde(default)]
    #[allow(dead_code)]
    name: Option<String>,
}

/// `--to-map-points FILE`: `{"pairs": [{"scene": [x,y,z], "map": [x,y,z]}, …]}` or the bare list.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(untagged)]
enum PointFile {
    Object { pairs: Vec<PointPair> },
    List(Vec<PointPair>),
}

fn mat_vec(m: &[[f64; 3]; 3], v: DVec3) -> DVec3 {
    DVec3::new(
        m[0][0] * v.x + m[0][1] * v.y + m[0][2] * v.z,
        m[1][0] * v.x + m[1][1] * v.y + m[1][2] * v.z,
        m[2][0] * v.x + m[2][1] * v.y + m[2][2] * v.z,
    )
}

fn mat_t_vec(m: &[[f64; 3]; 3], v: DVec3) -> DVec3 {
    DVec3::new(
        m[0][0] * v.x + m[1][0] * v.y + m[2][0] * v.z,
        m[0][1] * v.x + m[1][1] * v.y + m[2][1] * v.z,
        m[0][2] * v.x + m[1][2] * v.y + m[2][2] * v.z,
    )
}

/// Rotation matrix (row-major) of a unit quaternion `(w, x, y, z)`.
pub fn quaternion_to_matrix(q: [f64; 4]) -> [[f64; 3]; 3] {
    let [w, x, y, z] = q;
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// The rotation (unit quaternion `(w, x, y, z)`) maximising `Σ b_i · R a_i`, from the
/// cross-covariance `s[j][k] = Σ_i a_i[j] b_i[k]` (Horn 1987: the eigenvector of the largest
/// eigenvalue of a symmetric 4×4 matrix). It is the same rotation as Umeyama's SVD solution with
/// the reflection correction (both maximise `trace(Rᵀ S)` over proper rotations).
fn horn_rotation(s: [[f64; 3]; 3]) -> [f64; 4] {
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = s;
    let n = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (w, v) = super::eigen::jacobi_eigen(n);
    let i = (0..4).max_by(|&i, &j| w[i].total_cmp(&w[j])).unwrap_or(0);
    let q = [v[0][i], v[1][i], v[2][i], v[3][i]];
    let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
    let q = q.map(|x| x / norm);
    if q[0] < 0.0 { q.map(|x| -x) } else { q }
}

/// Nearest rotation (polar factor) of a matrix `m`, as a unit quaternion `(w, x, y, z)`.
fn nearest_rotation(m: &[[f64; 3]; 3]) -> [f64; 4] {
    // Σ_i (M e_i) · (R e_i) = trace(Mᵀ R): a_i = e_i, b_i = column i of M, so s[j][k] = M[k][j].
    let mut s = [[0.0; 3]; 3];
    for (j, row) in s.iter_mut().enumerate() {
        for (k, x) in row.iter_mut().enumerate() {
            *x = m[k][j];
        }
    }
    horn_rotation(s)
}

fn finite(v: &[f64]) -> bool {
    v.iter().all(|x| x.is_finite())
}

/// Eigenvalues (descending) of the covariance of `pts` about their centroid, and the centroid.
fn spread(pts: &[DVec3]) -> ([f64; 3], DVec3) {
    let n = pts.len() as f64;
    let c = pts.iter().copied().sum::<DVec3>() / n;
    let mut m = [[0.0; 3]; 3];
    for p in pts {
        let d = (*p - c).to_array();
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] += d[i] * d[j] / n;
            }
        }
    }
    let (mut w, _) = super::eigen::jacobi_eigen(m);
    w.sort_by(|a, b| b.total_cmp(a));
    (w, c)
}

impl SceneToMap {
    /// The identity (a geo-registered scene: scene units are metres of the map frame).
    pub fn identity() -> SceneToMap {
        SceneToMap {
            scale: 1.0,
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [0.0; 3],
            source: MapSource::Identity,
            rms_residual: None,
            points: None,
        }
    }

    /// Builds a transform from its parts, checking them: `scale` finite and > 0, `translation`
    /// finite, `rotation` orthonormal within [`ROTATION_TOLERANCE`] with determinant +1 (it is
    /// then replaced by the nearest exact rotation, so the inverse is exact to rounding).
    ///
    /// Errors: [`Error::Invalid`] naming the bad part.
    pub fn new(
        scale: f64,
        rotation: [[f64; 3]; 3],
        translation: [f64; 3],
        source: MapSource,
    ) -> Result<SceneToMap> {
        if !(scale.is_finite() && scale > 0.0) {
            return Err(Error::Invalid(format!(
                "scene-to-map scale {scale}: use a finite number > 0 (metres per scene unit)"
            )));
        }
        if !finite(&translation) {
            return Err(Error::Invalid(format!(
                "scene-to-map translation {translation:?} is not finite"
            )));
        }
        if !finite(rotation.as_flattened()) {
            return Err(Error::Invalid(format!(
                "scene-to-map rotation {rotation:?} is not finite"
            )));
        }
        let mut worst: f64 = 0.0;
        for i in 0..3 {
            for j in 0..3 {
                let dot: f64 = (0..3).map(|k| rotation[i][k] * rotation[j][k]).sum();
                worst = worst.max((dot - if i == j { 1.0 } else { 0.0 }).abs());
            }
        }
        let r = rotation;
        let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
            - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
            + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
        if worst > ROTATION_TOLERANCE || det <= 0.0 {
            return Err(Error::Invalid(format!(
                "scene-to-map rotation {rotation:?} is not a rotation (R·Rᵀ differs from I by \
                 {worst:.2e}, det {det:.6}); give an orthonormal row-major matrix with det +1, or \
                 quaternion_wxyz"
            )));
        }
        Ok(SceneToMap {
            scale,
            rotation: quaternion_to_matrix(nearest_rotation(&rotation)),
            translation,
            source,
            rms_residual: None,
            points: None,
        })
    }

    /// Parses the JSON of `partition --to-map FILE`:
    /// `{"scale": s, "rotation": [[r00, r01, r02], [r10, …], [r20, …]], "translation": [tx, ty, tz]}`
    /// (row-major `R`, `x_map = s·R·x_scene + t`), or `"quaternion_wxyz": [w, x, y, z]` instead of
    /// `rotation`. `scale` defaults to 1, `translation` to 0, the rotation to the identity.
    ///
    /// Errors: [`Error::Format`] for bad JSON or unknown keys, [`Error::Invalid`] for bad values
    /// (both rotation forms, a zero quaternion, a non-rotation, a scale ≤ 0).
    pub fn from_json(bytes: &[u8], origin: &str) -> Result<SceneToMap> {
        let f: Sim3File = serde_json::from_slice(bytes).map_err(|e| {
            Error::format(
                origin,
                format!(
                    "not a scene-to-map transform: {e}; write {{\"scale\": s, \"rotation\": \
                     [[…], […], […]] or \"quaternion_wxyz\": [w, x, y, z], \"translation\": \
                     [tx, ty, tz]}}"
                ),
            )
        })?;
        let rotation = match (f.rotation, f.quaternion_wxyz) {
            (Some(_), Some(_)) => {
                return Err(Error::Invalid(format!(
                    "{origin}: give either rotation or quaternion_wxyz, not both"
                )));
            }
            (Some(r), None) => r,
            (None, Some(q)) => {
                let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
                if !(n.is_finite() && n > 1e-12) {
                    return Err(Error::Invalid(format!(
                        "{origin}: quaternion_wxyz {q:?} is zero or not finite"
                    )));
                }
                quaternion_to_matrix(q.map(|x| x / n))
            }
            (None, None) => SceneToMap::identity().rotation,
        };
        SceneToMap::new(
            f.scale.unwrap_or(1.0),
            rotation,
            f.translation.unwrap_or([0.0; 3]),
            MapSource::File,
        )
        .map_err(|e| match e {
            Error::Invalid(m) => Error::Invalid(format!("{origin}: {m}")),
            e => e,
        })
    }

    /// Reads `--to-map FILE` (JSON, [`Self::from_json`]); the word `identity` instead of a path
    /// gives [`Self::identity`].
    ///
    /// Errors: [`Error::Io`], as [`Self::from_json`].
    pub fn read(path: &std::path::Path) -> Result<SceneToMap> {
        if path.as_os_str() == "identity" {
            return Ok(SceneToMap::identity());
        }
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        SceneToMap::from_json(&bytes, &path.display().to_string())
    }

    /// Reads `--to-map-points FILE`: `{"pairs": [{"scene": [x, y, z], "map": [x, y, z]}, …]}` (or
    /// the bare list; an optional `"name"` per pair is ignored) and estimates the transform with
    /// [`Self::from_point_pairs`].
    ///
    /// Errors: [`Error::Io`], [`Error::Format`] (bad JSON), as [`Self::from_point_pairs`].
    pub fn read_points(path: &std::path::Path) -> Result<SceneToMap> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let f: PointFile = serde_json::from_slice(&bytes).map_err(|e| {
            Error::format(
                path,
                format!(
                    "not a list of surveyed points: {e}; write {{\"pairs\": [{{\"scene\": [x, y, \
                     z], \"map\": [x, y, z]}}, …]}} with at least 3 pairs"
                ),
            )
        })?;
        let pairs = match f {
            PointFile::Object { pairs } | PointFile::List(pairs) => pairs,
        };
        let scene: Vec<[f64; 3]> = pairs.iter().map(|p| p.scene).collect();
        let map: Vec<[f64; 3]> = pairs.iter().map(|p| p.map).collect();
        SceneToMap::from_point_pairs(&scene, &map).map_err(|e| match e {
            Error::Invalid(m) => Error::Invalid(format!("{}: {m}", path.display())),
            e => e,
        })
    }

    /// Least-squares similarity `map ≈ s·R·scene + t` from surveyed pairs (Umeyama 1991, closed
    /// form: centroids, rotation maximising the correlation of the centred points — computed as
    /// Horn's quaternion eigenvector, equal to Umeyama's SVD solution with its reflection fix —
    /// then `s = Σ b_i·R a_i / Σ |a_i|²` and `t = b̄ − s·R·ā`). Records the RMS residual (map
    /// units) and the number of pairs.
    ///
    /// Errors ([`Error::Invalid`]): fewer than 3 pairs, lists of different lengths, non-finite
    /// coordinates, scene or map points that are coincident or collinear (the rotation about
    /// their line is then undetermined).
    pub fn from_point_pairs(scene: &[[f64; 3]], map: &[[f64; 3]]) -> Result<SceneToMap> {
        if scene.len() != map.len() {
            return Err(Error::Invalid(format!(
                "{} scene points but {} map points; give them in pairs",
                scene.len(),
                map.len()
            )));
        }
        if scene.len() < 3 {
            return Err(Error::Invalid(format!(
                "{} surveyed point pair(s): a scene-to-map transform needs at least 3 pairs of \
                 points that are not on one line",
                scene.len()
            )));
        }
        if !finite(scene.as_flattened()) || !finite(map.as_flattened()) {
            return Err(Error::Invalid("a surveyed point is not finite".into()));
        }
        let a: Vec<DVec3> = scene.iter().map(|&p| DVec3::from(p)).collect();
        let b: Vec<DVec3> = map.iter().map(|&p| DVec3::from(p)).collect();
        let (wa, ca) = spread(&a);
        let (wb, cb) = spread(&b);
        for (w, which) in [(wa, "scene"), (wb, "map")] {
            if w[0].is_nan() || w[0] <= 0.0 || w[1] <= 1e-10 * w[0] {
                return Err(Error::Invalid(format!(
                    "the {which} points are {}: the rotation is undetermined; survey at least 3 \
                     points that are not on one line (spread over the site)",
                    if w[0] > 0.0 {
                        "collinear"
                    } else {
                        "all the same point"
                    }
                )));
            }
        }
        let mut s = [[0.0; 3]; 3];
        let mut var_a = 0.0;
        for (pa, pb) in a.iter().zip(&b) {
            let (da, db) = ((*pa - ca).to_array(), (*pb - cb).to_array());
            var_a += (*pa - ca).length_squared();
            for j in 0..3 {
                for k in 0..3 {
                    s[j][k] += da[j] * db[k];
                }
            }
        }
        let q = horn_rotation(s);
        let rotation = quaternion_to_matrix(q);
        let corr: f64 = a
            .iter()
            .zip(&b)
            .map(|(pa, pb)| (*pb - cb).dot(mat_vec(&rotation, *pa - ca)))
            .sum();
        let scale = corr / var_a;
        if !(scale.is_finite() && scale > 0.0) {
            return Err(Error::Invalid(format!(
                "the surveyed points give scale {scale}: are the scene and map points listed in \
                 the same order?"
            )));
        }
        let t = cb - scale * mat_vec(&rotation, ca);
        let mut out = SceneToMap {
            scale,
            rotation,
            translation: t.to_array(),
            source: MapSource::Points,
            rms_residual: None,
            points: Some(scene.len()),
        };
        let sq: f64 = scene
            .iter()
            .zip(map)
            .map(|(&p, &m)| (DVec3::from(out.to_map(p)) - DVec3::from(m)).length_squared())
            .sum();
        out.rms_residual = Some((sq / scene.len() as f64).sqrt());
        Ok(out)
    }

    /// `s·R·x + t`: a scene point in the map frame.
    pub fn to_map(&self, x: [f64; 3]) -> [f64; 3] {
        (self.scale * mat_vec(&self.rotation, DVec3::from(x)) + DVec3::from(self.translation))
            .to_array()
    }

    /// `Rᵀ·(y − t) / s`: a map point in the scene frame (the exact inverse of [`Self::to_map`]).
    pub fn to_scene(&self, y: [f64; 3]) -> [f64; 3] {
        (mat_t_vec(
            &self.rotation,
            DVec3::from(y) - DVec3::from(self.translation),
        ) / self.scale)
            .to_array()
    }

    /// [`Self::to_map`] of an `f32` point, rounded to `f32`.
    pub fn to_map_f32(&self, x: [f32; 3]) -> [f32; 3] {
        self.to_map(x.map(f64::from)).map(|v| v as f32)
    }

    /// The rotation as a unit quaternion `(w, x, y, z)` (w ≥ 0).
    pub fn quaternion_wxyz(&self) -> [f64; 4] {
        nearest_rotation(&self.rotation)
    }

    /// A distance in map units (metres) as scene units: `d / s`.
    pub fn map_to_scene_distance(&self, d: f64) -> f64 {
        d / self.scale
    }

    /// The map frame's up axis `(0, 0, 1)` in the scene frame, `Rᵀ·ẑ` (ROS REP 103 maps are z-up);
    /// `partition` tiles on the plane normal to it unless `--up` is given.
    pub fn map_up_in_scene(&self) -> [f64; 3] {
        mat_t_vec(&self.rotation, DVec3::Z).to_array()
    }

    /// The box `[lo, hi]` of the 8 corners of the map-frame box `[lo, hi]` taken to the scene
    /// frame (it contains every scene point whose map image is in the map box).
    pub fn map_box_in_scene(&self, lo: [f64; 3], hi: [f64; 3]) -> ([f64; 3], [f64; 3]) {
        let mut out_lo = [f64::INFINITY; 3];
        let mut out_hi = [f64::NEG_INFINITY; 3];
        for c in 0..8 {
            let p = [
                if c & 1 == 0 { lo[0] } else { hi[0] },
                if c & 2 == 0 { lo[1] } else { hi[1] },
                if c & 4 == 0 { lo[2] } else { hi[2] },
            ];
            let s = self.to_scene(p);
            for a in 0..3 {
                out_lo[a] = out_lo[a].min(s[a]);
                out_hi[a] = out_hi[a].max(s[a]);
            }
        }
        (out_lo, out_hi)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn known() -> SceneToMap {
        let q = [0.3, -0.5, 0.7, 0.2];
        let n = q.iter().map(|x: &f64| x * x).sum::<f64>().sqrt();
        SceneToMap::new(
            2.75,
            quaternion_to_matrix(q.map(|x| x / n)),
            [412_345.25, 5_321_987.5, 87.125],
            MapSource::File,
        )
        .unwrap()
    }

    /// SplitMix64 → uniform in [-1, 1).
    fn rnd(s: &mut u64) -> f64 {
        *s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = *s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }

    #[test]
    fn a_known_transform_round_trips_scene_map_scene() {
        let t = known();
        let mut s = 1;
        for _ in 0..1000 {
            let x = [100.0 * rnd(&mut s), 100.0 * rnd(&mut s), 10.0 * rnd(&mut s)];
            let back = t.to_scene(t.to_map(x));
            for a in 0..3 {
                assert!((back[a] - x[a]).abs() < 1e-9, "{x:?} -> {back:?}");
            }
            // Distances scale by s.
            let y = [rnd(&mut s), rnd(&mut s), rnd(&mut s)];
            let d_scene = (DVec3::from(x) - DVec3::from(y)).length();
            let d_map = (DVec3::from(t.to_map(x)) - DVec3::from(t.to_map(y))).length();
            assert!((d_map - t.scale * d_scene).abs() < 1e-6 * d_map.max(1.0));
        }
        // The JSON of the manifest round-trips (to an ulp: serde_json without float_roundtrip),
        // and so does the quaternion form.
        let j = serde_json::to_vec(&t).unwrap();
        let back: SceneToMap = serde_json::from_slice(&j).unwrap();
        assert_eq!((back.scale, back.translation), (t.scale, t.translation));
        for i in 0..3 {
            for k in 0..3 {
                assert!((back.rotation[i][k] - t.rotation[i][k]).abs() <= 1e-15);
            }
        }
        let q = t.quaternion_wxyz();
        let f = serde_json::json!({"scale": t.scale, "quaternion_wxyz": q, "translation": t.translation});
        let u = SceneToMap::from_json(f.to_string().as_bytes(), "t.json").unwrap();
        for i in 0..3 {
            for k in 0..3 {
                assert!((u.rotation[i][k] - t.rotation[i][k]).abs() < 1e-12);
            }
        }
        let id = SceneToMap::identity();
        assert_eq!(id.to_map([1.0, 2.0, 3.0]), [1.0, 2.0, 3.0]);
    }

    #[test]
    fn umeyama_recovers_a_known_similarity_from_noisy_points() {
        let truth = known();
        let mut s = 42;
        let scene: Vec<[f64; 3]> = (0..12)
            .map(|_| [20.0 * rnd(&mut s), 20.0 * rnd(&mut s), 3.0 * rnd(&mut s)])
            .collect();
        let noise = 0.01; // metres
        let map: Vec<[f64; 3]> = scene
            .iter()
            .map(|&p| {
                let m = truth.to_map(p);
                [
                    m[0] + noise * rnd(&mut s),
                    m[1] + noise * rnd(&mut s),
                    m[2] + noise * rnd(&mut s),
                ]
            })
            .collect();
        let est = SceneToMap::from_point_pairs(&scene, &map).unwrap();
        assert!(
            (est.scale / truth.scale - 1.0).abs() < 1e-3,
            "{}",
            est.scale
        );
        for i in 0..3 {
            for k in 0..3 {
                assert!(
                    (est.rotation[i][k] - truth.rotation[i][k]).abs() < 1e-3,
                    "{:?} vs {:?}",
                    est.rotation,
                    truth.rotation
                );
            }
        }
        // Translation: compare where the scene origin lands (t itself is far from the points).
        let c = [0.0, 0.0, 0.0];
        let (a, b) = (est.to_map(c), truth.to_map(c));
        assert!(
            (DVec3::from(a) - DVec3::from(b)).length() < 0.05,
            "{a:?} {b:?}"
        );
        // Uniform noise in ±noise per axis has an RMS length of `noise`; the fit absorbs a little.
        let rms = est.rms_residual.unwrap();
        assert!(rms > 0.3 * noise && rms < 1.5 * noise, "rms {rms}");
        assert_eq!(est.points, Some(12));
        // Noise-free: exact to rounding, also from 3 points and from coplanar ones.
        let exact: Vec<[f64; 3]> = scene[..3].iter().map(|&p| truth.to_map(p)).collect();
        let e = SceneToMap::from_point_pairs(&scene[..3], &exact).unwrap();
        assert!((e.scale - truth.scale).abs() < 1e-9);
        assert!(e.rms_residual.unwrap() < 1e-6);
        let flat: Vec<[f64; 3]> = (0..5).map(|i| [i as f64, (i * i) as f64, 0.0]).collect();
        let flat_map: Vec<[f64; 3]> = flat.iter().map(|&p| truth.to_map(p)).collect();
        let e = SceneToMap::from_point_pairs(&flat, &flat_map).unwrap();
        assert!((e.scale - truth.scale).abs() < 1e-9);
    }

    #[test]
    fn too_few_degenerate_or_bad_inputs_are_typed_errors() {
        let t = known();
        let p = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]];
        let m: Vec<[f64; 3]> = p.iter().map(|&x| t.to_map(x)).collect();
        let e = SceneToMap::from_point_pairs(&p, &m).unwrap_err();
        assert!(
            matches!(e, Error::Invalid(_)) && e.to_string().contains("at least 3"),
            "{e}"
        );
        let line = [
            [0.0, 0.0, 0.0],
            [1.0, 1.0, 1.0],
            [2.0, 2.0, 2.0],
            [5.0, 5.0, 5.0],
        ];
        let m: Vec<[f64; 3]> = line.iter().map(|&x| t.to_map(x)).collect();
        let e = SceneToMap::from_point_pairs(&line, &m).unwrap_err();
        assert!(
            matches!(e, Error::Invalid(_)) && e.to_string().contains("collinear"),
            "{e}"
        );
        let same = [[1.0, 2.0, 3.0]; 3];
        let e = SceneToMap::from_point_pairs(&same, &same).unwrap_err();
        assert!(e.to_string().contains("same point"), "{e}");
        assert!(SceneToMap::from_point_pairs(&line[..3], &m[..2]).is_err());
        for bad in [
            r#"{"scale": 0}"#,
            r#"{"scale": -2}"#,
            r#"{"rotation": [[1,0,0],[0,1,0],[0,0,-1]]}"#,
            r#"{"rotation": [[1,0,0],[0,2,0],[0,0,1]]}"#,
            r#"{"quaternion_wxyz": [0,0,0,0]}"#,
            r#"{"rotation": [[1,0,0],[0,1,0],[0,0,1]], "quaternion_wxyz": [1,0,0,0]}"#,
        ] {
            let e = SceneToMap::from_json(bad.as_bytes(), "t.json").unwrap_err();
            assert!(matches!(e, Error::Invalid(_)), "{bad}: {e}");
        }
        let e = SceneToMap::from_json(br#"{"scael": 2}"#, "t.json").unwrap_err();
        assert!(matches!(e, Error::Format { .. }), "{e}");
    }
}
