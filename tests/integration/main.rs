//! The integration tests: real servers on real sockets (127.0.0.1:0), real child
//! processes, real Redis. One test binary rather than one per file: each binary linked the
//! whole server and tonic's generics again, which made building the tests take several
//! times longer than running them.

mod common;

mod auth;
mod bad_input;
mod cli;
mod damage;
mod dashboard;
mod durability;
mod faults;
mod follow;
mod group_commit;
mod limits;
mod metrics;
mod migration;
mod pool_cli;
mod pool_metrics;
mod quotas;
mod redis;
mod redis_pool_rule;
mod redis_tls;
mod server;
mod tls;
mod undecodable;
mod version;
