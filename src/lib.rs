//! tamrm: the trajectory action meta-reward model (TAMRM) as a gRPC service.
//!
//! Layers, from the inside out:
//! - [`core`]: the pure shaping engine (pool, distances, kNN reward, potential term);
//! - [`store`]: where pools live (memory, or a data directory on disk);
//! - [`registry`]: tasks, their pools and the stream-facing step path, with locking;
//! - [`service`]: the `tamrm.v1.Shaping` gRPC mapping and validation;
//! - [`server`] and [`settings`]: the server assembly, CLI settings and telemetry.

pub mod core;

/// Generated protobuf and gRPC code for `tamrm.v1`.
#[allow(missing_docs, clippy::all)]
pub mod proto {
    tonic::include_proto!("tamrm.v1");
    /// The encoded descriptor set of `proto/`, served by gRPC reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("tamrm_descriptor");
}
pub mod error;
pub mod registry;
pub mod server;
pub mod service;
pub mod settings;
pub mod store;
