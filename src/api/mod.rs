//! The HTTP API: routes, errors, configuration and the server's lifecycle (start-up, warm-up,
//! readiness, graceful shutdown).

pub mod body_deadline;
pub mod config;
pub mod error;
pub mod extract;
pub mod offline;
pub mod openapi;
pub mod overlay;
pub mod routes;
pub mod track;
pub mod types;
pub mod web;

use std::future::Future;
use std::net::SocketAddr;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use anyhow::{Context, Result};
use axum::Router;
use axum::extract::DefaultBodyLimit;
use axum::http::HeaderMap;
use axum::routing::{get, post, put};
use metrics_exporter_prometheus::{PrometheusBuilder, PrometheusHandle};

use crate::maps::{MapCache, MapStore, Maps};
use crate::model::{BackendOptions, ModelSet};
use crate::serving::{Lifecycle, Localizer, Scheduler};

pub use config::ServeArgs;
pub use error::ApiError;

/// Everything a handler can reach.
pub struct AppState {
    pub config: ServeArgs,
    pub models: ModelSet,
    pub localizer: Localizer,
    pub maps: Arc<Maps>,
    pub scheduler: Arc<Scheduler>,
    pub lifecycle: Arc<Lifecycle>,
    pub metrics: PrometheusHandle,
}

impl AppState {
    pub fn is_ready(&self) -> bool {
        self.lifecycle.is_ready()
    }

    /// Map management needs the bearer token when one is configured.
    pub fn authorize(&self, headers: &HeaderMap) -> Result<(), ApiError> {
        let Some(token) = self.config.admin_token.as_deref().filter(|t| !t.is_empty()) else {
            return Ok(());
        };
        let given = headers
            .get(axum::http::header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "));
        match given {
            Some(g) if constant_time_eq(g.as_bytes(), token.as_bytes()) => Ok(()),
            _ => Err(ApiError::Unauthorized),
        }
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The process-wide Prometheus recorder (a process can install only one).
pub fn metrics_handle() -> PrometheusHandle {
    static HANDLE: OnceLock<PrometheusHandle> = OnceLock::new();
    HANDLE
        .get_or_init(|| {
            let seconds = [0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0];
            let builder = PrometheusBuilder::new()
                .set_buckets_for_metric(metrics_exporter_prometheus::Matcher::Suffix("_seconds".into()), &seconds)
                .and_then(|b| b.set_buckets_for_metric(metrics_exporter_prometheus::Matcher::Full("cmr_batch_size".into()), &[1.0, 2.0, 4.0, 8.0, 16.0, 32.0]))
                .and_then(|b| b.set_buckets_for_metric(metrics_exporter_prometheus::Matcher::Full("cmr_iterations".into()), &[1.0, 2.0, 5.0, 10.0, 20.0, 50.0]))
                .expect("valid buckets");
            match builder.install_recorder() {
                Ok(h) => h,
                // Another recorder is installed (embedding): keep a private one so /metrics works.
                Err(_) => PrometheusBuilder::new().build_recorder().handle(),
            }
        })
        .clone()
}

/// Loads models and maps and starts the workers. Model problems fail here, with one message.
pub fn build_state(config: ServeArgs) -> Result<Arc<AppState>> {
    let engine = &config.engine;
    engine.search.check(engine.default_hypotheses).map_err(|e| anyhow::anyhow!("--default-hypotheses and --axis-starts: {e}"))?;
    let options = BackendOptions { intra_threads: config.intra_threads(), ort_lib: engine.ort_lib.clone() };
    crate::model::runtime::environment(engine.ort_lib.as_deref())?;
    let models = ModelSet::load(&engine.models, options).with_context(|| format!("cannot load the models in {}", engine.models.display()))?;
    let (store, warnings) = MapStore::open(&config.maps).map_err(|e| anyhow::anyhow!("{e}"))?;
    for w in warnings {
        tracing::warn!("map store: {w}");
    }
    let cache = MapCache::new(engine.cache_mb.saturating_mul(1024 * 1024));
    // Registering a map runs the point encoder once, rarely and one at a time: all cores for it.
    let encoder = ModelSet { options: BackendOptions { intra_threads: config::cores(), ..models.options.clone() }, ..models.clone() };
    let maps = Arc::new(Maps::new(store, cache, Box::new(encoder.backend()?), engine.regions()));
    // With several workers, one more set of sessions with every core's threads, for whichever
    // worker is alone with work (a lone request then has the idle cores; about 25 MB).
    let lone = (config.workers() > 1 && config.intra_threads() < config::cores()).then(|| encoder.factory());
    let scheduler = Arc::new(Scheduler::start_with_lone(&models.factory(), lone.as_ref(), config.scheduler())?);
    let lifecycle = Arc::new(Lifecycle::default());
    let localizer = Localizer::new(maps.clone(), scheduler.clone(), lifecycle.clone(), models.manifest.clone(), engine.localizer());
    match localizer.calibration.threshold() {
        Some(t) => tracing::info!(
            threshold = t,
            bounded_threshold = localizer.calibration.bounded_threshold(),
            "answers are localized when p_registered >= threshold (bounded_threshold for requests with a prior_bound)"
        ),
        None => tracing::warn!("the model set has no calibrator: every answer is p_registered null, localized false"),
    }
    Ok(Arc::new(AppState { config, models, localizer, maps, scheduler, lifecycle, metrics: metrics_handle() }))
}

pub fn router(state: Arc<AppState>) -> Router {
    let body_limit = state.config.max_body_bytes;
    let map_limit = state.config.max_map_bytes;
    Router::new()
        .route("/health", get(routes::health))
        .route("/ready", get(routes::ready))
        .route("/metrics", get(routes::metrics))
        .route("/v1/info", get(routes::info))
        .route("/v1/maps", get(routes::list_maps))
        .route(
            "/v1/maps/{id}",
            get(routes::get_map).put(routes::put_map).delete(routes::delete_map).layer(DefaultBodyLimit::max(map_limit)),
        )
        .route("/v1/maps/{id}/points", get(routes::map_points))
        .route("/v1/maps/{id}/metadata", put(routes::put_metadata).layer(DefaultBodyLimit::max(1024 * 1024)))
        .route("/v1/maps/{id}/localize", post(routes::localize).layer(DefaultBodyLimit::max(body_limit)))
        .route("/v1/maps/{id}/overlay", post(overlay::overlay).layer(DefaultBodyLimit::max(body_limit)))
        .route("/", get(web::index))
        .route("/ui/{asset}", get(web::asset))
        .fallback(routes::not_found)
        .layer(axum::middleware::from_fn_with_state(
            Duration::from_millis(state.config.body_timeout_ms),
            body_deadline::limit_body_time,
        ))
        .layer(axum::middleware::from_fn_with_state(state.lifecycle.clone(), close_when_draining))
        .layer(axum::middleware::from_fn(access_log))
        .with_state(state)
}

/// The response header that carries a request's id (also read from the request, see [`request_id`]).
pub const REQUEST_ID_HEADER: &str = "x-request-id";

/// Every HTTP request, once it is answered: one `info` line on the `access` target (method,
/// path without the query, status, latency in ms, request id), the Prometheus counters
/// (`cmr_http_requests_total` by route template, method and status; `cmr_http_request_seconds`),
/// and the `x-request-id` response header. Logs made while handling it (a localization's) are in
/// a `request{id=...}` span, so they carry the same id.
async fn access_log(request: axum::extract::Request, next: axum::middleware::Next) -> axum::response::Response {
    use tracing::Instrument;
    let route = request
        .extensions()
        .get::<axum::extract::MatchedPath>()
        .map(|p| p.as_str().to_string())
        .unwrap_or_else(|| "unmatched".into());
    let method = request.method().clone();
    let path: String = request.uri().path().chars().take(256).collect();
    let id = request_id(request.headers());
    let started = std::time::Instant::now();
    let mut response = next.run(request).instrument(tracing::info_span!("request", id = %id)).await;
    let latency = started.elapsed();
    let status = response.status().as_u16();
    tracing::info!(target: "access", %method, path = %path, status = %status, latency_ms = format_args!("{:.1}", latency.as_secs_f64() * 1000.0), request_id = %id);
    metrics::counter!("cmr_http_requests_total", "route" => route.clone(), "method" => method.to_string(), "status" => status.to_string()).increment(1);
    metrics::histogram!("cmr_http_request_seconds", "route" => route).record(latency.as_secs_f64());
    if let Ok(v) = axum::http::HeaderValue::from_str(&id) {
        response.headers_mut().insert(REQUEST_ID_HEADER, v);
    }
    response
}

/// The request's id: the client's `x-request-id` when it is 1 to 64 characters of
/// `[A-Za-z0-9._:-]` (so a proxy's id follows the request through), else a new one: this
/// process's random 8-hex-digit prefix, a dash and a counter (`3f9a0c12-17`).
pub fn request_id(headers: &HeaderMap) -> String {
    static PREFIX: OnceLock<u32> = OnceLock::new();
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let given = headers.get(REQUEST_ID_HEADER).and_then(|v| v.to_str().ok()).filter(|v| {
        (1..=64).contains(&v.len()) && v.bytes().all(|b| b.is_ascii_alphanumeric() || b"._:-".contains(&b))
    });
    match given {
        Some(v) => v.to_string(),
        None => {
            let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            format!("{:08x}-{n}", PREFIX.get_or_init(rand::random::<u32>))
        }
    }
}

/// While draining, every response asks the client to close its connection, so kept-alive
/// connections end after their current request instead of being cut.
async fn close_when_draining(
    axum::extract::State(lifecycle): axum::extract::State<Arc<Lifecycle>>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> axum::response::Response {
    let mut response = next.run(request).await;
    if lifecycle.is_draining() {
        response.headers_mut().insert(axum::http::header::CONNECTION, axum::http::HeaderValue::from_static("close"));
    }
    response
}

/// Runs the registration encoder on the model's N points (`Maps::warm_up_encoder`), prepares
/// every stored map (from `<id>.emb` when valid, else computed and stored), then marks the server
/// ready. Runs on the blocking pool while the listener already answers /health.
pub fn warm_up(state: &AppState) -> Result<()> {
    state.maps.warm_up_encoder()?;
    for entry in state.maps.store.list() {
        match state.maps.prepared_for(&entry) {
            Ok(_) => tracing::info!("map {:?} ready ({} points)", entry.id, entry.num_points),
            Err(e) => tracing::warn!("map {:?} could not be prepared: {e}", entry.id),
        }
    }
    state.maps.flush_writes(); // ready: nothing computed at start-up is left unstored
    state.lifecycle.set_ready();
    Ok(())
}

/// The probe port's connection limit and header/idle timeout (stated in `--probe-port`'s help).
pub const PROBE_MAX_CONNECTIONS: usize = 32;
pub const PROBE_HEADER_TIMEOUT: Duration = Duration::from_secs(2);

/// The probe port's routes: liveness, readiness and metrics, the same handlers as the main port's.
pub fn probe_router(state: Arc<AppState>) -> Router {
    Router::new()
        .route("/health", get(routes::health))
        .route("/ready", get(routes::ready))
        .route("/metrics", get(routes::metrics))
        .fallback(routes::not_found)
        .layer(axum::middleware::from_fn_with_state(state.lifecycle.clone(), close_when_draining))
        .with_state(state)
}

/// Serves on `listener` (and the probe routes on `probe`, when given: [`probe_router`], with
/// its own [`PROBE_MAX_CONNECTIONS`] connections, so probes never wait behind the main port's
/// `max_connections`) until `shutdown` resolves, then drains in three phases:
/// 1. draining: both listeners still answer (`/ready` 503, new localizations 503 `draining`)
///    while in-flight localizations finish, at most `shutdown_grace_s`;
/// 2. the listeners close; open connections finish their current request (kept-alive idle ones
///    close) within what is left of the grace;
/// 3. the agent workers stop, and the queued `<id>.emb` writes finish.
///
/// Connections: at most `max_connections` at once on the main port (more wait in the backlog),
/// headers must arrive within `header_timeout_s`, and a kept-alive connection idle for that long
/// is closed.
pub async fn serve(
    state: Arc<AppState>,
    listener: tokio::net::TcpListener,
    probe: Option<tokio::net::TcpListener>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<()> {
    let addr: SocketAddr = listener.local_addr()?;
    tracing::info!("listening on http://{addr}");
    let warm_state = state.clone();
    tokio::task::spawn_blocking(move || {
        let t = std::time::Instant::now();
        match warm_up(&warm_state) {
            Ok(()) => tracing::info!("ready after {:.0} ms of warm-up", t.elapsed().as_secs_f64() * 1000.0),
            Err(e) => tracing::error!("warm-up failed, staying not ready: {e:#}"),
        }
    });
    let grace = Duration::from_secs(state.config.shutdown_grace_s);
    let lifecycle = state.lifecycle.clone();
    // Set to the end of the grace once draining is over: the listeners close then.
    let (drained_tx, drained_rx) = tokio::sync::watch::channel::<Option<tokio::time::Instant>>(None);
    tokio::spawn(async move {
        shutdown.await;
        let grace_ends = tokio::time::Instant::now() + grace;
        tracing::info!(in_flight = lifecycle.in_flight(), "shutting down: draining for at most {grace:?}");
        lifecycle.start_drain();
        if tokio::time::timeout_at(grace_ends, lifecycle.idle()).await.is_err() {
            tracing::warn!(in_flight = lifecycle.in_flight(), "grace period over with localizations still in flight");
        }
        let _ = drained_tx.send(Some(grace_ends));
    });

    let probes = match probe {
        Some(probe) => {
            tracing::info!("probes (/health, /ready, /metrics) on http://{}", probe.local_addr()?);
            let port = Port { app: probe_router(state.clone()), max_connections: PROBE_MAX_CONNECTIONS, header_timeout: PROBE_HEADER_TIMEOUT };
            Some(tokio::spawn(accept(port, probe, drained_rx.clone())))
        }
        None => None,
    };
    let main = Port {
        app: router(state.clone()),
        max_connections: state.config.max_connections,
        header_timeout: Duration::from_secs(state.config.header_timeout_s.max(1)),
    };
    accept(main, listener, drained_rx).await;
    if let Some(probes) = probes {
        let _ = probes.await;
    }
    let scheduler = state.scheduler.clone();
    let finished = tokio::task::spawn_blocking(move || scheduler.shutdown(Duration::from_secs(2))).await.unwrap_or(false);
    if !finished {
        tracing::warn!("agent workers did not stop in time");
    }
    let maps = state.maps.clone();
    let _ = tokio::task::spawn_blocking(move || maps.finish_writes()).await;
    Ok(())
}

/// One listening port's service and connection rules.
struct Port {
    app: Router,
    /// Open connections at most; more wait in the listen backlog.
    max_connections: usize,
    /// Headers must arrive within this, and a kept-alive connection idle this long is closed.
    header_timeout: Duration,
}

/// The accept loop of one port: serves connections until `stop` holds the grace's end, then
/// closes the listener and lets open connections finish until the grace ends.
async fn accept(port: Port, listener: tokio::net::TcpListener, mut stop: tokio::sync::watch::Receiver<Option<tokio::time::Instant>>) {
    use hyper_util::rt::{TokioIo, TokioTimer};
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(TokioTimer::new()).header_read_timeout(port.header_timeout).keep_alive(true);
    let graceful = hyper_util::server::graceful::GracefulShutdown::new();
    let connections = Arc::new(tokio::sync::Semaphore::new(port.max_connections.max(1)));
    let stopped = async move {
        match stop.wait_for(Option::is_some).await {
            Ok(ends) => (*ends).expect("waited for Some"),
            Err(_) => tokio::time::Instant::now(), // the sender is gone: stop now
        }
    };
    tokio::pin!(stopped);
    let grace_ends = loop {
        let permit = tokio::select! {
            permit = connections.clone().acquire_owned() => permit.expect("never closed"),
            ends = &mut stopped => break ends,
        };
        let stream = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => stream,
                Err(e) => {
                    // Out of descriptors or a connection reset before accept: back off briefly.
                    tracing::warn!("accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            ends = &mut stopped => break ends,
        };
        let _ = stream.set_nodelay(true);
        let service = hyper_util::service::TowerToHyperService::new(port.app.clone());
        let connection = graceful.watch(http.serve_connection(TokioIo::new(stream), service));
        tokio::spawn(async move {
            let _ = connection.await;
            drop(permit);
        });
    };
    drop(listener);
    if tokio::time::timeout_at(grace_ends, graceful.shutdown()).await.is_err() {
        tracing::warn!("grace period over; closing remaining connections");
    }
}

/// `cmr-agent serve`: binds, serves, stops on SIGINT/SIGTERM.
pub fn run_serve(config: ServeArgs) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    runtime.block_on(async move {
        let addr = format!("{}:{}", config.host, config.port);
        let probe_addr = config.probe_port.map(|p| format!("{}:{p}", config.host));
        let state = build_state(config)?;
        let listener = tokio::net::TcpListener::bind(&addr).await.with_context(|| format!("cannot listen on {addr}"))?;
        let probe = match probe_addr {
            Some(a) => Some(tokio::net::TcpListener::bind(&a).await.with_context(|| format!("cannot listen on {a} (--probe-port)"))?),
            None => None,
        };
        serve(state, listener, probe, shutdown_signal()).await
    })
}

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! { _ = ctrl_c => {}, _ = terminate => {} }
}
