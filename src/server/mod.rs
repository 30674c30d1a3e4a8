//! `factord serve`: configuration (file < environment < flags), the state directory, starting
//! HTTP and zenoh over one [`Service`], and graceful shutdown.
//!
//! Layer 12, the composition root: may import everything.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

mod config;
mod error;
mod fleet;
mod sessions;
mod signal;
mod state_dir;
mod tokens;

pub use config::{AuthConfig, FleetConfig, ServeConfig};
pub use error::ServeError;
pub use signal::shutdown_signal;
pub use state_dir::ServerInfo;

use crate::service::Service;
use crate::transport::http::listener as http_listener;
use crate::transport::{http, zenoh};
use state_dir::StateDir;
use tokens::tokens_for;

/// Runs until `shutdown` resolves, then stops accepting, stops running solves after their
/// current iteration, closes zenoh and releases the state directory.
pub async fn run(
    config: ServeConfig,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), ServeError> {
    let instance = fleet::instance_id(&config)?;
    let key = match instance {
        Some(_) => fleet::fleet_key(&config.fleet)?,
        None => None,
    };
    let state = StateDir::open(&config.state_dir, instance.is_some())?;
    // Every connection is a file: use all the process may have, and cap connections below it.
    let file_limit = http_listener::raise_file_limit();
    let connection_cap = http_listener::connection_cap(&config.http, file_limit);
    let listener = http_listener::bind(&config.listen)
        .await
        .map_err(|source| ServeError::Listen {
            addr: config.listen.clone(),
            source,
        })?;
    let http_addr: SocketAddr = listener.local_addr().map_err(ServeError::Http)?;
    let service = start_service(&config, instance.as_deref(), key, &http_addr).await?;
    let tokens = tokens_for(&config.auth, &http_addr)?;
    let zenoh = match config.zenoh_enabled {
        true => {
            let policy = zenoh::ZenohPolicy {
                tokens_required: tokens.is_some(),
                max_payload_bytes: config.max_body_bytes,
            };
            Some(zenoh::start(Arc::clone(&service), &config.zenoh, policy).await?)
        }
        false => None,
    };
    let info_path = state.write_info(&config, &http_addr, instance.as_deref())?;
    tracing::info!(
        "factord {} serving HTTP on http://{http_addr} ({} workers, at most {connection_cap} \
         connections + {} for health and metrics; open-file limit {})",
        env!("CARGO_PKG_VERSION"),
        service.limits().workers,
        http_listener::RESERVE_CONNECTIONS,
        file_limit.map_or("unknown".into(), |l| l.to_string()),
    );
    let http = Http {
        listener,
        addr: http_addr,
        connection_cap,
        tokens,
    };
    let result = serve_until_stopped(&service, &config, http, shutdown).await;
    if let Some(z) = zenoh {
        z.close().await;
    }
    let _ = std::fs::remove_file(&info_path);
    drop(state);
    tracing::info!("stopped");
    result.map_err(ServeError::Http)
}

/// The service over the state directory: the config's factor types, the fleet joined, the
/// sessions on disk recovering, and the config's sessions there.
async fn start_service(
    config: &ServeConfig,
    instance: Option<&str>,
    mut key: Option<crate::service::fleet_key::FleetKey>,
    http_addr: &SocketAddr,
) -> Result<Arc<Service>, ServeError> {
    let service = Service::with_journal(
        config.limits.clone(),
        Some((config.state_dir.clone(), config.journal.clone())),
    );
    service
        .set_server_factor_types(&config.factor_types)
        .map_err(|e| ServeError::Config {
            file: "(factor_types)".into(),
            message: e,
        })?;
    if let Some(instance) = instance {
        let http = fleet::advertised_http(&config.fleet, http_addr)?;
        let lease = Duration::from_millis(config.fleet.lease_ms);
        service.join_fleet(instance, &http, key.take(), lease);
        tracing::info!("fleet instance `{instance}`, reached at {http}");
    }
    let recovering = service
        .recover_sessions()
        .map_err(|e| ServeError::StateDir {
            dir: config.state_dir.clone(),
            message: e.to_string(),
        })?;
    if recovering > 0 {
        tracing::info!(
            "recovering {recovering} session(s) from {}",
            config.state_dir.display()
        );
    }
    // After recovery, so a configured session that is on disk is found, not created again;
    // before zenoh, which binds every session's ROS 2 topics when it starts.
    sessions::ensure(&service, &config.sessions)
        .await
        .map_err(|message| ServeError::Config {
            file: "(sessions)".into(),
            message,
        })?;
    Ok(service)
}

/// The bound HTTP listener and what serving it needs.
struct Http {
    listener: tokio::net::TcpListener,
    addr: SocketAddr,
    connection_cap: usize,
    tokens: Option<Arc<http::auth::Tokens>>,
}

/// How long event streams still open after the service has stopped are kept before closing.
const STREAM_GRACE: Duration = Duration::from_millis(500);

/// Serves HTTP until `shutdown` resolves; then stops the service first (new commands get 503
/// shutting_down, running solves stop after their current iteration, queued work and jobs are
/// dropped, and waiting requests are woken with their answers) and only then lets HTTP drain,
/// because those requests are what it waits for.
async fn serve_until_stopped(
    service: &Arc<Service>,
    config: &ServeConfig,
    http: Http,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let tokens_required = http.tokens.is_some();
    let guard = http::guard::HttpGuard::new(&config.listen, &http.addr, &config.http);
    let app = http::router(
        Arc::clone(service),
        config.max_body_bytes,
        http.tokens,
        Arc::new(guard),
    );
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    tokio::spawn(async move {
        shutdown.await;
        let _ = stop_tx.send(true);
    });
    let timeout = Duration::from_millis(config.shutdown_timeout_ms);
    let (stopped_tx, mut stopped_rx) = tokio::sync::watch::channel(false);
    {
        let svc = Arc::clone(service);
        let mut stop = stop_rx.clone();
        tokio::spawn(async move {
            let _ = stop.wait_for(|s| *s).await;
            tracing::info!("shutting down: refusing new work, stopping solves");
            let _ = tokio::task::spawn_blocking(move || svc.shutdown(timeout)).await;
            let _ = stopped_tx.send(true);
        });
    }
    let mut http_stop = stop_rx.clone();
    let serve = http_listener::serve(
        http.listener,
        app,
        &config.http,
        http.connection_cap,
        tokens_required,
        async move {
            let _ = http_stop.wait_for(|s| *s).await;
        },
    );
    // Event streams (SSE, WebSocket) never end by themselves, and graceful shutdown would wait
    // for them forever: once the service has stopped, whatever is still open gets
    // `STREAM_GRACE` and is then closed.
    let streams_closed = async move {
        let _ = stopped_rx.wait_for(|s| *s).await;
        tokio::time::sleep(STREAM_GRACE).await;
    };
    let result = tokio::select! {
        () = serve => Ok(()),
        () = streams_closed => {
            tracing::info!("shutting down: closing open event streams");
            Ok(())
        }
    };
    // Idempotent: waits for the stop begun above, or stops the service if HTTP ended by itself.
    let svc = Arc::clone(service);
    let _ = tokio::task::spawn_blocking(move || svc.shutdown(timeout)).await;
    result
}
