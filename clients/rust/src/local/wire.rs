//! The Follow stream's messages to and from the core's types: the pool's snapshots and
//! updates in, the episode ends out.

use std::sync::Arc;

use tamrm::core::{ActionCount, ActionSeq, Pool, TaskConfig, Trajectory};
use tamrm::proto::{self, follow_request};
use tamrm::store::PoolOp;
use tonic::Status;

pub(crate) fn pool_from(config: &TaskConfig, p: proto::Pool) -> Result<Pool, Status> {
    let trajectories = p
        .trajectories
        .into_iter()
        .map(|t| trajectory_from(config, t))
        .collect::<Result<Vec<_>, _>>()?;
    Pool::restore(
        config.pool_capacity as usize,
        trajectories,
        p.pool_version,
        p.next_seq,
    )
    .map_err(|e| Status::internal(format!("the server's pool snapshot is malformed: {e}")))
}

fn trajectory_from(config: &TaskConfig, t: proto::Trajectory) -> Result<Trajectory, Status> {
    let actions = config
        .action_space
        .to_seq(t.actions, t.action_vectors, ActionCount::AtLeastOne)
        .map_err(|e| {
            Status::internal(format!(
                "the server sent a malformed trajectory (seq {}): {}",
                t.seq, e.message
            ))
        })?;
    Ok(Trajectory {
        actions,
        score: t.score,
        seq: t.seq,
    })
}

/// The pool after an update, or an error if it does not apply to `pool`.
pub(crate) fn updated(
    config: &TaskConfig,
    pool: &Pool,
    u: proto::PoolUpdate,
) -> Result<Pool, Status> {
    if u.base_version != pool.version() {
        return Err(Status::internal(format!(
            "the server sent an update from version {} to a copy at version {}",
            u.base_version,
            pool.version()
        )));
    }
    let added = u
        .added
        .into_iter()
        .map(|t| trajectory_from(config, t).map(Arc::new))
        .collect::<Result<Vec<_>, _>>()?;
    pool.with_update(&u.removed, added, u.pool_version, u.next_seq)
        .map_err(|e| Status::internal(format!("the server's pool update is malformed: {e}")))
}

pub(crate) fn ends_request(msg: proto::EpisodeEnds) -> proto::FollowRequest {
    proto::FollowRequest {
        kind: Some(follow_request::Kind::Ends(msg)),
    }
}

/// One episode end as the proto's `EpisodeEnd`.
pub(crate) fn end_proto(op: PoolOp) -> Result<proto::EpisodeEnd, Status> {
    let PoolOp::Offer {
        actions,
        score,
        end: Some(mark),
    } = op
    else {
        return Err(Status::internal(
            "a local session commits only the episode ends of a named client",
        ));
    };
    let (actions, action_vectors) = match actions {
        ActionSeq::Discrete(v) => (v, Vec::new()),
        ActionSeq::Continuous { data, .. } => (Vec::new(), data),
    };
    Ok(proto::EpisodeEnd {
        env_id: mark.env,
        episode: mark.episode,
        actions,
        action_vectors,
        score: Some(score),
        reward_sum: score,
    })
}
