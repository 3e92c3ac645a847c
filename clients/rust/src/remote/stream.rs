//! One `Shape` stream to a server, resumed transparently when it breaks (SPEC §9).

use std::sync::Arc;
use std::time::{Duration, Instant};

use tamrm::proto::{self, shape_request, shape_response};
use tamrm::session::Batch;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::metadata::MetadataMap;
use tonic::{Code, Status, Streaming};

use super::driver::Driver;
use super::failure::{connect_error, none_answered, resumable};
use super::targets::Targets;
use crate::answer::Answer;
use crate::error::{BoxError, Error};
use crate::options::Interrupt;
use crate::rpc::request;
use crate::session::Transport;
use crate::tracker::Tracker;

/// How often a step waiting for its answer runs the interrupt check.
const SIGNAL_CHECK: Duration = Duration::from_millis(100);

/// The first wait before resuming a broken session; it doubles up to [`MAX_PAUSE`].
pub(crate) const FIRST_PAUSE: Duration = Duration::from_millis(50);
/// The longest wait between two attempts to resume.
pub(crate) const MAX_PAUSE: Duration = Duration::from_secs(2);

/// One `Shape` stream to a server (the [`Transport`] of [`crate::Channel::open`]).
pub struct RemoteStream {
    /// The channel's addresses; `at` is the one this stream uses.
    targets: Arc<Targets>,
    at: usize,
    metadata: MetadataMap,
    tls: bool,
    task_id: String,
    num_envs: u32,
    client_id: String,
    resume_timeout: Option<Duration>,
    /// How long a step polls for its answer before it sleeps.
    busy_poll: Duration,
    interrupt: Option<Interrupt>,
    /// The stream's own connection and the runtime it runs on.
    driver: Driver,
    tx: Option<mpsc::Sender<proto::ShapeRequest>>,
    inbound: Option<Streaming<proto::ShapeResponse>>,
}

/// Where and how a stream connects (what [`crate::Channel`] hands it).
pub(crate) struct StreamConfig {
    pub targets: Arc<Targets>,
    pub metadata: MetadataMap,
    pub tls: bool,
    pub resume_timeout: Option<Duration>,
    pub busy_poll: Duration,
    pub interrupt: Option<Interrupt>,
}

/// The columns as a `StepBatch` message.
pub fn step_batch(b: &Batch<'_>) -> proto::StepBatch {
    proto::StepBatch {
        env_ids: b.env_ids.to_vec(),
        actions: b.actions.to_vec(),
        action_vectors: b.action_vectors.to_vec(),
        rewards: b.rewards.to_vec(),
        terminated: b.terminated.to_vec(),
        truncated: b.truncated.to_vec(),
        values: b.values.to_vec(),
        next_values: b.next_values.to_vec(),
        q_values: b.q_values.to_vec(),
        next_q_values: b.next_q_values.to_vec(),
        episode_scores: b.episode_scores.iter().copied().collect(),
        abandon: b.abandon.to_vec(),
    }
}

/// Runs `check` (if any).
fn check(interrupt: &Option<Interrupt>) -> Result<(), BoxError> {
    match interrupt {
        Some(f) => f(),
        None => Ok(()),
    }
}

impl RemoteStream {
    /// A stream not yet open on `task_id`.
    pub(crate) fn new(
        config: StreamConfig,
        task_id: &str,
        num_envs: u32,
        client_id: &str,
    ) -> Result<RemoteStream, Error> {
        Ok(RemoteStream {
            at: config.targets.current(),
            targets: config.targets,
            metadata: config.metadata,
            tls: config.tls,
            task_id: task_id.to_string(),
            num_envs,
            client_id: client_id.to_string(),
            resume_timeout: config.resume_timeout,
            busy_poll: config.busy_poll,
            interrupt: config.interrupt,
            driver: Driver::new()?,
            tx: None,
            inbound: None,
        })
    }

    /// The address this stream uses.
    fn target(&self) -> String {
        self.targets.get(self.at).uri()
    }

    /// Opens the stream on the current address, or with several addresses, on the first
    /// one after it that answers (an `Open` changes nothing, so it can go anywhere).
    pub(crate) fn open_anywhere(&mut self, tracker: &Tracker) -> Result<proto::Task, Status> {
        let first = self.at;
        let mut failure = match self.open(tracker) {
            Ok(task) => return Ok(task),
            Err(s) if resumable(&s) && self.targets.len() > 1 => s,
            Err(s) => return Err(s),
        };
        for i in self.targets.after(first).take(self.targets.len() - 1) {
            self.at = i;
            match self.open(tracker) {
                Ok(task) => {
                    self.targets.set_current(i);
                    return Ok(task);
                }
                Err(s) if resumable(&s) => failure = s,
                Err(s) => return Err(s),
            }
        }
        self.at = first;
        Err(none_answered(&self.targets.names(), &failure))
    }

    /// Opens the stream, resuming `tracker`'s episodes; returns the `opened` task.
    fn open(&mut self, tracker: &Tracker) -> Result<proto::Task, Status> {
        self.close_stream();
        let open = proto::ShapeRequest {
            kind: Some(shape_request::Kind::Open(proto::Open {
                task_id: self.task_id.clone(),
                num_envs: self.num_envs,
                resume: tracker.resume(),
                client_id: self.client_id.clone(),
            })),
        };
        let (tx, rx) = mpsc::channel(4);
        let mut client = self.driver.client(&self.targets, self.at);
        let req = request(ReceiverStream::new(rx), &self.metadata, None);
        let (target, tls) = (self.target(), self.tls);
        let (inbound, first) = self.driver.rt.block_on(async move {
            tx.send(open)
                .await
                .map_err(|_| Status::internal("the stream's sender closed"))?;
            let mut inbound = client
                .shape(req)
                .await
                .map_err(|s| connect_error(&target, tls, s))?
                .into_inner();
            let first = inbound
                .message()
                .await
                .map_err(|s| connect_error(&target, tls, s))?;
            Ok::<_, Status>(((tx, inbound), first))
        })?;
        match first.and_then(|r| r.kind) {
            Some(shape_response::Kind::Opened(task)) => {
                self.tx = Some(inbound.0);
                self.inbound = Some(inbound.1);
                Ok(task)
            }
            Some(shape_response::Kind::Shaped(_)) => Err(Status::internal(
                "expected 'opened' as the first Shape response, got 'shaped'",
            )),
            None => Err(Status::unavailable(
                "the server ended the Shape stream before answering Open",
            )),
        }
    }

    /// Sends one batch and waits for its answer. After a rejected batch
    /// (INVALID_ARGUMENT, nothing applied) the stream is re-opened with every episode of
    /// `tracker` resumed, so that the session goes on as if it had never been sent.
    ///
    /// When the stream breaks (the server went away, restarted, or answers UNAVAILABLE)
    /// the step resumes (SPEC §9): it re-opens the stream with every episode of `tracker`
    /// (the state before this batch) and the session's `client_id`, with exponential
    /// backoff for up to `resume_timeout`, re-sends the batch and returns its answer as
    /// if nothing had happened. The server commits no episode end twice for one
    /// `client_id`, so a batch that was applied before its answer was lost is safe to
    /// re-send.
    fn step_resuming(&mut self, batch: &Batch<'_>, tracker: &Tracker) -> Result<Answer, Error> {
        let first = self.step_once(batch, tracker);
        let Some(limit) = self.resume_timeout else {
            return first.map_err(|e| match e {
                Error::Status(s) if resumable(&s) && s.code() != Code::Unavailable => {
                    Status::unavailable(format!(
                        "the connection to {} broke under the session: {}",
                        self.target(),
                        s.message()
                    ))
                    .into()
                }
                other => other,
            });
        };
        let mut failure = match first {
            Err(Error::Status(s)) if resumable(&s) => s,
            other => return other,
        };
        let deadline = Instant::now() + limit;
        let mut pause = FIRST_PAUSE;
        let mut attempt = 0usize;
        loop {
            let now = Instant::now();
            if now >= deadline {
                self.close_now();
                return Err(Status::unavailable(format!(
                    "the session could not be resumed within resume_timeout_secs = {} ({}): {}",
                    limit.as_secs_f64(),
                    self.targets.names(),
                    failure.message()
                ))
                .into());
            }
            let n = self.targets.len();
            attempt += 1;
            // Each address in turn, starting with the one after the failed one (another
            // replica), and a pause (doubling) before each round over all of them.
            self.at = (self.at + 1) % n;
            if attempt % n == 1 || n == 1 {
                self.pause(pause.min(deadline - now))?;
                pause = (pause * 2).min(MAX_PAUSE);
            }
            match self.open(tracker) {
                Ok(_) => {}
                Err(s) if resumable(&s) => {
                    failure = s;
                    continue;
                }
                Err(s) => return Err(s.into()),
            }
            self.targets.set_current(self.at);
            match self.step_once(batch, tracker) {
                Err(Error::Status(s)) if resumable(&s) => failure = s,
                other => return other,
            }
        }
    }

    /// Waits `d` (running the interrupt check meanwhile).
    fn pause(&mut self, d: Duration) -> Result<(), Error> {
        let interrupt = &self.interrupt;
        let waited = self.driver.rt.block_on(async {
            let end = tokio::time::Instant::now() + d;
            while tokio::time::Instant::now() < end {
                tokio::time::sleep_until(end.min(tokio::time::Instant::now() + SIGNAL_CHECK)).await;
                check(interrupt)?;
            }
            Ok::<(), BoxError>(())
        });
        waited.map_err(|interrupt| {
            self.close_now();
            Error::Interrupted(interrupt)
        })
    }

    /// Drops the stream without waiting for the server.
    fn close_now(&mut self) {
        self.tx = None;
        self.inbound = None;
    }

    /// One round trip on the current stream (see [`RemoteStream::step_resuming`]).
    fn step_once(&mut self, batch: &Batch<'_>, tracker: &Tracker) -> Result<Answer, Error> {
        let (Some(tx), Some(inbound)) = (self.tx.as_ref(), self.inbound.as_mut()) else {
            return Err(Status::cancelled("the session is closed").into());
        };
        let req = proto::ShapeRequest {
            kind: Some(shape_request::Kind::Steps(step_batch(batch))),
        };
        self.driver.touch();
        let (busy_poll, interrupt) = (self.busy_poll, &self.interrupt);
        let result = self.driver.rt.block_on(async {
            if tx.send(req).await.is_err() {
                // The request stream ended: the answer (the status) says why.
            }
            let answer = inbound.message();
            tokio::pin!(answer);
            // Busy polling: the stream's runtime is this thread's, so yielding lets it
            // poll the socket without sleeping, and the vCPU stays awake for the
            // answer instead of being woken for it.
            if !busy_poll.is_zero() {
                let until = Instant::now() + busy_poll;
                while Instant::now() < until {
                    tokio::select! {
                        biased;
                        r = &mut answer => return Ok(r),
                        () = tokio::task::yield_now() => {}
                    }
                }
            }
            loop {
                tokio::select! {
                    r = &mut answer => return Ok(r),
                    () = tokio::time::sleep(SIGNAL_CHECK) => {
                        // A Ctrl-C while the server takes its time: the Python client
                        // handles signals only once it runs again.
                        check(interrupt)?;
                    }
                }
            }
        });
        let result = match result {
            Ok(r) => r,
            Err(interrupt) => {
                self.close_now();
                return Err(Error::Interrupted(interrupt));
            }
        };
        match result {
            Ok(Some(proto::ShapeResponse {
                kind: Some(shape_response::Kind::Shaped(msg)),
            })) => Ok(Answer::from_proto(msg)),
            Ok(Some(_)) => Err(Status::internal("expected a 'shaped' Shape response").into()),
            Ok(None) => {
                Err(Status::unavailable("the server ended the Shape stream unexpectedly").into())
            }
            Err(s) if s.code() == Code::InvalidArgument => {
                if self.open(tracker).is_err() {
                    self.close_stream();
                }
                Err(s.into())
            }
            Err(s) => Err(s.into()),
        }
    }

    /// Half-closes the stream and lets the server end it.
    fn close_stream(&mut self) {
        self.tx = None;
        if let Some(mut inbound) = self.inbound.take() {
            // Drain briefly so the server sees a clean end; never wait long.
            let _ = self.driver.rt.block_on(async {
                tokio::time::timeout(Duration::from_secs(2), async {
                    while let Ok(Some(_)) = inbound.message().await {}
                })
                .await
            });
        }
    }
}

impl Transport for RemoteStream {
    fn step(&mut self, batch: &Batch<'_>, tracker: &Tracker) -> Result<Answer, Error> {
        self.step_resuming(batch, tracker)
    }

    fn close(&mut self) {
        self.close_stream();
    }

    /// Re-opens with new episodes everywhere (`tracker` discarded them).
    fn reopen(&mut self, tracker: &Tracker) -> Result<(), Status> {
        self.open(tracker).map(|_| ())
    }

    fn broken(&self) -> bool {
        self.tx.is_none()
    }

    fn resumes(&self) -> bool {
        true
    }
}
