//! tamrm: the trajectory action meta-reward model (TAMRM) as a gRPC service.
//!
//! Layers, from the inside out (`docs/architecture.md`):
//! - [`core`]: the pure shaping engine (pool, distances, kNN reward, potential term,
//!   the action validator): no I/O, no async, no locks;
//! - [`store`]: where task configs and pools live (memory, a data directory), behind one
//!   async trait with conditional commits;
//! - [`registry`]: tasks, their published pools, limits, and the serialised commit path;
//! - [`session`]: the transport-free stream: episodes, batch validation, the step path;
//! - [`service`]: the `tamrm.v1.Shaping` gRPC mapping only; errors become statuses in one
//!   place ([`service::status`]);
//! - [`auth`]: credentials, roles, tenants and quotas (SPEC §11), checked by a tower
//!   layer before any handler runs;
//! - [`server`], [`settings`], [`limits`]: the server assembly and layered settings;
//! - [`telemetry`]: Prometheus metrics (`--metrics-listen`);
//! - [`cli`]: the client-side commands (`tamrm tasks`, `tamrm pool`), a gRPC client of the
//!   server like any other;
//! - leaf modules, which use nothing of the crate and which any layer may use:
//!   [`task_key`] (the key of a tenant's task), [`net`] (TLS files, the text of a failed
//!   call), [`limits`] (the server limits), [`quota`] (tenant quotas shared by the
//!   replicas of a store).

#![warn(missing_docs)]

pub mod auth;
pub mod build_info;
pub mod cli;
pub mod core;

/// The global allocator of the `tamrm` binary, and of benchmarks that run the server in
/// their own process (`benches/loadgen.rs`), so that they measure what is deployed:
/// mimalloc, whose thread-local heaps take the tonic and h2 buffers that one worker
/// thread allocates and another frees without the lock traffic of glibc's malloc arenas
/// (+16–25 % server env-steps/s at 256 entries × 4 streams; docs/benchmarks.md).
/// Declare it with `#[global_allocator] static A: tamrm::ServerAllocator =
/// tamrm::ServerAllocator;`.
#[cfg(feature = "mimalloc")]
pub use mimalloc::MiMalloc as ServerAllocator;

/// Generated protobuf and gRPC code for `tamrm.v1`.
#[allow(missing_docs, clippy::all)]
pub mod proto {
    tonic::include_proto!("tamrm.v1");
    /// The encoded descriptor set of `proto/`, served by gRPC reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("tamrm_descriptor");
}
pub mod error;
pub mod limits;
pub mod net;
pub mod quota;
pub mod registry;
pub mod server;
pub mod service;
pub mod session;
pub mod settings;
pub mod store;
pub mod task_key;
pub mod telemetry;
