//! slag-edge library: the robot-side runtime (fetch shards by radius into sled, scan, serve).
pub mod scan;
