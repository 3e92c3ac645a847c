//! Accepted connections that close without losing the peer's last unread data.
//!
//! When a server closes a TCP socket while bytes from the peer are still unread (an HTTP/2
//! WINDOW_UPDATE or PING that arrived during shutdown, say), the kernel answers with a
//! RST, and the peer's kernel may discard data it has received but its application has
//! not read yet: the last `ShapedBatch` and the stream's final status. A [`Lingering`]
//! connection instead half-closes (FIN) and, on drop, reads and discards what the peer
//! still sends for up to [`LINGER`], closing only after the peer's EOF. The lingering
//! tasks are tracked so that shutdown can wait for them.

use std::io;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio_util::task::TaskTracker;
use tonic::transport::server::{Connected, TcpConnectInfo};

/// How long a closed connection waits for the peer's EOF at most.
pub const LINGER: Duration = Duration::from_secs(2);

/// An accepted TCP connection with a lingering close.
pub struct Lingering {
    stream: Option<TcpStream>,
    tracker: TaskTracker,
}

impl Lingering {
    fn get(&mut self) -> io::Result<&mut TcpStream> {
        self.stream
            .as_mut()
            .ok_or_else(|| io::Error::new(io::ErrorKind::NotConnected, "connection closed"))
    }
}

impl Drop for Lingering {
    fn drop(&mut self) {
        let Some(mut stream) = self.stream.take() else {
            return;
        };
        let Ok(handle) = tokio::runtime::Handle::try_current() else {
            return;
        };
        self.tracker.spawn_on(
            async move {
                let _ = stream.shutdown().await;
                let mut sink = [0u8; 4096];
                let drain = async {
                    while let Ok(n) = stream.read(&mut sink).await {
                        if n == 0 {
                            break;
                        }
                    }
                };
                let _ = tokio::time::timeout(LINGER, drain).await;
            },
            &handle,
        );
    }
}

impl AsyncRead for Lingering {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        match self.get() {
            Ok(s) => Pin::new(s).poll_read(cx, buf),
            Err(e) => Poll::Ready(Err(e)),
        }
    }
}

impl AsyncWrite for Lingering {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        match self.get() {
            Ok(s) => Pin::new(s).poll_write(cx, buf),
            Err(e) => Poll::Ready(Err(e)),
        }
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        match self.get() {
            Ok(s) => Pin::new(s).poll_write_vectored(cx, bufs),
            Err(e) => Poll::Ready(Err(e)),
        }
    }

    fn is_write_vectored(&self) -> bool {
        true
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get() {
            Ok(s) => Pin::new(s).poll_flush(cx),
            Err(e) => Poll::Ready(Err(e)),
        }
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get() {
            Ok(s) => Pin::new(s).poll_shutdown(cx),
            Err(e) => Poll::Ready(Err(e)),
        }
    }
}

impl Connected for Lingering {
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> TcpConnectInfo {
        match &self.stream {
            Some(s) => s.connect_info(),
            None => TcpConnectInfo {
                local_addr: None,
                remote_addr: None,
            },
        }
    }
}

/// Accepted connections as a stream for `serve_with_incoming_shutdown`, with
/// `TCP_NODELAY` set (one small frame per environment step must not wait for delayed
/// ACKs).
pub fn incoming(
    listener: TcpListener,
    tracker: TaskTracker,
) -> impl futures::Stream<Item = io::Result<Lingering>> {
    futures::stream::unfold((listener, tracker), |(listener, tracker)| async move {
        let item = listener.accept().await.and_then(|(stream, _)| {
            stream.set_nodelay(true)?;
            Ok(Lingering {
                stream: Some(stream),
                tracker: tracker.clone(),
            })
        });
        Some((item, (listener, tracker)))
    })
}
