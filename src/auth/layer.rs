//! The tower layer that checks every request's credential before any handler runs (one
//! place for every RPC, unary and streaming), and hands the handler its [`Caller`] as a
//! request extension.

use std::sync::Arc;
use std::task::{Context, Poll};

use futures::future::{Either, Ready};
use tonic::Status;
use tower::{Layer, Service};

use super::Access;

/// Wraps a service with [`Access::authorize`].
#[derive(Clone)]
pub struct AuthLayer {
    access: Arc<Access>,
}

impl AuthLayer {
    /// A layer deciding requests with `access`.
    pub fn new(access: Arc<Access>) -> AuthLayer {
        AuthLayer { access }
    }
}

impl<S> Layer<S> for AuthLayer {
    type Service = Authorized<S>;

    fn layer(&self, inner: S) -> Authorized<S> {
        Authorized {
            inner,
            access: self.access.clone(),
        }
    }
}

/// A service whose requests carry a known credential with the role they need.
#[derive(Clone)]
pub struct Authorized<S> {
    inner: S,
    access: Arc<Access>,
}

impl<S, B, R> Service<http::Request<B>> for Authorized<S>
where
    S: Service<http::Request<B>, Response = http::Response<R>>,
    R: Default,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = Either<S::Future, Ready<Result<S::Response, S::Error>>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut req: http::Request<B>) -> Self::Future {
        let authorization = req
            .headers()
            .get(http::header::AUTHORIZATION)
            .map(|v| v.as_bytes());
        match self.access.authorize(req.uri().path(), authorization) {
            Ok(caller) => {
                if let Some(caller) = caller {
                    req.extensions_mut().insert(caller);
                }
                Either::Left(self.inner.call(req))
            }
            Err(refusal) => {
                let status = Status::from(refusal);
                tracing::debug!(path = req.uri().path(), code = ?status.code(), "request refused");
                Either::Right(futures::future::ready(Ok(status.into_http())))
            }
        }
    }
}
