//! Objects in a query's answer: groups of matching Gaussians that a planner can use (where each
//! one is, how big it is, how sure the answer is), instead of one summary over every match.
//!
//! Every coordinate is in the answer's frame (the map frame, metres, when the manifest has a
//! scene-to-map transform; else the scene frame, scene units).

/// An oriented bounding box: the principal axes (PCA) of an object's Gaussian means.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OrientedBox {
    /// Box centre, answer frame.
    pub center: [f32; 3],
    /// The three unit axes (rows), right-handed, largest extent first.
    pub axes: [[f32; 3]; 3],
    /// Full extents along each axis (metres in the map frame), same order as `axes`.
    pub extents: [f32; 3],
}

/// One object: a group of matching Gaussians.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SceneObject {
    /// Identifier, stable for the same scene, stored Gaussians and prompt (derived from the
    /// group's members, not from its rank).
    pub id: u64,
    /// Centroid weighted by score × opacity, answer frame.
    pub centroid: [f32; 3],
    /// Axis-aligned box `[min xyz, max xyz]`, answer frame.
    pub aabb: [[f32; 3]; 2],
    /// Oriented box (PCA of the members' means).
    pub obb: OrientedBox,
    /// Matching Gaussians in the group.
    pub gaussians: usize,
    /// Best score of a member.
    pub max_score: f32,
    /// Mean score of the members.
    pub mean_score: f32,
}
