//! nerfstudio `transforms.json` reader.
//!
//! Intrinsics `fl_x fl_y cx cy w h` (pixels) come from the top level or, when present, the frame;
//! `camera_model` defaults to `OPENCV` (nerfstudio's default) and is accepted only with zero
//! distortion (`k1 k2 k3 k4 p1 p2`). `frames[].transform_matrix` is camera-to-world in OpenGL
//! camera axes (x right, y up, z backwards); it is converted to the OpenCV/COLMAP camera axes
//! (flip y and z) and inverted to world-to-camera. `applied_transform` is ignored (the poses are
//! used in the frame the file states them).

use std::path::Path;

use glam::{DMat3, DVec3};
use serde_json::Value;

use super::sources::{UNDISTORT_HINT, sort_views};
use super::{Intrinsics, View, WorldToCamera};
use crate::{Error, Result};

const DISTORTION: [&str; 6] = ["k1", "k2", "k3", "k4", "p1", "p2"];

/// A value from the frame, else the top level.
fn field<'a>(frame: &'a Value, top: &'a Value, key: &str) -> Option<&'a Value> {
    frame.get(key).or_else(|| top.get(key))
}

fn number(path: &Path, frame: &Value, top: &Value, key: &str, what: &str) -> Result<f64> {
    match field(frame, top, key) {
        Some(v) => v.as_f64().filter(|x| x.is_finite()).ok_or_else(|| {
            Error::format(path, format!("{what}: `{key}` is {v}, not a finite number"))
        }),
        None => Err(Error::format(
            path,
            format!(
                "{what}: no `{key}` (neither in the frame nor at the top level); slag needs pinhole \
                 intrinsics fl_x fl_y cx cy w h in pixels"
            ),
        )),
    }
}

pub(super) fn load(path: &Path, scene_dir: &Path) -> Result<Vec<View>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let top: Value = serde_json::from_slice(&bytes)
        .map_err(|e| Error::format(path, format!("not valid JSON: {e}")))?;
    let frames = top
        .get("frames")
        .and_then(Value::as_array)
        .ok_or_else(|| Error::format(path, "no `frames` array"))?;
    let mut views = Vec::with_capacity(frames.len());
    for (i, frame) in frames.iter().enumerate() {
        let what = format!("frame {i}");
        let file_path = frame
            .get("file_path")
            .and_then(Value::as_str)
            .ok_or_else(|| Error::format(path, format!("{what}: no `file_path` string")))?;
        let name = file_path
            .strip_prefix("./")
            .unwrap_or(file_path)
            .to_string();
        let what = format!("frame {i} (`{name}`)");
        let model = field(frame, &top, "camera_model")
            .and_then(Value::as_str)
            .unwrap_or("OPENCV");
        if !matches!(model, "OPENCV" | "PINHOLE" | "SIMPLE_PINHOLE") {
            return Err(Error::Unsupported {
                path: path.into(),
                message: format!("{what}: camera_model {model}; {UNDISTORT_HINT}"),
            });
        }
        for k in DISTORTION {
            if let Some(v) = field(frame, &top, k)
                && v.as_f64() != Some(0.0)
            {
                return Err(Error::Unsupported {
                    path: path.into(),
                    message: format!(
                        "{what}: camera_model {model} with distortion {k} = {v}; {UNDISTORT_HINT}"
                    ),
                });
            }
        }
        let fx = number(path, frame, &top, "fl_x", &what)?;
        let fy = number(path, frame, &top, "fl_y", &what)?;
        let cx = number(path, frame, &top, "cx", &what)?;
        let cy = number(path, frame, &top, "cy", &what)?;
        let w = number(path, frame, &top, "w", &what)?;
        let h = number(path, frame, &top, "h", &what)?;
        let size_ok = |v: f64| v >= 1.0 && v.fract() == 0.0 && v <= u32::MAX as f64;
        if !size_ok(w) || !size_ok(h) || fx <= 0.0 || fy <= 0.0 {
            return Err(Error::format(
                path,
                format!("{what}: invalid intrinsics w {w} h {h} fl_x {fx} fl_y {fy}"),
            ));
        }
        let intrinsics = Intrinsics {
            width: w as u32,
            height: h as u32,
            fx,
            fy,
            cx,
            cy,
        };
        let world_to_camera = pose(path, frame, &what)?;
        views.push(View {
            image_path: scene_dir.join(&name),
            name,
            intrinsics,
            world_to_camera,
        });
    }
    sort_views(path, views)
}

/// `transform_matrix` (camera-to-world, OpenGL camera axes, 3x4 or 4x4 rows) to world-to-camera in
/// OpenCV camera axes.
fn pose(path: &Path, frame: &Value, what: &str) -> Result<WorldToCamera> {
    let bad = |m: &str| {
        Error::format(
            path,
            format!("{what}: `transform_matrix` {m}; expected 3 or 4 rows of 4 numbers"),
        )
    };
    let rows = frame
        .get("transform_matrix")
        .and_then(Value::as_array)
        .ok_or_else(|| bad("missing"))?;
    if rows.len() != 3 && rows.len() != 4 {
        return Err(bad(&format!("has {} rows", rows.len())));
    }
    let mut m = [[0f64; 4]; 3];
    for (r, row) in rows.iter().take(3).enumerate() {
        let row = row
            .as_array()
            .filter(|a| a.len() == 4)
            .ok_or_else(|| bad("has a bad row"))?;
        for (c, v) in row.iter().enumerate() {
            m[r][c] = v
                .as_f64()
                .filter(|x| x.is_finite())
                .ok_or_else(|| bad("has a non-number"))?;
        }
    }
    // Columns of the camera-to-world rotation are the camera axes in world coordinates; OpenGL
    // y (up) and z (back) are the negated OpenCV y (down) and z (forward).
    let x = DVec3::new(m[0][0], m[1][0], m[2][0]);
    let y = -DVec3::new(m[0][1], m[1][1], m[2][1]);
    let z = -DVec3::new(m[0][2], m[1][2], m[2][2]);
    let centre = DVec3::new(m[0][3], m[1][3], m[2][3]);
    let c2w = DMat3::from_cols(x, y, z);
    let err = (c2w.transpose() * c2w - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0f64, |a, v| a.max(v.abs()));
    if err > 1e-4 || c2w.determinant() < 0.0 {
        return Err(Error::format(
            path,
            format!(
                "{what}: the rotation part of `transform_matrix` is not a rotation (orthonormality \
                 error {err:.2e}, det {:.4}); scaled or mirrored poses are not supported",
                c2w.determinant()
            ),
        ));
    }
    let rotation = c2w.transpose();
    Ok(WorldToCamera {
        rotation,
        translation: -(rotation * centre),
    })
}
