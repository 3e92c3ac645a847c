//! One `Shape` stream: protocol mapping between the proto messages and a
//! [`StreamSession`]: `Open`, then one `ShapedBatch` per `StepBatch`.

use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::BytesMut;
use tokio::sync::mpsc::Sender;
use tonic::{Status, Streaming};

use super::codec::{encode_shaped, Answer};
use super::convert::{batch_view, resume_views, shaped_proto, task_proto};
use super::status::remap_decode_status;
use crate::auth::{Caller, StreamSlot, StreamWatch};
use crate::error::Error;
use crate::proto::{shape_request, shape_response, ShapeRequest, ShapeResponse};
use crate::registry::Registry;
use crate::session::{OpenRequest, Shaped, StreamSession};
use crate::telemetry::Metrics;

/// The messages a Shape stream answers with, as its transport sends them.
pub(super) trait Answers: Send + 'static {
    /// The answer to `Open`.
    fn opened(task: crate::proto::Task) -> Self;
    /// The answer to a batch; `scratch` is the stream's to keep between batches.
    fn shaped(shaped: &Shaped<'_>, scratch: &mut BytesMut) -> Self;
}

/// Messages for prost's codec (the generated `ShapingServer`).
impl Answers for ShapeResponse {
    fn opened(task: crate::proto::Task) -> Self {
        ShapeResponse {
            kind: Some(shape_response::Kind::Opened(task)),
        }
    }
    fn shaped(shaped: &Shaped<'_>, _: &mut BytesMut) -> Self {
        ShapeResponse {
            kind: Some(shape_response::Kind::Shaped(shaped_proto(shaped))),
        }
    }
}

/// Messages for [`super::codec::ShapeCodec`]: a batch's answer is encoded here, into the
/// stream's buffer (whose memory comes back once the transport has sent the bytes).
impl Answers for Answer {
    fn opened(task: crate::proto::Task) -> Self {
        Answer::Message(ShapeResponse::opened(task))
    }
    fn shaped(shaped: &Shaped<'_>, scratch: &mut BytesMut) -> Self {
        encode_shaped(shaped, scratch);
        Answer::Encoded(scratch.split().freeze())
    }
}

type Tx<A> = Sender<Result<A, Status>>;

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

/// Reads the next client message, or ends the stream: at shutdown or when a key file
/// reload takes the stream's key away (only between batches, never in the middle of
/// one), when the client half-closes, on a transport error, or after `idle` without a
/// message.
async fn next(
    inbound: &mut Streaming<ShapeRequest>,
    watch: &StreamWatch,
    idle: Option<Duration>,
) -> Result<shape_request::Kind, End> {
    let idle_timer = async {
        match idle {
            Some(d) => tokio::time::sleep(d).await,
            None => std::future::pending().await,
        }
    };
    tokio::select! {
        biased;
        _ = watch.ended() => Err(watch.why().into()),
        _ = idle_timer => Err(End::Fail(Status::unavailable(format!(
            "stream idle for {}s without a message: closed by the server (stream_idle_timeout_secs); reconnect to go on",
            idle.map_or(0, |d| d.as_secs())
        )))),
        msg = inbound.message() => match msg {
            Ok(Some(ShapeRequest { kind: Some(kind) })) => Ok(kind),
            Ok(Some(ShapeRequest { kind: None })) => Err(Error::invalid(
                "kind",
                "a ShapeRequest must set open or steps",
            )
            .into()),
            Ok(None) => Err(End::ClientDone),
            Err(status) => Err(End::Fail(remap_decode_status(status))),
        },
    }
}

async fn serve<A: Answers>(
    registry: Arc<Registry>,
    watch: &StreamWatch,
    caller: &Caller,
    metrics: Option<Arc<Metrics>>,
    mut inbound: Streaming<ShapeRequest>,
    tx: &Tx<A>,
) -> End {
    let secs = registry.limits().stream_idle_timeout_secs;
    let idle = (secs > 0).then(|| Duration::from_secs(secs));
    let mut session = match next(&mut inbound, watch, idle).await {
        Ok(shape_request::Kind::Open(o)) => {
            let resume = resume_views(&o.resume);
            let req = OpenRequest {
                tenant: caller.tenant(),
                task_id: &o.task_id,
                num_envs: o.num_envs,
                resume: &resume,
                client_id: &o.client_id,
                transport_bytes: u64::from(super::STREAM_WINDOW),
            };
            match StreamSession::open(&registry, &req).await {
                Ok(s) => s,
                Err(e) => return e.into(),
            }
        }
        Ok(shape_request::Kind::Steps(_)) => {
            return Error::invalid("open", "the first message of a Shape stream must be open")
                .into()
        }
        // SPEC §8: a missing Open, also when the stream ends before any message.
        Err(End::ClientDone) => {
            return Error::invalid(
                "open",
                "the stream ended before its first message, which must be open",
            )
            .into()
        }
        Err(end) => return end,
    };
    let opened = A::opened(task_proto(session.task()));
    if tx.send(Ok(opened)).await.is_err() {
        return End::ClientDone;
    }
    tracing::debug!(task = %session.task().id(), num_envs = session.num_envs(), "stream opened");
    // The store's key (`tenant@id`), as the commit metrics see it.
    let meter = metrics.map(|m| m.shape(session.task().key()));

    let mut scores = Vec::new();
    let mut scratch = BytesMut::new();
    loop {
        let batch = match next(&mut inbound, watch, idle).await {
            Ok(shape_request::Kind::Steps(b)) => b,
            Ok(shape_request::Kind::Open(_)) => {
                return Error::invalid("open", "the stream is already open; send steps").into()
            }
            Err(end) => return end,
        };
        if let Err(e) = caller.take_steps(batch.rewards.len()).await {
            return e.into();
        }
        let started = meter.as_ref().map(|_| Instant::now());
        let msg = match session.step(&batch_view(&batch, &mut scores)).await {
            Ok(shaped) => {
                if let (Some(m), Some(t)) = (&meter, started) {
                    m.batch(shaped.outputs.len(), shaped.episodes_ended, t.elapsed());
                }
                A::shaped(&shaped, &mut scratch)
            }
            Err(e) => return e.into(),
        };
        if tx.send(Ok(msg)).await.is_err() {
            return End::ClientDone;
        }
    }
}

/// Drives one stream of `caller` to its end and reports a failure as the stream's final
/// status; the caller's stream slot is held until then.
pub(super) async fn run<A: Answers>(
    registry: Arc<Registry>,
    watch: StreamWatch,
    (caller, _slot): (Caller, StreamSlot),
    metrics: Option<Arc<Metrics>>,
    inbound: Streaming<ShapeRequest>,
    tx: Tx<A>,
) {
    match serve(registry, &watch, &caller, metrics, inbound, &tx).await {
        End::ClientDone => {}
        End::Fail(status) => {
            tracing::debug!(code = ?status.code(), message = status.message(), "stream ended with an error");
            let _ = tx.send(Err(status)).await;
        }
    }
}
