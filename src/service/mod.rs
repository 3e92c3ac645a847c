//! The `tamrm.v1.Shaping` gRPC service: protocol mapping only. Streams are
//! [`crate::session`]s, tasks and pools live in the [`crate::registry`], the numbers come
//! from [`crate::core`], and every error becomes a status in [`status`].

pub mod codec;
pub mod convert;
mod follow;
pub mod status;
mod stream;

use std::convert::Infallible;
use std::sync::Arc;
use std::task::{Context, Poll};

use tokio_stream::wrappers::ReceiverStream;
use tokio_util::sync::CancellationToken;
use tonic::codegen::{http, Body, BoxFuture, Service, StdError};
use tonic::server::NamedService;
use tonic::{Request, Response, Status, Streaming};

use crate::auth::{Caller, StreamWatch};
use crate::error::Error;
use crate::proto::shaping_server::{Shaping, ShapingServer};
use crate::proto::{self};
use crate::registry::{Registry, TaskHandle};
use crate::session::validate_task_id;
use crate::telemetry::Metrics;
use convert::{config_input, pool_proto, task_proto, trajectory_input};

/// HTTP/2 receive window of one stream: what a client can have in flight on a stream
/// whose answers it does not read (the server stops reading a stream whose two queued
/// answers are not taken). hyper's default. A Shape stream counts it against the memory
/// limits (`OpenRequest::transport_bytes`).
pub const STREAM_WINDOW: u32 = 1 << 20;

/// The Shaping service over a [`Registry`].
#[derive(Clone)]
pub struct ShapingService {
    registry: Arc<Registry>,
    shutdown: CancellationToken,
    /// `None`: every request must carry a [`Caller`] (put there by `auth::AuthLayer`);
    /// `Some`: the caller of requests without one (a server without credentials, the
    /// embedded engine).
    open_caller: Option<Caller>,
    metrics: Option<Arc<Metrics>>,
}

impl ShapingService {
    /// A service over `registry` open to every caller as the default tenant; open
    /// streams end with UNAVAILABLE once `shutdown` is cancelled (after finishing the
    /// batch they are processing).
    pub fn new(registry: Arc<Registry>, shutdown: CancellationToken) -> ShapingService {
        ShapingService {
            registry,
            shutdown,
            open_caller: Some(Caller::open()),
            metrics: None,
        }
    }

    /// Records each Shape stream's batches into `metrics` (nothing with `None`).
    pub fn with_metrics(mut self, metrics: Option<Arc<Metrics>>) -> ShapingService {
        self.metrics = metrics;
        self
    }

    /// Requires a [`Caller`] on every request (credentials are on): a request without
    /// one is refused with UNAUTHENTICATED rather than served as the default tenant.
    pub fn with_credentials_required(mut self) -> ShapingService {
        self.open_caller = None;
        self
    }

    /// Who makes `request`.
    fn caller<T>(&self, request: &Request<T>) -> Result<Caller, Error> {
        match (request.extensions().get::<Caller>(), &self.open_caller) {
            (Some(c), _) | (None, Some(c)) => Ok(c.clone()),
            (None, None) => Err(Error::Unauthenticated(
                crate::auth::MISSING_CREDENTIALS.into(),
            )),
        }
    }

    /// The caller's task `id`.
    async fn task<T>(&self, request: &Request<T>, id: &str) -> Result<Arc<TaskHandle>, Error> {
        let caller = self.caller(request)?;
        validate_task_id("task_id", id)?;
        self.registry.lookup(caller.tenant(), id).await
    }

    /// Starts a Shape stream answering with `A` (prost's messages or [`codec::Answer`]s).
    async fn open_shape<A: stream::Answers>(
        &self,
        request: Request<Streaming<proto::ShapeRequest>>,
    ) -> Result<Response<ReceiverStream<Result<A, Status>>>, Status> {
        self.start_stream("Shape", request, stream::run::<A>).await
    }

    /// Starts a Follow stream (SPEC §13).
    async fn open_follow(
        &self,
        request: Request<Streaming<proto::FollowRequest>>,
    ) -> Result<Response<ReceiverStream<Result<proto::FollowResponse, Status>>>, Status> {
        self.start_stream("Follow", request, follow::run).await
    }

    /// Takes one of the caller's stream slots, watches the caller's key (a reload that
    /// takes the key away ends the stream) and spawns `run`, which drives the stream
    /// to its end and sends its answers (two at most queued).
    async fn start_stream<Req, Resp, Fut>(
        &self,
        rpc: &'static str,
        request: Request<Streaming<Req>>,
        run: impl FnOnce(
            Arc<Registry>,
            StreamWatch,
            (Caller, crate::auth::StreamSlot),
            Option<Arc<Metrics>>,
            Streaming<Req>,
            tokio::sync::mpsc::Sender<Result<Resp, Status>>,
        ) -> Fut,
    ) -> Result<Response<ReceiverStream<Result<Resp, Status>>>, Status>
    where
        Fut: std::future::Future<Output = ()> + Send + 'static,
    {
        let caller = self.caller(&request)?;
        let slot = caller.open_stream().await?;
        let watch = caller.watch_stream(rpc, &self.shutdown);
        let inbound = request.into_inner();
        let (tx, rx) = tokio::sync::mpsc::channel(2);
        tokio::spawn(run(
            self.registry.clone(),
            watch,
            (caller, slot),
            self.metrics.clone(),
            inbound,
            tx,
        ));
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    /// An answer larger than `max_message_bytes` could not be sent; say so clearly
    /// instead of failing in the transport.
    fn fits(&self, what: &str, msg: &impl prost::Message) -> Result<(), Error> {
        let (len, max) = (msg.encoded_len(), self.registry.limits().max_message_bytes);
        if len > max {
            return Err(Error::ResourceExhausted(format!(
                "{what}: the answer is {len} bytes, over this server's limit max_message_bytes = {max}"
            )));
        }
        Ok(())
    }
}

#[tonic::async_trait]
impl Shaping for ShapingService {
    async fn create_task(
        &self,
        request: Request<proto::CreateTaskRequest>,
    ) -> Result<Response<proto::Task>, Status> {
        let caller = self.caller(&request)?;
        let req = request.into_inner();
        validate_task_id("task_id", &req.task_id)?;
        let input = config_input(req.config.as_ref());
        let task = self
            .registry
            .create(caller.tenant(), &req.task_id, &input, caller.max_tasks())
            .await?;
        tracing::info!(tenant = caller.tenant(), task = %req.task_id, config = ?task.config(), "task created (or already present)");
        Ok(Response::new(task_proto(&task)))
    }

    async fn get_task(
        &self,
        request: Request<proto::GetTaskRequest>,
    ) -> Result<Response<proto::Task>, Status> {
        let id = &request.get_ref().task_id;
        let mut task = self.task(&request, id).await?;
        // On a shared store, the counters over every replica (SPEC §10).
        if let Err(Error::TaskNotFound { .. }) = task.check_with_store().await {
            // Deleted by another server since this one loaded it, before the notification
            // came: gone, or created again there (SPEC §10), which the store answers.
            task = self.task(&request, id).await?;
            task.check_with_store().await?;
        }
        Ok(Response::new(task_proto(&task)))
    }

    async fn list_tasks(
        &self,
        request: Request<proto::ListTasksRequest>,
    ) -> Result<Response<proto::ListTasksResponse>, Status> {
        let caller = self.caller(&request)?;
        let tasks = self
            .registry
            .list(caller.tenant())
            .await?
            .iter()
            .map(|t| task_proto(t))
            .collect();
        let msg = proto::ListTasksResponse { tasks };
        self.fits("tasks", &msg)?;
        Ok(Response::new(msg))
    }

    async fn delete_task(
        &self,
        request: Request<proto::DeleteTaskRequest>,
    ) -> Result<Response<proto::DeleteTaskResponse>, Status> {
        let caller = self.caller(&request)?;
        let id = &request.get_ref().task_id;
        validate_task_id("task_id", id)?;
        self.registry.delete(caller.tenant(), id).await?;
        tracing::info!(tenant = caller.tenant(), task = %id, "task deleted");
        Ok(Response::new(proto::DeleteTaskResponse {}))
    }

    async fn reset_pool(
        &self,
        request: Request<proto::ResetPoolRequest>,
    ) -> Result<Response<proto::Task>, Status> {
        let task = self.task(&request, &request.get_ref().task_id).await?;
        let version = task.reset_pool().await?;
        tracing::info!(tenant = task.tenant(), task = %task.id(), pool_version = version, "pool reset");
        Ok(Response::new(task_proto(&task)))
    }

    async fn get_pool(
        &self,
        request: Request<proto::GetPoolRequest>,
    ) -> Result<Response<proto::Pool>, Status> {
        let task = self.task(&request, &request.get_ref().task_id).await?;
        let pool = task.pool_snapshot()?;
        let msg = pool_proto(task.id(), &pool);
        self.fits("pool", &msg)?;
        Ok(Response::new(msg))
    }

    async fn add_trajectory(
        &self,
        request: Request<proto::AddTrajectoryRequest>,
    ) -> Result<Response<proto::AddTrajectoryResponse>, Status> {
        let task = self.task(&request, &request.get_ref().task_id).await?;
        let req = request.into_inner();
        let (actions, score) = trajectory_input(task.config(), req.trajectory)?;
        let (inserted, pool_version) = task.offer(actions, score).await?;
        Ok(Response::new(proto::AddTrajectoryResponse {
            inserted,
            pool_version,
        }))
    }

    type ShapeStream = ReceiverStream<Result<proto::ShapeResponse, Status>>;

    async fn shape(
        &self,
        request: Request<Streaming<proto::ShapeRequest>>,
    ) -> Result<Response<Self::ShapeStream>, Status> {
        self.open_shape(request).await
    }

    type FollowStream = ReceiverStream<Result<proto::FollowResponse, Status>>;

    async fn follow(
        &self,
        request: Request<Streaming<proto::FollowRequest>>,
    ) -> Result<Response<Self::FollowStream>, Status> {
        self.open_follow(request).await
    }
}

/// The path of the Shape stream.
const SHAPE_PATH: &str = "/tamrm.v1.Shaping/Shape";

/// The Shaping service as the server mounts it: the Shape stream with
/// [`codec::ShapeCodec`] (the same bytes as prost's, read and written in fewer steps), and
/// every other method through the generated [`ShapingServer`]. Both refuse messages over
/// `max_message_bytes` as the generated server does.
#[derive(Clone)]
pub struct ShapingRoutes {
    service: Arc<ShapingService>,
    generated: ShapingServer<ShapingService>,
    max_message_bytes: usize,
}

impl ShapingRoutes {
    /// The routes of `service`, with messages of at most `max_message_bytes` either way.
    pub fn new(service: ShapingService, max_message_bytes: usize) -> ShapingRoutes {
        ShapingRoutes {
            generated: ShapingServer::new(service.clone())
                .max_decoding_message_size(max_message_bytes)
                .max_encoding_message_size(max_message_bytes),
            service: Arc::new(service),
            max_message_bytes,
        }
    }
}

impl NamedService for ShapingRoutes {
    const NAME: &'static str = <ShapingServer<ShapingService> as NamedService>::NAME;
}

/// The Shape method for `tonic::server::Grpc`.
struct ShapeMethod(Arc<ShapingService>);

impl tonic::server::StreamingService<proto::ShapeRequest> for ShapeMethod {
    type Response = codec::Answer;
    type ResponseStream = ReceiverStream<Result<codec::Answer, Status>>;
    type Future = BoxFuture<Response<Self::ResponseStream>, Status>;

    fn call(&mut self, request: Request<Streaming<proto::ShapeRequest>>) -> Self::Future {
        let service = self.0.clone();
        Box::pin(async move { service.open_shape(request).await })
    }
}

impl<B> Service<http::Request<B>> for ShapingRoutes
where
    B: Body + Send + 'static,
    B::Error: Into<StdError> + Send + 'static,
{
    type Response = http::Response<tonic::body::Body>;
    type Error = Infallible;
    type Future = BoxFuture<Self::Response, Self::Error>;

    fn poll_ready(&mut self, _: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        Poll::Ready(Ok(()))
    }

    fn call(&mut self, req: http::Request<B>) -> Self::Future {
        if req.uri().path() != SHAPE_PATH {
            return self.generated.call(req);
        }
        let method = ShapeMethod(self.service.clone());
        let max = Some(self.max_message_bytes);
        Box::pin(async move {
            let mut grpc =
                tonic::server::Grpc::new(codec::ShapeCodec).apply_max_message_size_config(max, max);
            Ok(grpc.streaming(method, req).await)
        })
    }
}
