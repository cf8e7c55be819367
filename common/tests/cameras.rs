//! Camera-source tests: COLMAP binary vs text on the real snowmiku model, nerfstudio conversion
//! checked by projection, distorted-model and malformed-input errors.

use std::path::{Path, PathBuf};

use glam::DVec3;
use slag_common::camera::{View, load_views};
use slag_common::{Error, paths::source_tree_shared_dir as shared_dir};

fn snowmiku() -> PathBuf {
    shared_dir().join("scenes").join("snowmiku")
}

/// Pixel coordinates (COLMAP convention) and depth of world point `x` in `v`.
fn project(v: &View, x: DVec3) -> (f64, f64, f64) {
    let p = v.world_to_camera.rotation * x + v.world_to_camera.translation;
    let k = &v.intrinsics;
    (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy, p.z)
}

fn copy_sparse_text(dst: &Path) {
    let s0 = dst.join("sparse").join("0");
    std::fs::create_dir_all(&s0).expect("mkdir");
    for f in ["cameras.txt", "images.txt"] {
        std::fs::copy(snowmiku().join("sparse/0").join(f), s0.join(f)).expect("copy");
    }
}

#[test]
fn snowmiku_binary_and_text_agree() {
    let bin = load_views(&snowmiku()).expect("binary model loads");
    let dir = tempfile::tempdir().expect("tempdir");
    copy_sparse_text(dir.path());
    let txt = load_views(dir.path()).expect("text model loads");
    assert_eq!(bin.len(), 97);
    assert_eq!(txt.len(), 97);
    let mut names: Vec<&str> = bin.iter().map(|v| v.name.as_str()).collect();
    names.sort();
    assert_eq!(
        names,
        bin.iter().map(|v| v.name.as_str()).collect::<Vec<_>>(),
        "sorted by name"
    );
    for (b, t) in bin.iter().zip(&txt) {
        assert_eq!(b.name, t.name);
        assert_eq!(b.image_path, snowmiku().join("images").join(&b.name));
        assert!(b.image_path.is_file(), "{}", b.image_path.display());
        assert_eq!(t.image_path, dir.path().join("images").join(&t.name));
        let k = b.intrinsics;
        assert_eq!((k.width, k.height), (990, 742));
        assert!((k.fx - 819.6428892994618).abs() < 1e-9 && (k.fy - 819.22892824426).abs() < 1e-9);
        assert_eq!((k.cx, k.cy), (495.0, 371.0));
        assert_eq!(t.intrinsics, k);
        let (rb, rt) = (b.world_to_camera.rotation, t.world_to_camera.rotation);
        for (x, y) in rb.to_cols_array().iter().zip(rt.to_cols_array()) {
            assert!((x - y).abs() < 1e-9);
        }
        assert!(
            (b.world_to_camera.translation - t.world_to_camera.translation)
                .abs()
                .max_element()
                < 1e-9
        );
        // A rotation: orthonormal with determinant +1.
        assert!((rb.determinant() - 1.0).abs() < 1e-9);
    }
    // The first image's pose, read independently from images.txt line 3.
    let first = &bin[0];
    assert_eq!(first.name, "20240212_003919.jpg");
    assert!(
        (first.world_to_camera.translation
            - DVec3::new(1.343638563100403, -1.1559792850137878, 3.6460153765079215))
        .length()
            < 1e-12
    );
}

/// Builds a nerfstudio transforms.json from COLMAP views (camera-to-world, OpenGL axes).
fn transforms_json(views: &[View], per_frame_intrinsics: bool) -> serde_json::Value {
    let frames: Vec<serde_json::Value> = views
        .iter()
        .map(|v| {
            let r = v.world_to_camera.rotation.transpose(); // camera-to-world, OpenCV axes
            let c = v.world_to_camera.camera_centre();
            // OpenGL camera axes: y and z flipped.
            let (x, y, z) = (r.x_axis, -r.y_axis, -r.z_axis);
            let m = [[x.x, y.x, z.x, c.x], [x.y, y.y, z.y, c.y], [x.z, y.z, z.z, c.z], [0.0, 0.0, 0.0, 1.0]];
            let mut f = serde_json::json!({ "file_path": format!("./images/{}", v.name), "transform_matrix": m });
            if per_frame_intrinsics {
                put_intrinsics(&mut f, &v.intrinsics);
            }
            f
        })
        .collect();
    let k = views[0].intrinsics;
    let mut top = serde_json::json!({ "camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames });
    if !per_frame_intrinsics {
        put_intrinsics(&mut top, &k);
    }
    top
}

/// Writes `k` into a transforms.json object (a frame or the top level) under nerfstudio's keys.
fn put_intrinsics(json: &mut serde_json::Value, k: &slag_common::camera::Intrinsics) {
    json["fl_x"] = k.fx.into();
    json["fl_y"] = k.fy.into();
    json["cx"] = k.cx.into();
    json["cy"] = k.cy.into();
    json["w"] = k.width.into();
    json["h"] = k.height.into();
}

#[test]
fn nerfstudio_transforms_project_like_colmap() {
    let colmap = load_views(&snowmiku()).expect("loads");
    // Reverse the frame order: the loader must sort by name.
    let mut subset: Vec<View> = colmap.iter().step_by(7).cloned().collect();
    subset.reverse();
    for per_frame in [false, true] {
        let dir = tempfile::tempdir().expect("tempdir");
        let json = transforms_json(&subset, per_frame);
        std::fs::write(dir.path().join("transforms.json"), json.to_string()).expect("write");
        let ns = load_views(dir.path()).expect("transforms.json loads");
        assert_eq!(ns.len(), subset.len());
        let mut rng = 0x9e3779b97f4a7c15u64;
        let mut rand = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (rng >> 11) as f64 / (1u64 << 53) as f64 * 8.0 - 4.0
        };
        for v in &ns {
            let name = v
                .name
                .strip_prefix("images/")
                .expect("name is the file_path");
            let c = colmap.iter().find(|c| c.name == name).expect("same image");
            assert_eq!(v.image_path, dir.path().join("images").join(name));
            assert_eq!(v.intrinsics, c.intrinsics);
            let mut checked = 0;
            for _ in 0..200 {
                let x = DVec3::new(rand(), rand(), rand());
                let (u0, v0, z0) = project(c, x);
                let (u1, v1, z1) = project(v, x);
                assert!((z0 - z1).abs() < 1e-9, "depth {z0} vs {z1}");
                if z0 > 0.1 {
                    assert!(
                        (u0 - u1).abs() < 1e-6 && (v0 - v1).abs() < 1e-6,
                        "({u0},{v0}) vs ({u1},{v1})"
                    );
                    checked += 1;
                }
            }
            assert!(checked > 20);
        }
        let names: Vec<&String> = ns.iter().map(|v| &v.name).collect();
        assert!(names.windows(2).all(|w| w[0] < w[1]), "sorted by name");
    }
}

#[test]
fn nerfstudio_distortion_is_unsupported() {
    let colmap = load_views(&snowmiku()).expect("loads");
    let mut json = transforms_json(&colmap[..3], false);
    json["k1"] = 0.05.into();
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(dir.path().join("transforms.json"), json.to_string()).expect("write");
    let err = load_views(dir.path()).expect_err("distorted");
    assert!(matches!(err, Error::Unsupported { .. }), "{err}");
    assert!(
        err.to_string().contains("image_undistorter") && err.to_string().contains("k1"),
        "{err}"
    );
    json["k1"] = 0.0.into();
    json["camera_model"] = "OPENCV_FISHEYE".into();
    std::fs::write(dir.path().join("transforms.json"), json.to_string()).expect("write");
    let err = load_views(dir.path()).expect_err("fisheye");
    assert!(err.to_string().contains("OPENCV_FISHEYE"), "{err}");
    // Missing intrinsics are named.
    json["camera_model"] = "OPENCV".into();
    json.as_object_mut().expect("object").remove("fl_y");
    std::fs::write(dir.path().join("transforms.json"), json.to_string()).expect("write");
    let err = load_views(dir.path()).expect_err("no fl_y");
    assert!(err.to_string().contains("fl_y"), "{err}");
}

#[test]
fn distorted_colmap_models_are_unsupported() {
    for (line, model) in [
        (
            "1 SIMPLE_RADIAL 990 742 819.6 495 371 0.03",
            "SIMPLE_RADIAL",
        ),
        ("1 OPENCV 990 742 819 819 495 371 0.1 0.01 0 0", "OPENCV"),
        (
            "1 OPENCV_FISHEYE 990 742 819 819 495 371 0.1 0.01 0 0",
            "OPENCV_FISHEYE",
        ),
    ] {
        let dir = tempfile::tempdir().expect("tempdir");
        copy_sparse_text(dir.path());
        std::fs::write(
            dir.path().join("sparse/0/cameras.txt"),
            format!("# c\n{line}\n"),
        )
        .expect("w");
        let err = load_views(dir.path()).expect_err("distorted");
        assert!(matches!(err, Error::Unsupported { .. }), "{err}");
        let msg = err.to_string();
        assert!(
            msg.contains("image_undistorter") && msg.contains(model),
            "{msg}"
        );
    }
    // The same in binary: model id 2 = SIMPLE_RADIAL with 4 parameters.
    let dir = tempfile::tempdir().expect("tempdir");
    let s0 = dir.path().join("sparse/0");
    std::fs::create_dir_all(&s0).expect("mkdir");
    let mut cam = Vec::new();
    cam.extend(1u64.to_le_bytes());
    cam.extend(1i32.to_le_bytes());
    cam.extend(2i32.to_le_bytes());
    cam.extend(990u64.to_le_bytes());
    cam.extend(742u64.to_le_bytes());
    for p in [819.6f64, 495.0, 371.0, 0.03] {
        cam.extend(p.to_le_bytes());
    }
    std::fs::write(s0.join("cameras.bin"), &cam).expect("w");
    std::fs::copy(
        snowmiku().join("sparse/0/images.bin"),
        s0.join("images.bin"),
    )
    .expect("copy");
    let err = load_views(dir.path()).expect_err("distorted");
    assert!(
        err.to_string().contains("SIMPLE_RADIAL") && err.to_string().contains("image_undistorter"),
        "{err}"
    );
}

#[test]
fn simple_pinhole_and_two_line_text_format() {
    let dir = tempfile::tempdir().expect("tempdir");
    let s0 = dir.path().join("sparse/0");
    std::fs::create_dir_all(&s0).expect("mkdir");
    std::fs::write(
        s0.join("cameras.txt"),
        "2 SIMPLE_PINHOLE 640 480 500 320 240\n",
    )
    .expect("w");
    // Image b has a non-empty 2D point line, image a an empty one; identity-ish quaternion not unit.
    std::fs::write(
        s0.join("images.txt"),
        "# header\n7 2 0 0 0 1 2 3 2 b.png\n10.0 20.0 -1 30.0 40.0 5\n3 1 0 0 0 0 0 0 2 a.png\n\n",
    )
    .expect("w");
    let views = load_views(dir.path()).expect("loads");
    assert_eq!(
        views.iter().map(|v| v.name.as_str()).collect::<Vec<_>>(),
        ["a.png", "b.png"]
    );
    let k = views[0].intrinsics;
    assert_eq!(
        (k.width, k.height, k.fx, k.fy, k.cx, k.cy),
        (640, 480, 500.0, 500.0, 320.0, 240.0)
    );
    assert_eq!(views[1].world_to_camera.rotation, glam::DMat3::IDENTITY);
    assert_eq!(
        views[1].world_to_camera.translation,
        DVec3::new(1.0, 2.0, 3.0)
    );
}

#[test]
fn malformed_sources_give_typed_errors() {
    // Nothing there: the message lists what was looked for.
    let dir = tempfile::tempdir().expect("tempdir");
    let msg = load_views(dir.path()).expect_err("empty").to_string();
    assert!(
        msg.contains("cameras.bin")
            && msg.contains("images.txt")
            && msg.contains("transforms.json"),
        "{msg}"
    );
    assert!(load_views(&dir.path().join("missing")).is_err());

    // Truncated images.bin.
    let s0 = dir.path().join("sparse/0");
    std::fs::create_dir_all(&s0).expect("mkdir");
    std::fs::copy(
        snowmiku().join("sparse/0/cameras.bin"),
        s0.join("cameras.bin"),
    )
    .expect("copy");
    let images = std::fs::read(snowmiku().join("sparse/0/images.bin")).expect("read");
    for cut in [3usize, 100, images.len() - 10] {
        std::fs::write(s0.join("images.bin"), &images[..cut]).expect("w");
        let err = load_views(dir.path()).expect_err("truncated");
        assert!(
            matches!(err, Error::Format { .. }) && err.to_string().contains("truncated"),
            "{err}"
        );
    }

    // Unknown camera id.
    let dir = tempfile::tempdir().expect("tempdir");
    copy_sparse_text(dir.path());
    std::fs::write(
        dir.path().join("sparse/0/cameras.txt"),
        "5 PINHOLE 990 742 800 800 495 371\n",
    )
    .expect("w");
    let err = load_views(dir.path()).expect_err("unknown camera");
    assert!(err.to_string().contains("camera 1"), "{err}");

    // A bad number in images.txt names the line.
    std::fs::write(
        dir.path().join("sparse/0/cameras.txt"),
        "1 PINHOLE 990 742 800 800 495 371\n",
    )
    .expect("w");
    std::fs::write(
        dir.path().join("sparse/0/images.txt"),
        "1 1 0 0 zero 0 0 0 1 a.jpg\n\n",
    )
    .expect("w");
    let err = load_views(dir.path()).expect_err("bad number");
    assert!(
        err.to_string().contains("line 1") && err.to_string().contains("QZ"),
        "{err}"
    );
}
