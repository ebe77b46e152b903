//! The one HTTP endpoint both farm binaries serve beside gRPC: `GET /metrics`, the
//! Prometheus text of whatever the caller's `render` returns at that moment. HTTP/1.1 over
//! hyper (already in the tree through tonic), one connection task per scraper; a scrape is
//! small and rare, so nothing here is tuned.

use std::convert::Infallible;
use std::future::Future;
use std::sync::Arc;

use http_body_util::Full;
use hyper::body::{Bytes, Incoming};
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::TokioIo;
use tokio::net::TcpListener;
use tokio::task::JoinSet;

/// The content type of OpenMetrics text, what `prometheus-client` encodes.
pub const OPENMETRICS_CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// What renders the metrics page on every scrape.
pub type RenderMetrics = Arc<dyn Fn() -> String + Send + Sync>;

/// Serves `GET /metrics` on `listener` until `shutdown` resolves; then open connections
/// are closed. Any other path is 404, any other method 405.
pub async fn serve_metrics(
    listener: TcpListener,
    shutdown: impl Future<Output = ()>,
    render: RenderMetrics,
) -> std::io::Result<()> {
    tokio::pin!(shutdown);
    let mut connections = JoinSet::new();
    loop {
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            () = &mut shutdown => break,
            // Reap finished connections so the set does not grow with every scrape.
            Some(_) = connections.join_next(), if !connections.is_empty() => continue,
        };
        let (stream, peer) = match accepted {
            Ok(a) => a,
            Err(e) => {
                // A full file table or a reset during accept: the listener is still good.
                tracing::warn!(error = %e, "metrics: accept failed");
                continue;
            }
        };
        let render = render.clone();
        connections.spawn(async move {
            let service = hyper::service::service_fn(move |request| answer(request, render.clone()));
            if let Err(e) =
                hyper::server::conn::http1::Builder::new().serve_connection(TokioIo::new(stream), service).await
            {
                tracing::debug!(%peer, error = %e, "metrics: connection ended");
            }
        });
    }
    connections.shutdown().await;
    Ok(())
}

async fn answer(request: Request<Incoming>, render: RenderMetrics) -> Result<Response<Full<Bytes>>, Infallible> {
    let reply = |status: StatusCode, content_type: &str, body: String| {
        let mut response = Response::new(Full::new(Bytes::from(body)));
        *response.status_mut() = status;
        if let Ok(value) = content_type.parse() {
            response.headers_mut().insert(hyper::header::CONTENT_TYPE, value);
        }
        Ok(response)
    };
    let text = "text/plain; charset=utf-8";
    if request.uri().path() != "/metrics" {
        return reply(StatusCode::NOT_FOUND, text, "not found: metrics are at /metrics\n".into());
    }
    if request.method() != Method::GET && request.method() != Method::HEAD {
        return reply(StatusCode::METHOD_NOT_ALLOWED, text, "only GET /metrics\n".into());
    }
    // Rendering reads locks briefly; off the runtime's threads, it cannot stall gRPC.
    let body = tokio::task::spawn_blocking(move || render()).await;
    match body {
        Ok(body) => reply(StatusCode::OK, OPENMETRICS_CONTENT_TYPE, body),
        Err(e) => reply(StatusCode::INTERNAL_SERVER_ERROR, text, format!("rendering the metrics failed: {e}\n")),
    }
}
