//! A query's answer as the node's three messages ([`messages`]).

use slag_common::objects::{OrientedBox, SceneObject};
use slag_common::similarity::Match;

use super::msg::{
    BoundingBox3D, ColorRGBA, Detection3D, Detection3DArray, Header, Marker, MarkerArray,
    ObjectHypothesis, ObjectHypothesisWithPose, Point, PointCloud2, PointField, Pose,
    PoseWithCovariance, Quaternion, Time, Vector3,
};
use crate::query::QueryAnswer;

/// RViz namespace of the object boxes.
pub const BOX_NS: &str = "slag_objects";
/// RViz namespace of the object labels.
pub const LABEL_NS: &str = "slag_labels";
/// RViz namespace of the one text marker that says an answer is partial ([`partial_marker`]).
pub const PARTIAL_NS: &str = "slag_partial";
/// Height above the frame's origin of the [`partial_marker`], metres.
pub const PARTIAL_MARKER_HEIGHT: f64 = 1.0;
/// Height of a label's text, metres (RViz reads `scale.z`).
pub const LABEL_HEIGHT: f64 = 0.15;
/// Smallest edge drawn for a box marker (a flat object still shows), metres.
pub const MIN_MARKER_EDGE: f64 = 0.01;
/// Bytes per point of the `~/matches` cloud: x, y, z, score as little-endian f32.
pub const POINT_STEP: u32 = 16;

/// The messages of one answer.
#[derive(Debug, Clone, PartialEq)]
pub struct AnswerMessages {
    /// `~/objects`.
    pub objects: Detection3DArray,
    /// `~/matches`.
    pub matches: PointCloud2,
    /// `~/markers`.
    pub markers: MarkerArray,
}

/// The messages of `answer`, all with the header (`frame_id`, `stamp`):
/// - objects: one `Detection3D` per [`SceneObject`], `bbox` = its oriented box (centre, the
///   rotation whose columns are the box axes, extents as `size`), `results` = one hypothesis
///   with the prompt as `class_id`, the object's best score as `score` and its centroid as
///   pose; `id` = the object's id in decimal;
/// - matches: the answer's top matches as an unordered cloud (height 1) of x, y, z, score
///   (FLOAT32, little-endian, 16 bytes per point), in the answer's order;
/// - markers: `DELETEALL` first (no box of an earlier answer stays), then per object a
///   translucent `CUBE` on its oriented box and a `TEXT_VIEW_FACING` label (prompt and score)
///   above it; and, for a partial answer ([`QueryAnswer::partial`]: some stored tiles are still
///   pending verification, so the answer covers only the tiles verified so far), the
///   [`partial_marker`] last.
pub fn messages(answer: &QueryAnswer, frame_id: &str, stamp: Time) -> AnswerMessages {
    let header = Header {
        stamp,
        frame_id: frame_id.to_string(),
    };
    AnswerMessages {
        objects: Detection3DArray {
            header: header.clone(),
            detections: answer
                .objects
                .iter()
                .map(|o| detection(o, &answer.query, &header))
                .collect(),
        },
        matches: point_cloud(&answer.matches, &header),
        markers: markers(
            &answer.objects,
            &answer.query,
            answer.partial.then_some(answer.tiles_pending_verification),
            &header,
        ),
    }
}

/// The marker that says an answer is partial: a `TEXT_VIEW_FACING` marker in namespace
/// [`PARTIAL_NS`], id 0, [`PARTIAL_MARKER_HEIGHT`] above the frame's origin, orange, whose text
/// is `partial: N tiles pending verification` (`pending` = N). A subscriber of `~/markers` tells
/// a partial answer by this namespace; RViz shows the text.
pub fn partial_marker(pending: usize, header: &Header) -> Marker {
    let origin = Point {
        x: 0.0,
        y: 0.0,
        z: PARTIAL_MARKER_HEIGHT,
    };
    let orange = ColorRGBA {
        r: 1.0,
        g: 0.6,
        b: 0.0,
        a: 1.0,
    };
    let text = format!("partial: {pending} tiles pending verification");
    text_marker(header, (PARTIAL_NS, 0), origin, orange, text)
}

/// A `TEXT_VIEW_FACING` marker `(ns, id)` showing `text` at `position`, [`LABEL_HEIGHT`] high.
fn text_marker(
    header: &Header,
    (ns, id): (&str, i32),
    position: Point,
    color: ColorRGBA,
    text: String,
) -> Marker {
    Marker {
        header: header.clone(),
        ns: ns.into(),
        id,
        type_: Marker::TEXT_VIEW_FACING,
        action: Marker::ADD,
        pose: Pose {
            position,
            orientation: Quaternion::default(),
        },
        scale: Vector3 {
            x: 0.0,
            y: 0.0,
            z: LABEL_HEIGHT,
        },
        color,
        text,
        ..Marker::default()
    }
}

fn point(p: [f32; 3]) -> Point {
    Point {
        x: f64::from(p[0]),
        y: f64::from(p[1]),
        z: f64::from(p[2]),
    }
}

/// The oriented box as a pose (centre, rotation) and size.
pub fn bounding_box(b: &OrientedBox) -> BoundingBox3D {
    BoundingBox3D {
        center: Pose {
            position: point(b.center),
            orientation: rotation_to_quaternion(b.axes),
        },
        size: Vector3 {
            x: f64::from(b.extents[0]),
            y: f64::from(b.extents[1]),
            z: f64::from(b.extents[2]),
        },
    }
}

/// The unit quaternion of the rotation whose columns are `axes[0]`, `axes[1]`, `axes[2]` (the
/// rotation taking the box's x, y, z to its axes). Axes that are not orthonormal and
/// right-handed give the nearest such rotation's quaternion only approximately.
pub fn rotation_to_quaternion(axes: [[f32; 3]; 3]) -> Quaternion {
    // r[i][j]: row i, column j; column j is axes[j].
    let r = |i: usize, j: usize| f64::from(axes[j][i]);
    let trace = r(0, 0) + r(1, 1) + r(2, 2);
    let (x, y, z, w) = if trace > 0.0 {
        let s = (trace + 1.0).sqrt() * 2.0;
        (
            (r(2, 1) - r(1, 2)) / s,
            (r(0, 2) - r(2, 0)) / s,
            (r(1, 0) - r(0, 1)) / s,
            0.25 * s,
        )
    } else if r(0, 0) > r(1, 1) && r(0, 0) > r(2, 2) {
        let s = (1.0 + r(0, 0) - r(1, 1) - r(2, 2)).sqrt() * 2.0;
        (
            0.25 * s,
            (r(0, 1) + r(1, 0)) / s,
            (r(0, 2) + r(2, 0)) / s,
            (r(2, 1) - r(1, 2)) / s,
        )
    } else if r(1, 1) > r(2, 2) {
        let s = (1.0 + r(1, 1) - r(0, 0) - r(2, 2)).sqrt() * 2.0;
        (
            (r(0, 1) + r(1, 0)) / s,
            0.25 * s,
            (r(1, 2) + r(2, 1)) / s,
            (r(0, 2) - r(2, 0)) / s,
        )
    } else {
        let s = (1.0 + r(2, 2) - r(0, 0) - r(1, 1)).sqrt() * 2.0;
        (
            (r(0, 2) + r(2, 0)) / s,
            (r(1, 2) + r(2, 1)) / s,
            0.25 * s,
            (r(1, 0) - r(0, 1)) / s,
        )
    };
    let n = (x * x + y * y + z * z + w * w).sqrt();
    if n.is_finite() && n > 0.0 {
        Quaternion {
            x: x / n,
            y: y / n,
            z: z / n,
            w: w / n,
        }
    } else {
        Quaternion::default()
    }
}

fn detection(o: &SceneObject, prompt: &str, header: &Header) -> Detection3D {
    Detection3D {
        header: header.clone(),
        results: vec![ObjectHypothesisWithPose {
            hypothesis: ObjectHypothesis {
                class_id: prompt.to_string(),
                score: f64::from(o.max_score),
            },
            pose: PoseWithCovariance {
                pose: Pose {
                    position: point(o.centroid),
                    orientation: Quaternion::default(),
                },
                covariance: [[0.0; 6]; 6],
            },
        }],
        bbox: bounding_box(&o.obb),
        id: o.id.to_string(),
    }
}

/// The matches as a `PointCloud2` of x, y, z, score.
pub fn point_cloud(matches: &[Match], header: &Header) -> PointCloud2 {
    let field = |name: &str, offset: u32| PointField {
        name: name.into(),
        offset,
        datatype: PointField::FLOAT32,
        count: 1,
    };
    let mut data = Vec::with_capacity(matches.len() * POINT_STEP as usize);
    for m in matches {
        for v in [m.position[0], m.position[1], m.position[2], m.score] {
            data.extend_from_slice(&v.to_le_bytes());
        }
    }
    let width = u32::try_from(matches.len()).unwrap_or(u32::MAX);
    PointCloud2 {
        header: header.clone(),
        height: 1,
        width,
        fields: vec![
            field("x", 0),
            field("y", 4),
            field("z", 8),
            field("score", 12),
        ],
        is_bigendian: false,
        point_step: POINT_STEP,
        row_step: POINT_STEP.saturating_mul(width),
        data,
        is_dense: matches
            .iter()
            .all(|m| m.position.iter().all(|v| v.is_finite()) && m.score.is_finite()),
    }
}

/// Colour of an object's box: from red (score 0) to green (score 1), translucent.
fn score_color(score: f32) -> ColorRGBA {
    let s = score.clamp(0.0, 1.0);
    ColorRGBA {
        r: 1.0 - s,
        g: s,
        b: 0.2,
        a: 0.5,
    }
}

/// `DELETEALL`, then a box and a label per object, then, for a partial answer (`pending`:
/// `Some` count of tiles pending verification), the [`partial_marker`].
pub fn markers(
    objects: &[SceneObject],
    prompt: &str,
    pending: Option<usize>,
    header: &Header,
) -> MarkerArray {
    let mut markers = vec![Marker {
        header: header.clone(),
        action: Marker::DELETEALL,
        ..Marker::default()
    }];
    for (i, o) in objects.iter().enumerate() {
        let id = i32::try_from(i).unwrap_or(i32::MAX);
        let b = bounding_box(&o.obb);
        markers.push(Marker {
            header: header.clone(),
            ns: BOX_NS.into(),
            id,
            type_: Marker::CUBE,
            action: Marker::ADD,
            pose: b.center,
            scale: Vector3 {
                x: b.size.x.max(MIN_MARKER_EDGE),
                y: b.size.y.max(MIN_MARKER_EDGE),
                z: b.size.z.max(MIN_MARKER_EDGE),
            },
            color: score_color(o.max_score),
            ..Marker::default()
        });
        let mut above = point(o.obb.center);
        above.z = f64::from(o.aabb[1][2]) + LABEL_HEIGHT;
        let white = ColorRGBA {
            r: 1.0,
            g: 1.0,
            b: 1.0,
            a: 1.0,
        };
        let text = format!("{prompt} {:.2}", o.max_score);
        markers.push(text_marker(header, (LABEL_NS, id), above, white, text));
    }
    markers.extend(pending.map(|n| partial_marker(n, header)));
    MarkerArray { markers }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn rotate(q: &Quaternion, v: [f64; 3]) -> [f64; 3] {
        // v' = q v q* = R(q) v.
        let m = slag_common::shards::frame::quaternion_to_matrix([q.w, q.x, q.y, q.z]);
        [0, 1, 2].map(|i| (0..3).map(|j| m[i][j] * v[j]).sum())
    }

    #[test]
    fn the_quaternion_turns_the_box_frame_onto_the_axes() {
        let s = std::f32::consts::FRAC_1_SQRT_2;
        for axes in [
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            [[s, s, 0.0], [-s, s, 0.0], [0.0, 0.0, 1.0]],
            [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]],
            [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]],
            [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]],
        ] {
            let q = rotation_to_quaternion(axes);
            assert!(((q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w) - 1.0).abs() < 1e-9);
            for (k, e) in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
                .iter()
                .enumerate()
            {
                let got = rotate(&q, *e);
                for i in 0..3 {
                    assert!(
                        (got[i] - f64::from(axes[k][i])).abs() < 1e-6,
                        "{axes:?} {k}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_cloud_packs_x_y_z_score_little_endian() {
        let h = Header::default();
        let m = [
            Match {
                id: 3,
                position: [1.0, -2.0, 0.5],
                score: 0.9,
            },
            Match {
                id: 4,
                position: [0.0, 0.25, 8.0],
                score: 0.3,
            },
        ];
        let c = point_cloud(&m, &h);
        assert_eq!(
            (c.height, c.width, c.point_step, c.row_step),
            (1, 2, 16, 32)
        );
        assert_eq!(c.data.len(), 32);
        let f = |i: usize| f32::from_le_bytes(c.data[4 * i..4 * i + 4].try_into().unwrap());
        assert_eq!(
            [f(0), f(1), f(2), f(3), f(4), f(5), f(6), f(7)],
            [1.0, -2.0, 0.5, 0.9, 0.0, 0.25, 8.0, 0.3]
        );
        let names: Vec<_> = c
            .fields
            .iter()
            .map(|f| (f.name.as_str(), f.offset))
            .collect();
        assert_eq!(names, [("x", 0), ("y", 4), ("z", 8), ("score", 12)]);
        assert!(c.is_dense);
    }

    #[test]
    fn an_object_becomes_a_detection_a_box_and_a_label() {
        let o = SceneObject {
            id: 77,
            centroid: [1.0, 2.0, 3.0],
            aabb: [[0.0, 1.0, 2.0], [2.0, 3.0, 4.0]],
            obb: OrientedBox {
                center: [1.0, 2.0, 3.0],
                axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                extents: [2.0, 2.0, 0.0],
            },
            gaussians: 10,
            max_score: 0.75,
            mean_score: 0.5,
            score_mass: 5.0,
        };
        let h = Header {
            stamp: Time { sec: 5, nanosec: 6 },
            frame_id: "map".into(),
        };
        let d = detection(&o, "chair", &h);
        assert_eq!(d.id, "77");
        assert_eq!(d.results[0].hypothesis.class_id, "chair");
        assert_eq!(d.results[0].hypothesis.score, 0.75);
        assert_eq!(
            d.results[0].pose.pose.position,
            Point {
                x: 1.0,
                y: 2.0,
                z: 3.0
            }
        );
        assert_eq!(
            d.bbox.size,
            Vector3 {
                x: 2.0,
                y: 2.0,
                z: 0.0
            }
        );
        let m = markers(std::slice::from_ref(&o), "chair", None, &h);
        assert_eq!(m.markers.len(), 3);
        assert!(m.markers.iter().all(|k| k.ns != PARTIAL_NS));
        assert_eq!(m.markers[0].action, Marker::DELETEALL);
        assert_eq!(m.markers[1].type_, Marker::CUBE);
        assert_eq!(m.markers[1].scale.z, MIN_MARKER_EDGE);
        assert_eq!(m.markers[2].text, "chair 0.75");
        assert_eq!(m.markers[2].pose.position.z, 4.0 + LABEL_HEIGHT);
        assert!(m.markers.iter().all(|k| k.header == h));

        // A partial answer: the same markers, then the one that says so, last.
        let p = markers(std::slice::from_ref(&o), "chair", Some(7), &h);
        assert_eq!(p.markers.len(), 4);
        assert_eq!(p.markers[..3], m.markers[..]);
        let last = &p.markers[3];
        assert_eq!(
            (last.ns.as_str(), last.type_, last.action),
            (PARTIAL_NS, Marker::TEXT_VIEW_FACING, Marker::ADD)
        );
        assert_eq!(last.text, "partial: 7 tiles pending verification");
        assert_eq!(last.header, h);
    }
}
