//! One `Shape` stream: `Open`, then one `ShapedBatch` per `StepBatch`.

use std::sync::Arc;

use tokio::sync::mpsc::Sender;
use tokio_util::sync::CancellationToken;
use tonic::{Status, Streaming};

use super::convert::{task_proto, validate_task_id};
use super::status::remap_decode_status;
use super::validate::step_entries;
use crate::core::{Episode, KnnScratch, StepOutput};
use crate::error::Error;
use crate::proto::{shape_request, shape_response, Open, ShapeRequest, ShapeResponse, ShapedBatch};
use crate::registry::{Registry, StreamGuard, TaskHandle};

type Tx = Sender<Result<ShapeResponse, Status>>;

/// Entries × pool capacity above which a batch is shaped off the async workers
/// (about a millisecond of work).
const HEAVY_BATCH_WORK: usize = 1 << 20;

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

/// Reads the next client message, or ends the stream: at shutdown (only between
/// batches, never in the middle of one), when the client half-closes, or on a transport
/// error.
async fn next(
    inbound: &mut Streaming<ShapeRequest>,
    shutdown: &CancellationToken,
) -> Result<shape_request::Kind, End> {
    tokio::select! {
        biased;
        _ = shutdown.cancelled() => Err(Error::ShuttingDown.into()),
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

fn open(registry: &Registry, open: &Open) -> Result<(Arc<TaskHandle>, StreamGuard, usize), Error> {
    validate_task_id("open.task_id", &open.task_id)?;
    if open.num_envs == 0 {
        return Err(Error::invalid("open.num_envs", "must be >= 1"));
    }
    let max = registry.limits().max_envs_per_stream;
    if open.num_envs > max {
        return Err(Error::ResourceExhausted(format!(
            "open.num_envs: {} exceeds this server's limit max_envs_per_stream = {max}",
            open.num_envs
        )));
    }
    let task = registry.get(&open.task_id)?;
    let guard = task.open_stream()?;
    Ok((task, guard, open.num_envs as usize))
}

async fn serve(
    registry: Arc<Registry>,
    shutdown: CancellationToken,
    mut inbound: Streaming<ShapeRequest>,
    tx: &Tx,
) -> End {
    let (task, _guard, num_envs) = match next(&mut inbound, &shutdown).await {
        Ok(shape_request::Kind::Open(o)) => match open(&registry, &o) {
            Ok(opened) => opened,
            Err(e) => return e.into(),
        },
        Ok(shape_request::Kind::Steps(_)) => {
            return Error::invalid("open", "the first message of a Shape stream must be open")
                .into()
        }
        Err(end) => return end,
    };
    let opened = ShapeResponse {
        kind: Some(shape_response::Kind::Opened(task_proto(&task))),
    };
    if tx.send(Ok(opened)).await.is_err() {
        return End::ClientDone;
    }
    tracing::debug!(task = %task.id(), num_envs, "stream opened");

    let action_dim = task.config().action_space.action_dim();
    let mut episodes: Vec<Episode> = (0..num_envs).map(|_| Episode::new(action_dim)).collect();
    let mut scratch = KnnScratch::default();
    let mut outputs: Vec<StepOutput> = Vec::new();
    let durable = registry.is_durable();
    loop {
        let batch = match next(&mut inbound, &shutdown).await {
            Ok(shape_request::Kind::Steps(b)) => b,
            Ok(shape_request::Kind::Open(_)) => {
                return Error::invalid("open", "the stream is already open; send steps").into()
            }
            Err(end) => return end,
        };
        outputs.clear();
        // Leave the executor thread for a batch that may write to disk (only an episode
        // end can) or is long enough to hold a worker for a noticeable time.
        let may_write =
            durable && (batch.terminated.iter().any(|&d| d) || batch.truncated.iter().any(|&d| d));
        let heavy = batch
            .rewards
            .len()
            .saturating_mul(task.config().pool_capacity as usize)
            > HEAVY_BATCH_WORK;
        let result =
            step_entries(&batch, task.config(), num_envs, registry.limits()).and_then(|entries| {
                super::blocking(may_write || heavy, || {
                    task.shape_batch(&mut episodes, &entries, &mut scratch, &mut outputs)
                })
            });
        let pool_version = match result {
            Ok(v) => v,
            Err(e) => return e.into(),
        };
        let shaped = ShapedBatch {
            rewards: outputs.iter().map(|o| o.reward).collect(),
            knn_rewards: outputs.iter().map(|o| o.knn_reward).collect(),
            potentials: outputs.iter().map(|o| o.potential).collect(),
            steps: outputs
                .iter()
                .map(|o| u32::try_from(o.step).unwrap_or(u32::MAX))
                .collect(),
            knn_active: outputs.iter().map(|o| o.knn_active).collect(),
            pool_version,
        };
        let msg = ShapeResponse {
            kind: Some(shape_response::Kind::Shaped(shaped)),
        };
        if tx.send(Ok(msg)).await.is_err() {
            return End::ClientDone;
        }
    }
}

/// Drives one stream to its end and reports a failure as the stream's final status.
pub(super) async fn run(
    registry: Arc<Registry>,
    shutdown: CancellationToken,
    inbound: Streaming<ShapeRequest>,
    tx: Tx,
) {
    match serve(registry, shutdown, inbound, &tx).await {
        End::ClientDone => {}
        End::Fail(status) => {
            tracing::debug!(code = ?status.code(), message = status.message(), "stream ended with an error");
            let _ = tx.send(Err(status)).await;
        }
    }
}
