//! udapose-service: the service's logic, with no transport (ARCHITECTURE.md "Crates"). The
//! model registry and store, the inference workers, the target buffer, the adaptation jobs and
//! the internal API ([`service::Service`]) the tonic and axum adapters of `udapose-server` call.

pub mod api;
pub mod auth;
pub mod buffer;
pub mod decode;
pub mod error;
pub mod jobs;
mod jpeg_dc;
pub mod metrics;
pub mod registry;
pub mod regression;
pub mod service;
pub mod store;
pub mod threads;
pub mod views;
pub mod worker;
