//! udapose-lab as a library: the parts of the offline tools that tests (and the service's
//! tests) reuse.

pub mod assets;
pub mod atomic;
pub mod augment;
pub mod corruptions;
pub mod datasets;
pub mod loader;
pub mod not_objects;
pub mod npz;
pub mod preview;
pub mod render;
pub mod synth;

/// The commit this build comes from (set by build.rs), for reports and manifests.
pub const BUILD_COMMIT: &str = env!("UDAPOSE_BUILD_COMMIT");

/// CPU model and thread count, for reports.
pub fn machine() -> String {
    let cpu = udapose_engine::runtime::cpu_model();
    let n = rayon::current_num_threads();
    format!("{cpu}, {n} thread{}", if n == 1 { "" } else { "s" })
}
