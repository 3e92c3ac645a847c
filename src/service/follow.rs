//! One `Follow` stream (SPEC §13): protocol mapping between the proto messages and a
//! [`FollowSession`]: `opened` and a snapshot, then the pool's updates as they are
//! published, and one `ack` per message of episode ends, after the updates it produced.

use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::mpsc::Sender;
use tonic::{Status, Streaming};

use super::convert::{pool_proto, task_proto, trajectory_proto};
use super::status::remap_decode_status;
use crate::auth::{Caller, StreamSlot, StreamWatch};
use crate::error::Error;
use crate::proto::{
    follow_request, follow_response, EndsAck, EpisodeEnds, FollowRequest, FollowResponse,
    PoolUpdate,
};
use crate::registry::Registry;
use crate::session::{Ack, EndInput, FollowRequest as OpenRequest, FollowSession, PoolNews};
use crate::telemetry::Metrics;

type Tx = Sender<Result<FollowResponse, Status>>;

/// What ended a stream; only errors are sent to the client.
enum End {
    ClientDone,
    Fail(Status),
}

impl From<Error> for End {
    fn from(e: Error) -> End {
        End::Fail(e.into())
    }
}

/// What woke the stream.
enum Event {
    Message(follow_request::Kind),
    PoolChanged,
}

fn idle_message(idle: Duration) -> Status {
    Status::unavailable(format!(
        "stream idle for {}s without a message: closed by the server \
         (stream_idle_timeout_secs); send an empty EpisodeEnds to keep a quiet stream open",
        idle.as_secs()
    ))
}

/// Reads the next client message, or ends the stream: at shutdown or when a key file
/// reload takes the stream's key away, when the client
/// half-closes, on a transport error, or after `idle` without a message. With `session`,
/// also returns when the task's pool changes.
async fn next(
    inbound: &mut Streaming<FollowRequest>,
    session: Option<&mut FollowSession>,
    watch: &StreamWatch,
    idle: Option<(Duration, tokio::time::Instant)>,
) -> Result<Event, End> {
    let idle_timer = async {
        match idle {
            Some((_, deadline)) => tokio::time::sleep_until(deadline).await,
            None => std::future::pending().await,
        }
    };
    let changed = async {
        match session {
            Some(s) => s.changed().await,
            None => std::future::pending().await,
        }
    };
    tokio::select! {
        biased;
        _ = watch.ended() => Err(watch.why().into()),
        r = changed => r.map(|()| Event::PoolChanged).map_err(End::from),
        msg = inbound.message() => match msg {
            Ok(Some(FollowRequest { kind: Some(kind) })) => Ok(Event::Message(kind)),
            Ok(Some(FollowRequest { kind: None })) => Err(Error::invalid(
                "kind",
                "a FollowRequest must set open or ends",
            )
            .into()),
            Ok(None) => Err(End::ClientDone),
            Err(status) => Err(End::Fail(remap_decode_status(status))),
        },
        _ = idle_timer => Err(End::Fail(idle_message(idle.map(|(d, _)| d).unwrap_or_default()))),
    }
}

fn respond(kind: follow_response::Kind) -> Result<FollowResponse, Status> {
    Ok(FollowResponse { kind: Some(kind) })
}

/// The message that brings a learner up to date.
fn news_proto(task_id: &str, news: PoolNews) -> follow_response::Kind {
    match news {
        PoolNews::Snapshot(pool) => follow_response::Kind::Snapshot(pool_proto(task_id, &pool)),
        PoolNews::Update {
            base,
            pool,
            removed,
            added,
        } => follow_response::Kind::Update(PoolUpdate {
            base_version: base,
            pool_version: pool.version(),
            removed,
            added: added.iter().map(|t| trajectory_proto(t)).collect(),
            next_seq: pool.next_seq(),
        }),
    }
}

fn ack_proto(ack: Ack) -> follow_response::Kind {
    follow_response::Kind::Ack(EndsAck {
        changed: ack.changed,
        versions: ack.versions,
        resent: ack.resent,
        pool_version: ack.pool_version,
    })
}

/// Sends what the learner lacks of the latest pool; false if the client has gone.
async fn send_news(session: &mut FollowSession, tx: &Tx) -> bool {
    match session.news() {
        Some(news) => {
            let msg = news_proto(session.task().id(), news);
            tx.send(respond(msg)).await.is_ok()
        }
        None => true,
    }
}

async fn decide(
    session: &mut FollowSession,
    caller: &Caller,
    msg: &EpisodeEnds,
) -> Result<Ack, Error> {
    let ends: Vec<EndInput<'_>> = msg
        .ends
        .iter()
        .map(|e| EndInput {
            env_id: e.env_id,
            episode: e.episode,
            actions: &e.actions,
            action_vectors: &e.action_vectors,
            score: e.score,
            reward_sum: e.reward_sum,
        })
        .collect();
    caller
        .take_steps(usize::try_from(msg.steps).unwrap_or(usize::MAX))
        .await?;
    session.ends(&ends, msg.steps).await
}

async fn serve(
    registry: Arc<Registry>,
    watch: &StreamWatch,
    caller: &Caller,
    metrics: Option<Arc<Metrics>>,
    mut inbound: Streaming<FollowRequest>,
    tx: &Tx,
) -> End {
    let secs = registry.limits().stream_idle_timeout_secs;
    let idle = (secs > 0).then(|| Duration::from_secs(secs));
    let deadline = || idle.map(|d| (d, tokio::time::Instant::now() + d));
    let mut session = match next(&mut inbound, None, watch, deadline()).await {
        Ok(Event::Message(follow_request::Kind::Open(o))) => {
            let req = OpenRequest {
                tenant: caller.tenant(),
                task_id: &o.task_id,
                num_envs: o.num_envs,
                client_id: &o.client_id,
                transport_bytes: u64::from(super::STREAM_WINDOW),
            };
            match FollowSession::open(&registry, &req).await {
                Ok(s) => s,
                Err(e) => return e.into(),
            }
        }
        Ok(_) => {
            return Error::invalid("open", "the first message of a Follow stream must be open")
                .into()
        }
        Err(End::ClientDone) => {
            return Error::invalid(
                "open",
                "the stream ended before its first message, which must be open",
            )
            .into()
        }
        Err(end) => return end,
    };
    let opened = follow_response::Kind::Opened(task_proto(session.task()));
    if tx.send(respond(opened)).await.is_err() || !send_news(&mut session, tx).await {
        return End::ClientDone;
    }
    tracing::debug!(task = %session.task().id(), "follow stream opened");
    let meter = metrics.map(|m| m.shape(session.task().key()));
    let mut until = deadline();
    loop {
        let event = next(&mut inbound, Some(&mut session), watch, until).await;
        let msg = match event {
            Ok(Event::PoolChanged) => {
                if !send_news(&mut session, tx).await {
                    return End::ClientDone;
                }
                continue;
            }
            Ok(Event::Message(follow_request::Kind::Ends(m))) => m,
            Ok(Event::Message(follow_request::Kind::Open(_))) => {
                return Error::invalid("open", "the stream is already open; send ends").into()
            }
            Err(end) => return end,
        };
        until = deadline();
        let started = Instant::now();
        let ack = match decide(&mut session, caller, &msg).await {
            Ok(ack) => ack,
            Err(e) => return e.into(),
        };
        if let Some(m) = &meter {
            let ended = ack.resent.iter().filter(|r| !**r).count();
            m.batch(msg.steps as usize, ended, started.elapsed());
        }
        // The updates carrying this message's changes go first (SPEC §13).
        if !send_news(&mut session, tx).await || tx.send(respond(ack_proto(ack))).await.is_err() {
            return End::ClientDone;
        }
    }
}

/// Drives one Follow stream of `caller` to its end and reports a failure as the stream's
/// final status; the caller's stream slot is held until then.
pub(super) async fn run(
    registry: Arc<Registry>,
    watch: StreamWatch,
    (caller, _slot): (Caller, StreamSlot),
    metrics: Option<Arc<Metrics>>,
    inbound: Streaming<FollowRequest>,
    tx: Tx,
) {
    match serve(registry, &watch, &caller, metrics, inbound, &tx).await {
        End::ClientDone => {}
        End::Fail(status) => {
            tracing::debug!(code = ?status.code(), message = status.message(), "follow stream ended with an error");
            let _ = tx.send(Err(status)).await;
        }
    }
}
