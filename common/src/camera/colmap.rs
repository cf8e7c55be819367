//! COLMAP sparse model reader (`cameras.{bin,txt}` + `images.{bin,txt}`; `points3D` is never read).
//!
//! Binary layout (COLMAP `src/colmap/scene/reconstruction_io.cc`, little-endian):
//! `cameras.bin`: u64 count, then per camera i32 id, i32 model_id, u64 width, u64 height,
//! f64 params[model's count]. `images.bin`: u64 count, then per image i32 id, f64 qw qx qy qz,
//! f64 tx ty tz, i32 camera_id, NUL-terminated name, u64 n_points2D, n_points2D x (f64 x, f64 y,
//! i64 point3D_id). The pose (q, t) is world-to-camera.

use std::collections::HashMap;
use std::path::Path;

use glam::{DMat3, DQuat, DVec3};

use super::sources::{UNDISTORT_HINT, sort_views};
use super::{Intrinsics, View, WorldToCamera};
use crate::{Error, Result};

/// One image of a COLMAP `images.txt` (the format this module reads): its line `IMAGE_ID, QW, QX,
/// QY, QZ, TX, TY, TZ, CAMERA_ID, NAME` and an empty `POINTS2D[]` line. `(rotation, translation)`
/// is world-to-camera, rotation as a unit quaternion (w, x, y, z); ids are 1-based.
pub fn images_txt_entry(
    image_id: usize,
    rotation: DQuat,
    translation: DVec3,
    camera_id: usize,
    name: &str,
) -> String {
    let (q, t) = (rotation, translation);
    format!(
        "{image_id} {} {} {} {} {} {} {} {camera_id} {name}\n\n",
        q.w, q.x, q.y, q.z, t.x, t.y, t.z
    )
}

/// COLMAP camera models: (model_id, name, number of parameters).
const MODELS: [(i32, &str, usize); 12] = [
    (0, "SIMPLE_PINHOLE", 3),
    (1, "PINHOLE", 4),
    (2, "SIMPLE_RADIAL", 4),
    (3, "RADIAL", 5),
    (4, "OPENCV", 8),
    (5, "OPENCV_FISHEYE", 8),
    (6, "FULL_OPENCV", 12),
    (7, "FOV", 5),
    (8, "SIMPLE_RADIAL_FISHEYE", 4),
    (9, "RADIAL_FISHEYE", 5),
    (10, "THIN_PRISM_FISHEYE", 12),
    (11, "RAD_TAN_THIN_PRISM_FISHEYE", 16),
];

/// Builds pinhole intrinsics from a COLMAP model; distorted models are unsupported.
fn intrinsics(path: &Path, id: i64, model: &str, w: u64, h: u64, p: &[f64]) -> Result<Intrinsics> {
    let (fx, fy, cx, cy) = match (model, p) {
        ("PINHOLE", [fx, fy, cx, cy]) => (*fx, *fy, *cx, *cy),
        ("SIMPLE_PINHOLE", [f, cx, cy]) => (*f, *f, *cx, *cy),
        ("PINHOLE" | "SIMPLE_PINHOLE", _) => {
            return Err(Error::format(
                path,
                format!("camera {id}: {model} with {} parameters", p.len()),
            ));
        }
        _ => {
            return Err(Error::Unsupported {
                path: path.into(),
                message: format!("camera {id} uses the distorted model {model}; {UNDISTORT_HINT}"),
            });
        }
    };
    let width = u32::try_from(w).ok().filter(|&v| v > 0);
    let height = u32::try_from(h).ok().filter(|&v| v > 0);
    let (Some(width), Some(height)) = (width, height) else {
        return Err(Error::format(
            path,
            format!("camera {id}: invalid size {w}x{h}"),
        ));
    };
    if ![fx, fy, cx, cy].iter().all(|v| v.is_finite()) || fx <= 0.0 || fy <= 0.0 {
        return Err(Error::format(
            path,
            format!("camera {id}: invalid intrinsics fx {fx} fy {fy} cx {cx} cy {cy}"),
        ));
    }
    Ok(Intrinsics {
        width,
        height,
        fx,
        fy,
        cx,
        cy,
    })
}

/// World-to-camera from COLMAP's (qw, qx, qy, qz, tx, ty, tz); the quaternion is normalised.
fn pose(path: &Path, name: &str, v: &[f64; 7]) -> Result<WorldToCamera> {
    if !v.iter().all(|x| x.is_finite()) {
        return Err(Error::format(
            path,
            format!("image `{name}`: non-finite pose {v:?}"),
        ));
    }
    let q = DQuat::from_xyzw(v[1], v[2], v[3], v[0]);
    let n = q.length();
    if n < 1e-12 {
        return Err(Error::format(
            path,
            format!("image `{name}`: zero rotation quaternion"),
        ));
    }
    Ok(WorldToCamera {
        rotation: DMat3::from_quat(q / n),
        translation: DVec3::new(v[4], v[5], v[6]),
    })
}

/// A bounds-checked little-endian cursor over a COLMAP binary file.
struct Cursor<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len()).ok_or_else(|| {
            Error::format(
                self.path,
                format!(
                    "truncated: file ends at byte {} while reading {what}; re-export the COLMAP \
                     model",
                    self.bytes.len()
                ),
            )
        })?;
        let s = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N]> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N, what)?);
        Ok(a)
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        Ok(u64::from_le_bytes(self.array(what)?))
    }
    fn i32(&mut self, what: &str) -> Result<i32> {
        Ok(i32::from_le_bytes(self.array(what)?))
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        Ok(f64::from_le_bytes(self.array(what)?))
    }
}

fn read(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

/// Reads `cameras.bin` + `images.bin`; image paths are `images_dir/<name>`.
pub(super) fn load_binary(cameras: &Path, images: &Path, images_dir: &Path) -> Result<Vec<View>> {
    let cams = read_records(cameras, "camera", |c, what| {
        let id = c.i32(what)?;
        let model_id = c.i32(what)?;
        let (_, model, np) = MODELS.iter().find(|m| m.0 == model_id).ok_or_else(|| {
            Error::format(
                cameras,
                format!("camera {id}: unknown COLMAP model id {model_id}"),
            )
        })?;
        let w = c.u64(what)?;
        let h = c.u64(what)?;
        let params = (0..*np)
            .map(|_| c.f64(what))
            .collect::<Result<Vec<f64>>>()?;
        Ok((
            id as i64,
            intrinsics(cameras, id as i64, model, w, h, &params)?,
        ))
    })?
    .into_iter()
    .collect::<HashMap<i64, Intrinsics>>();
    let views = read_records(images, "image", |c, what| {
        let _id = c.i32(what)?;
        let mut v = [0f64; 7];
        for x in &mut v {
            *x = c.f64(what)?;
        }
        let cam_id = c.i32(what)? as i64;
        let rest = &c.bytes[c.pos..];
        let len = rest.iter().position(|&b| b == 0).ok_or_else(|| {
            Error::format(
                images,
                format!("truncated: the name of {what} has no terminator"),
            )
        })?;
        let name = std::str::from_utf8(&rest[..len])
            .map_err(|_| Error::format(images, format!("the name of {what} is not UTF-8")))?
            .to_string();
        c.pos += len + 1;
        let points = c.u64(what)?;
        let skip = usize::try_from(points)
            .ok()
            .and_then(|p| p.checked_mul(24))
            .ok_or_else(|| {
                Error::format(
                    images,
                    format!("{what}: implausible 2D point count {points}"),
                )
            })?;
        c.take(skip, &format!("the 2D points of {what}"))?;
        view(images, &cams, cam_id, name, &v, images_dir)
    })?;
    sort_views(images, views)
}

/// Reads a COLMAP binary file of `path`: a u64 record count, then the records, each read by
/// `record` (given the cursor and a name such as "camera #3" for messages).
///
/// Errors: I/O; [`Error::Format`] for a truncated file and whatever `record` returns.
fn read_records<T>(
    path: &Path,
    kind: &str,
    mut record: impl FnMut(&mut Cursor<'_>, &str) -> Result<T>,
) -> Result<Vec<T>> {
    let bytes = read(path)?;
    let mut c = Cursor {
        path,
        bytes: &bytes,
        pos: 0,
    };
    let n = c.u64(&format!("the {kind} count"))?;
    let mut records = Vec::new();
    for k in 0..n {
        records.push(record(&mut c, &format!("{kind} #{k}"))?);
    }
    Ok(records)
}

fn view(
    source: &Path,
    cams: &HashMap<i64, Intrinsics>,
    cam_id: i64,
    name: String,
    v: &[f64; 7],
    images_dir: &Path,
) -> Result<View> {
    let intrinsics = *cams.get(&cam_id).ok_or_else(|| {
        Error::format(
            source,
            format!(
                "image `{name}` refers to camera {cam_id}, which the cameras file does not list"
            ),
        )
    })?;
    Ok(View {
        image_path: images_dir.join(&name),
        world_to_camera: pose(source, &name, v)?,
        intrinsics,
        name,
    })
}

fn num<T: std::str::FromStr>(
    path: &Path,
    line_no: usize,
    tok: Option<&str>,
    what: &str,
) -> Result<T> {
    let tok = tok.ok_or_else(|| Error::format(path, format!("line {line_no}: missing {what}")))?;
    tok.parse::<T>().map_err(|_| {
        Error::format(
            path,
            format!("line {line_no}: {what} `{tok}` is not a number"),
        )
    })
}

/// The next record of a COLMAP text file: skips blank and `#` comment lines of `lines`
/// (`(index, line)` pairs) and returns the record's 1-based line number and its tokens.
fn next_record<'t>(
    lines: &mut impl Iterator<Item = (usize, &'t str)>,
) -> Option<(usize, std::str::SplitAsciiWhitespace<'t>)> {
    lines.find_map(|(i, line)| {
        let line = line.trim();
        (!line.is_empty() && !line.starts_with('#')).then(|| (i + 1, line.split_ascii_whitespace()))
    })
}

/// Reads `cameras.txt` + `images.txt` (COLMAP text format; `#` comments; images.txt has two lines
/// per image, the second being the possibly empty 2D-point list).
pub(super) fn load_text(cameras: &Path, images: &Path, images_dir: &Path) -> Result<Vec<View>> {
    let text = read(cameras)?;
    let text = String::from_utf8_lossy(&text);
    let mut cams = HashMap::new();
    let mut lines = text.lines().enumerate();
    while let Some((ln, mut t)) = next_record(&mut lines) {
        let id: i64 = num(cameras, ln, t.next(), "CAMERA_ID")?;
        let model = t.next().unwrap_or("");
        if !MODELS.iter().any(|m| m.1 == model) {
            return Err(Error::format(
                cameras,
                format!("line {ln}: unknown camera model `{model}`"),
            ));
        }
        let w: u64 = num(cameras, ln, t.next(), "WIDTH")?;
        let h: u64 = num(cameras, ln, t.next(), "HEIGHT")?;
        let params = t
            .map(|p| num::<f64>(cameras, ln, Some(p), "parameter"))
            .collect::<Result<Vec<_>>>()?;
        cams.insert(id, intrinsics(cameras, id, model, w, h, &params)?);
    }
    let text = read(images)?;
    let text = String::from_utf8_lossy(&text);
    let mut lines = text.lines().enumerate();
    let mut views = Vec::new();
    while let Some((ln, mut t)) = next_record(&mut lines) {
        let _id: i64 = num(images, ln, t.next(), "IMAGE_ID")?;
        let mut v = [0f64; 7];
        for (x, what) in v.iter_mut().zip(["QW", "QX", "QY", "QZ", "TX", "TY", "TZ"]) {
            *x = num(images, ln, t.next(), what)?;
        }
        let cam_id: i64 = num(images, ln, t.next(), "CAMERA_ID")?;
        let name: Vec<&str> = t.collect();
        if name.is_empty() {
            return Err(Error::format(images, format!("line {ln}: missing NAME")));
        }
        // The next line is this image's 2D points (possibly empty); it is not needed.
        lines.next();
        views.push(view(images, &cams, cam_id, name.join(" "), &v, images_dir)?);
    }
    sort_views(images, views)
}
