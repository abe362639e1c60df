//! udapose-lab as a library: the parts of the offline tools that tests (and the service's
//! tests) reuse.

pub mod assets;
pub mod atomic;
pub mod augment;
pub mod corruptions;
pub mod datasets;
pub mod loader;
pub mod npz;
pub mod preview;
pub mod render;
pub mod synth;
