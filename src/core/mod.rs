//! The pure shaping core: task configuration, action encoding and distances, the memory
//! pool, the per-episode incremental kNN engine and the potential term.
//!
//! Nothing in here does I/O, locking or async work, so every formula of SPEC.md §1–§6 can
//! be tested and benchmarked in isolation. The service layer feeds it validated inputs.

pub mod actions;
pub mod config;
pub mod episode;
pub mod knn;
pub mod pool;
pub mod potential;

pub use actions::{ActionCount, ActionError, ActionRef, ActionSeq};
pub use config::{ActionSpace, ConfigError, TaskConfig, TaskConfigInput};
pub use episode::{Episode, EpisodeEnd, StepInput, StepOutput};
pub use knn::KnnScratch;
pub use pool::{Pool, PoolChange, Trajectory};
pub use potential::{potential, Values};
