//! ROS 2 Humble message layouts that the node sends and receives, as serde structs.
//!
//! Field order and types follow the `.msg` definitions of ROS 2 Humble (`std_msgs`,
//! `builtin_interfaces`, `geometry_msgs`, `sensor_msgs`, `visualization_msgs` 4.2 of
//! `common_interfaces`, and `vision_msgs` 4.1): serialised by RustDDS's CDR serializer they are
//! byte for byte what `rclcpp` sends. Each struct's [`RosMessage::TYPE`] names its ROS type
//! (`package/msg/Name`); `ros2_client` maps it to the DDS type name
//! (`package::msg::dds_::Name_`).

use serde::{Deserialize, Serialize};

/// A ROS message type: the package and name it is known by on the ROS graph.
pub trait RosMessage: ros2_client::Message {
    /// `(package, type name)`, e.g. `("std_msgs", "String")`.
    const TYPE: (&'static str, &'static str);

    /// The [`ros2_client::MessageTypeName`] of [`RosMessage::TYPE`].
    fn type_name() -> ros2_client::MessageTypeName {
        ros2_client::MessageTypeName::new(Self::TYPE.0, Self::TYPE.1)
    }
}

macro_rules! ros_message {
    ($t:ty, $pkg:literal, $name:literal) => {
        impl ros2_client::Message for $t {}
        impl RosMessage for $t {
            const TYPE: (&'static str, &'static str) = ($pkg, $name);
        }
    };
}

/// `builtin_interfaces/msg/Time`: seconds and nanoseconds since the Unix epoch.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds, `0..1e9`.
    pub nanosec: u32,
}

impl Time {
    /// The time `t` (saturating at the `i32` seconds range).
    pub fn from_system(t: std::time::SystemTime) -> Time {
        let d = t.duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
        Time {
            sec: i32::try_from(d.as_secs()).unwrap_or(i32::MAX),
            nanosec: d.subsec_nanos(),
        }
    }
}

/// `builtin_interfaces/msg/Duration`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Duration {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds, `0..1e9`.
    pub nanosec: u32,
}

/// `std_msgs/msg/Header`: when and in which frame.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Time the data stands for.
    pub stamp: Time,
    /// Coordinate frame of the data (a tf2 frame name, e.g. `map`).
    pub frame_id: String,
}

/// `std_msgs/msg/String`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StringMsg {
    /// The text.
    pub data: String,
}
ros_message!(StringMsg, "std_msgs", "String");

/// `std_msgs/msg/ColorRGBA`, components in `0..=1`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ColorRGBA {
    /// Red.
    pub r: f32,
    /// Green.
    pub g: f32,
    /// Blue.
    pub b: f32,
    /// Alpha (0 = invisible).
    pub a: f32,
}

/// `geometry_msgs/msg/Point`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `geometry_msgs/msg/Vector3`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion` (`w` last, as ROS orders it).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

impl Default for Quaternion {
    /// The identity rotation (ROS's default is all zeros, which is no rotation at all).
    fn default() -> Self {
        Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position.
    pub position: Point,
    /// Orientation.
    pub orientation: Quaternion,
}

/// `geometry_msgs/msg/PoseWithCovariance`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// The `float64[36]` covariance of (x, y, z, rot x, rot y, rot z), row by row (the same 36
    /// doubles on the wire); all zeros = unknown.
    pub covariance: [[f64; 6]; 6],
}

impl Default for PoseWithCovariance {
    fn default() -> Self {
        PoseWithCovariance {
            pose: Pose::default(),
            covariance: [[0.0; 6]; 6],
        }
    }
}

/// `vision_msgs/msg/ObjectHypothesis` (vision_msgs 4.x).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ObjectHypothesis {
    /// The class: here the prompt.
    pub class_id: String,
    /// Its score.
    pub score: f64,
}

/// `vision_msgs/msg/ObjectHypothesisWithPose` (vision_msgs 4.x).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ObjectHypothesisWithPose {
    /// Class and score.
    pub hypothesis: ObjectHypothesis,
    /// Where the hypothesis puts the object.
    pub pose: PoseWithCovariance,
}

/// `vision_msgs/msg/BoundingBox3D`: an oriented box.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct BoundingBox3D {
    /// Centre and orientation of the box.
    pub center: Pose,
    /// Full extents along the box's own x, y, z.
    pub size: Vector3,
}

/// `vision_msgs/msg/Detection3D` (vision_msgs 4.x: no `source_cloud`, `id` last).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Detection3D {
    /// Stamp and frame.
    pub header: Header,
    /// Class hypotheses.
    pub results: Vec<ObjectHypothesisWithPose>,
    /// The box.
    pub bbox: BoundingBox3D,
    /// Identifier of the detected object.
    pub id: String,
}

/// `vision_msgs/msg/Detection3DArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Detection3DArray {
    /// Stamp and frame.
    pub header: Header,
    /// The detections.
    pub detections: Vec<Detection3D>,
}
ros_message!(Detection3DArray, "vision_msgs", "Detection3DArray");

/// `sensor_msgs/msg/PointField`: one field of a [`PointCloud2`] point.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PointField {
    /// Field name (`x`, `y`, `z`, …).
    pub name: String,
    /// Byte offset in the point.
    pub offset: u32,
    /// Element type ([`PointField::FLOAT32`], …).
    pub datatype: u8,
    /// Elements in the field.
    pub count: u32,
}

impl PointField {
    /// `sensor_msgs/msg/PointField.FLOAT32`.
    pub const FLOAT32: u8 = 7;
}

/// `sensor_msgs/msg/PointCloud2`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2 {
    /// Stamp and frame.
    pub header: Header,
    /// Rows (1 for an unordered cloud).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// Layout of one point.
    pub fields: Vec<PointField>,
    /// Byte order of `data`.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points, `row_step * height` bytes.
    pub data: Vec<u8>,
    /// No invalid (NaN) points.
    pub is_dense: bool,
}
ros_message!(PointCloud2, "sensor_msgs", "PointCloud2");

/// `sensor_msgs/msg/CompressedImage` (inside [`Marker`]; left empty here).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Stamp and frame.
    pub header: Header,
    /// `jpeg`, `png`, …
    pub format: String,
    /// The compressed bytes.
    pub data: Vec<u8>,
}

/// `visualization_msgs/msg/UVCoordinate`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct UVCoordinate {
    /// u.
    pub u: f32,
    /// v.
    pub v: f32,
}

/// `visualization_msgs/msg/MeshFile`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MeshFile {
    /// File name (its extension tells the format).
    pub filename: String,
    /// File contents.
    pub data: Vec<u8>,
}

/// `visualization_msgs/msg/Marker` (Humble layout, with the texture and mesh-file fields).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Marker {
    /// Stamp and frame.
    pub header: Header,
    /// Namespace: with `id`, the marker's identity in RViz.
    pub ns: String,
    /// Identifier within `ns`.
    pub id: i32,
    /// [`Marker::CUBE`], [`Marker::TEXT_VIEW_FACING`], …
    #[serde(rename = "type")]
    pub type_: i32,
    /// [`Marker::ADD`] or [`Marker::DELETEALL`].
    pub action: i32,
    /// Pose of the marker.
    pub pose: Pose,
    /// Size (a cube's extents; a text's height in `z`).
    pub scale: Vector3,
    /// Colour.
    pub color: ColorRGBA,
    /// How long the marker lives (0 = until replaced).
    pub lifetime: Duration,
    /// Re-transform the marker into its frame every frame.
    pub frame_locked: bool,
    /// Points (line and point markers).
    pub points: Vec<Point>,
    /// Per-point colours.
    pub colors: Vec<ColorRGBA>,
    /// Texture URI.
    pub texture_resource: String,
    /// Embedded texture.
    pub texture: CompressedImage,
    /// Texture coordinates.
    pub uv_coordinates: Vec<UVCoordinate>,
    /// Text of a text marker.
    pub text: String,
    /// Mesh URI.
    pub mesh_resource: String,
    /// Embedded mesh.
    pub mesh_file: MeshFile,
    /// Use the mesh's own materials.
    pub mesh_use_embedded_materials: bool,
}

impl Marker {
    /// `Marker.CUBE`.
    pub const CUBE: i32 = 1;
    /// `Marker.TEXT_VIEW_FACING`.
    pub const TEXT_VIEW_FACING: i32 = 9;
    /// `Marker.ADD`.
    pub const ADD: i32 = 0;
    /// `Marker.DELETEALL`: removes every marker of this publisher's namespace(s).
    pub const DELETEALL: i32 = 3;
}

/// `visualization_msgs/msg/MarkerArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MarkerArray {
    /// The markers, applied in order.
    pub markers: Vec<Marker>,
}
ros_message!(MarkerArray, "visualization_msgs", "MarkerArray");
