//! The transport-free session layer: one stream of a learner's vector environment on one
//! task, with each environment's episode state, the scratch buffers of the step path, and
//! the commit policy at episode end.
//!
//! A transport (the gRPC `Shape` stream, the embedded Python engine, ...) opens a
//! [`StreamSession`], feeds it [`Batch`]es and sends back the [`Shaped`] answers; it never
//! touches episodes, pools or the store itself.
//!
//! The step path of one batch: validate the whole batch ([`Batch::validate`]); drop the
//! abandoned episodes; shape entries in order against the task's published pool (no lock;
//! a change published by another stream is seen from the next entry on); at the first
//! episode end take the task's writer lock and from then on plan every episode end of the
//! batch against a private copy of the planned pool (the published one plus the changes
//! other streams queued before), so that later entries of the batch see it; at the end of
//! the batch queue the planned operations for the store, release the lock and wait until
//! the store acknowledged them: they are committed in one conditional commit, together
//! with whatever other streams of the task queued meanwhile (group commit), and the pool
//! it returns is published.

mod batch;
mod follow;

use std::sync::Arc;

pub use batch::{Batch, Entries};
pub use follow::{Ack, EndInput, FollowRequest, FollowSession, PoolNews, MAX_REPORTED_STEPS};

use crate::core::{ActionCount, Episode, KnnScratch, Pool, StepInput, StepOutput};
use crate::error::Error;
use crate::limits::Limits;
use crate::registry::{Registry, StreamBytes, StreamGuard, TaskHandle, Writer, DEFAULT_TENANT};
use crate::store::{EndMark, PoolOp};

/// Entries × pool capacity above which shaping a batch counts as long CPU work (about a
/// millisecond), which a multi-threaded async runtime should not run on a worker thread.
pub const HEAVY_BATCH_WORK: usize = 1 << 20;

/// What opens a session (the proto's `Open`).
#[derive(Debug, Clone, Copy)]
pub struct OpenRequest<'a> {
    /// The tenant of the caller (SPEC §11); [`crate::registry::DEFAULT_TENANT`] without
    /// credentials.
    pub tenant: &'a str,
    /// The task to shape on.
    pub task_id: &'a str,
    /// Environments of the stream, numbered `0..num_envs`.
    pub num_envs: u32,
    /// Episodes to resume (SPEC §9).
    pub resume: &'a [Resume<'a>],
    /// Names the client across its streams; empty for none.
    pub client_id: &'a str,
    /// Bytes the transport holds for the stream besides the session (a gRPC stream's
    /// receive window), counted with it against `max_stream_bytes` and
    /// `max_total_stream_bytes`.
    pub transport_bytes: u64,
}

impl Default for OpenRequest<'_> {
    /// The default tenant's task `""`, no env, nothing resumed, no client id.
    fn default() -> Self {
        OpenRequest {
            tenant: DEFAULT_TENANT,
            task_id: "",
            num_envs: 0,
            resume: &[],
            client_id: "",
            transport_bytes: 0,
        }
    }
}

/// One environment's current episode, resumed on a new stream (the proto's `EnvResume`).
#[derive(Debug, Clone, Copy, Default)]
pub struct Resume<'a> {
    /// The environment, `< num_envs`.
    pub env_id: u32,
    /// Discrete tasks: every action of the episode so far.
    pub actions: &'a [u32],
    /// Continuous tasks: t × action_dim floats.
    pub action_vectors: &'a [f32],
    /// Σ R of the episode so far.
    pub reward_sum: f64,
    /// Episodes this environment has ended since the client first opened.
    pub episode: u64,
}

/// The answer to one batch: one output per entry, in request order, and the task's pool
/// version after the batch.
#[derive(Debug, Clone, Copy)]
pub struct Shaped<'s> {
    /// Per entry: R_meta and its parts.
    pub outputs: &'s [StepOutput],
    /// The pool version after the batch.
    pub pool_version: u64,
    /// Episode ends of the batch offered to the pool (re-sent ones not counted).
    pub episodes_ended: usize,
}

/// One open stream on one task.
pub struct StreamSession {
    task: Arc<TaskHandle>,
    _guard: StreamGuard,
    _memory: StreamBytes,
    limits: Limits,
    episodes: Vec<Episode>,
    /// Per env: the number of the current episode (episodes ended before it).
    episode_no: Vec<u64>,
    /// The client's id, if it gave one: episode ends are then committed at most once.
    client_id: Option<Arc<str>>,
    scratch: KnnScratch,
    outputs: Vec<StepOutput>,
}

/// Task ids: 1–128 characters of `[A-Za-z0-9._:/-]`.
pub fn validate_task_id(field: &str, id: &str) -> Result<(), Error> {
    if id.is_empty() || id.len() > 128 {
        return Err(Error::invalid(
            field,
            format!("task ids are 1-128 characters, got {}", id.len()),
        ));
    }
    if let Some(c) = id
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | ':' | '/' | '-')))
    {
        return Err(Error::invalid(
            field,
            format!("task ids use only [A-Za-z0-9._:/-], found {c:?}"),
        ));
    }
    Ok(())
}

/// The checks every stream's `open` makes before it looks the task up: the task id, and
/// `num_envs` (≥ 1, within `max_envs_per_stream`).
fn check_open(registry: &Registry, task_id: &str, num_envs: u32) -> Result<(), Error> {
    validate_task_id("open.task_id", task_id)?;
    if num_envs == 0 {
        return Err(Error::invalid("open.num_envs", "must be >= 1"));
    }
    let max = registry.limits().max_envs_per_stream;
    if num_envs > max {
        return Err(Error::ResourceExhausted(format!(
            "open.num_envs: {num_envs} exceeds this server's limit max_envs_per_stream = {max}"
        )));
    }
    Ok(())
}

/// Runs CPU work that may take long without stalling a multi-threaded async runtime:
/// the current worker hands its other tasks off first. Inline elsewhere.
fn cpu<R>(long: bool, f: impl FnOnce() -> R) -> R {
    let multi = tokio::runtime::Handle::try_current()
        .map(|h| h.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread)
        .unwrap_or(false);
    if long && multi {
        tokio::task::block_in_place(f)
    } else {
        f()
    }
}

/// Where a run of lock-free shaping stopped.
enum Stop {
    /// Every entry is shaped.
    Done,
    /// Entry `i` ended an episode; its trajectory is to be offered to the pool.
    EpisodeEnd(usize, crate::core::EpisodeEnd),
}

impl StreamSession {
    /// Opens a session on `req.task_id` (SPEC §7: `Open`).
    pub async fn open(registry: &Registry, req: &OpenRequest<'_>) -> Result<StreamSession, Error> {
        check_open(registry, req.task_id, req.num_envs)?;
        let task = registry.lookup(req.tenant, req.task_id).await?;
        // A stream resumed here after its server failed shapes its next steps against
        // every change acknowledged there (SPEC §9, §10).
        task.catch_up_with_store().await;
        let config = *task.config();
        let bytes = config
            .env_bytes_bound()
            .saturating_mul(u64::from(req.num_envs))
            .saturating_add(req.transport_bytes);
        let max = registry.limits().max_stream_bytes;
        if bytes > max {
            return Err(Error::ResourceExhausted(format!(
                "open: {} envs of up to {} bytes each (max_trajectory_len {} actions of {} \
                 bytes, pool_capacity {}) and {} bytes of transport hold up to {bytes} \
                 bytes, past this server's limit max_stream_bytes = {max}; open fewer envs \
                 per stream",
                req.num_envs,
                config.env_bytes_bound(),
                config.max_trajectory_len,
                config.action_space.action_bytes(),
                config.pool_capacity,
                req.transport_bytes
            )));
        }
        let memory = registry.reserve_stream_bytes(bytes)?;
        let mut episodes: Vec<Episode> = (0..req.num_envs)
            .map(|_| Episode::new(config.action_space))
            .collect();
        let mut episode_no = vec![0; req.num_envs as usize];
        let mut seen = vec![false; episodes.len()];
        for (j, r) in req.resume.iter().enumerate() {
            let field = format!("open.resume[{j}].");
            match seen.get_mut(r.env_id as usize) {
                None => {
                    return Err(Error::invalid(
                        format!("{field}env_id"),
                        format!("env {} out of range: num_envs = {}", r.env_id, req.num_envs),
                    ))
                }
                Some(s) if *s => {
                    return Err(Error::invalid(
                        format!("{field}env_id"),
                        format!("env {} is resumed twice", r.env_id),
                    ))
                }
                Some(s) => *s = true,
            }
            let actions = config
                .action_space
                .to_seq(
                    r.actions.to_vec(),
                    r.action_vectors.to_vec(),
                    ActionCount::Any,
                )
                .map_err(|e| Error::invalid(e.field(&field), e.message))?;
            if !r.reward_sum.is_finite() {
                return Err(Error::invalid(
                    format!("{field}reward_sum"),
                    format!("must be finite, got {}", r.reward_sum),
                ));
            }
            episodes[r.env_id as usize] =
                Episode::resume(actions, r.reward_sum, config.max_trajectory_len);
            episode_no[r.env_id as usize] = r.episode;
        }
        if !req.client_id.is_empty() {
            // What the store committed for this client (on another server, or before a
            // restart) must not be committed again (SPEC §9), resumed or not.
            task.learn_ended(req.client_id).await?;
            // An env not listed starts a new episode: the one after the last end committed
            // for it, not episode 0, which would be taken for a re-send and dropped.
            for (env, count) in task.ended_counts(req.client_id) {
                if let Some(false) = seen.get(env as usize) {
                    episode_no[env as usize] = count;
                }
            }
        }
        let guard = task.open_stream()?;
        Ok(StreamSession {
            episodes,
            episode_no,
            client_id: (!req.client_id.is_empty()).then(|| Arc::from(req.client_id)),
            task,
            _guard: guard,
            _memory: memory,
            limits: *registry.limits(),
            scratch: KnnScratch::default(),
            outputs: Vec::new(),
        })
    }

    /// The task this session shapes on.
    pub fn task(&self) -> &Arc<TaskHandle> {
        &self.task
    }

    /// Environments of the session.
    pub fn num_envs(&self) -> usize {
        self.episodes.len()
    }

    /// Drops the current episodes of `envs` without updating the pool (SPEC §12); their
    /// next steps start new episodes at t = 0. Each id must be `< num_envs`, none twice.
    pub fn abandon(&mut self, envs: &[u32]) -> Result<(), Error> {
        batch::check_env_list("abandon", envs, self.num_envs())?;
        self.drop_episodes(envs);
        Ok(())
    }

    fn drop_episodes(&mut self, envs: &[u32]) {
        let space = self.task.config().action_space;
        for &e in envs {
            // An abandoned episode is not ended: its number is the next episode's.
            self.episodes[e as usize] = Episode::new(space);
        }
    }

    /// Validates and shapes one batch (SPEC §2–§6, §12). A rejected batch changes
    /// nothing; a batch that fails in the store changes no pool.
    pub async fn step(&mut self, batch: &Batch<'_>) -> Result<Shaped<'_>, Error> {
        let config = *self.task.config();
        let entries = batch.validate(&config, self.num_envs(), &self.limits)?;
        self.task.check_live()?;
        self.drop_episodes(batch.abandon);
        self.outputs.clear();
        // A resumed episode's first step compares its whole prefix with the pool.
        let resync = entries
            .iter()
            .map(|(env, _)| self.episodes[*env].pending_sync_len())
            .fold(0, usize::saturating_add);
        let long = entries
            .len()
            .saturating_add(resync)
            .saturating_mul(config.pool_capacity as usize)
            > HEAVY_BATCH_WORK;

        let mut pool = self.task.snapshot();
        let mut writer: Option<Writer> = None;
        let mut ops = Vec::new();
        let mut ended = Vec::new();
        let mut next = 0;
        loop {
            let stop = cpu(long, || {
                self.shape_run(&entries[next..], next, &mut pool, writer.is_some())
            });
            let (i, end) = match stop {
                Stop::Done => break,
                Stop::EpisodeEnd(i, end) => (i, end),
            };
            next = i + 1;
            let env = entries[i].0;
            let number = self.episode_no[env];
            // Saturating: a resumed count near 2^64 (a client's to send) cannot wrap.
            self.episode_no[env] = number.saturating_add(1);
            if writer.is_none() {
                // Plan this and every later episode end of the batch against the planned
                // pool, privately, while holding the task's writer lock.
                let w = self.task.writer().await?;
                pool = w.base().clone();
                writer = Some(w);
            }
            if let Some(client) = &self.client_id {
                if self.task.already_ended(client, env as u32, number) {
                    // A batch re-sent after its answer was lost (SPEC §9): this episode
                    // end was committed before; it is shaped, but not offered again.
                    continue;
                }
                ended.push((env as u32, number));
            }
            self.task.count_episode();
            // The private copy serves only the rest of this batch (the store's pool,
            // laid out by step, replaces it): not worth laying out.
            if let Some(change) = pool.plan_offer(end.actions.clone(), end.score) {
                Arc::make_mut(&mut pool).apply_without_layout(&change);
            }
            ops.push(PoolOp::Offer {
                actions: end.actions,
                score: end.score,
                end: self.client_id.as_ref().map(|client| EndMark {
                    client: client.clone(),
                    env: env as u32,
                    episode: number,
                }),
            });
        }
        self.task.count_steps(entries.len());
        let episodes_ended = ops.len();
        if let Some(w) = writer {
            let marks = self.client_id.as_deref().map(|c| (c, ended.as_slice()));
            let committed = self.task.commit_ends(w, ops, marks).await?;
            if committed.resent > 0 {
                // Another server committed one of these ends after this stream learnt the
                // client's record: the entries after it were shaped against a pool that
                // never existed, and this stream's episodes remember it. Its other changes
                // are committed; a resumed stream learns the record and re-sending the
                // batch gives the right answer (SPEC §9).
                return Err(Error::ResumeNeeded(format!(
                    "{} episode end(s) of this batch were committed meanwhile by another \
                     server for client {:?}: resume the stream and re-send the batch",
                    committed.resent,
                    self.client_id.as_deref().unwrap_or_default()
                )));
            }
            pool = committed.pool;
        }
        Ok(Shaped {
            outputs: &self.outputs,
            pool_version: pool.version(),
            episodes_ended,
        })
    }

    /// Shapes `entries` (which start at batch index `offset`) in order until one ends an
    /// episode. Without the writer lock, each entry sees the latest published pool.
    fn shape_run(
        &mut self,
        entries: &[(usize, StepInput<'_>)],
        offset: usize,
        pool: &mut Arc<Pool>,
        writing: bool,
    ) -> Stop {
        let config = self.task.config();
        for (j, (env, input)) in entries.iter().enumerate() {
            if !writing && self.task.published_version() != pool.version() {
                // Another stream committed a change: this step sees it.
                *pool = self.task.snapshot();
            }
            let (output, end) = self.episodes[*env].step(config, pool, input, &mut self.scratch);
            self.outputs.push(output);
            if let Some(end) = end {
                return Stop::EpisodeEnd(offset + j, end);
            }
        }
        Stop::Done
    }
}

#[cfg(test)]
mod tests;
