//! The udapose gRPC contract: prost messages and tonic client/server stubs for
//! package `udapose.v1`, plus the encoded descriptor set for gRPC reflection.

/// Package `udapose.v1` (generated from `proto/udapose/v1/*.proto`).
pub mod v1 {
    tonic::include_proto!("udapose.v1");
}

/// Encoded `google.protobuf.FileDescriptorSet` of every udapose proto file,
/// for registering with `tonic-reflection`.
pub const FILE_DESCRIPTOR_SET: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/udapose_descriptor.bin"));
