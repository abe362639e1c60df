//! udapose-testkit: what tests and benches compare the engine with, kept out of the engine so
//! that no release build carries it: the autograd reference solver (render-and-compare written
//! with tch autograd, METHOD.md §6) and synthetic fixtures (a car cuboid with random vertex
//! features, rendered into feature maps of known pose).

pub mod reference;
pub mod synthetic;
