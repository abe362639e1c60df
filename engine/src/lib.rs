//! udapose-engine: the 3DUDA method (see docs/METHOD.md). It knows no I/O protocol: callers
//! hand it images, meshes and poses, and get poses and models back.

pub mod adapt;
pub mod backbone;
pub mod camera;
pub mod checkpoint;
pub mod error;
pub mod estimator;
pub mod gate;
pub mod input;
pub mod mesh;
pub mod metrics;
pub mod raster;
pub mod runtime;
pub mod signature;
mod snapshot;
pub mod solver;
pub mod train;

pub use camera::{Camera, Pose, View};
pub use error::{EngineError, Result};
pub use mesh::{Cuboid, Mesh};
pub use metrics::{
    PoseMetrics, UpSymmetry, canonical_azimuth, nearest_look_alike, pose_error, pose_error_up_to, rotation_error,
    rotation_error_up_to,
};
pub use raster::{Fragments, Rasterizer};
