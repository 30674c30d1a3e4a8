//! `factord serve`: configuration (file < environment < flags), the state directory, starting
//! HTTP and zenoh over one [`Service`], and graceful shutdown.
//!
//! Layer 12, the composition root: may import everything.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use serde::{Deserialize, Serialize};

mod fleet;
mod sessions;

use crate::service::{Limits, Service};
use crate::transport::http::listener::{self as http_listener, HttpConfig};
use crate::transport::zenoh::ZenohConfig;
use crate::transport::{http, zenoh};

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServeConfig {
    /// HTTP address.
    pub listen: String,
    pub state_dir: PathBuf,
    /// Largest accepted request body.
    pub max_body_bytes: usize,
    /// HTTP connections (cap, timeouts) and the names and origins it answers.
    pub http: HttpConfig,
    /// Run the zenoh peer.
    pub zenoh_enabled: bool,
    pub zenoh: ZenohConfig,
    pub limits: Limits,
    pub auth: AuthConfig,
    /// Durable sessions: the write-ahead journal and snapshots under `state_dir/sessions`.
    pub journal: crate::journal::JournalConfig,
    /// How long shutdown waits for running solves to stop.
    pub shutdown_timeout_ms: u64,
    /// Several instances joined by zenoh, sharing `state_dir`, forming one service.
    pub fleet: FleetConfig,
    /// User-defined factor types every new graph session gets (those whose variable kinds it
    /// holds), as if its creation request declared them first.
    pub factor_types: Vec<crate::factors::expression::FactorTypeDefinition>,
    /// Sessions created at start unless they exist (see `server::sessions`), each a creation
    /// request with a name: e.g. a robot's ROS 2 binding.
    pub sessions: Vec<crate::api::wire::CreateSession>,
}

/// `fleet` in the config file (see docs/guide/fleets.md).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FleetConfig {
    pub enabled: bool,
    /// This instance's id, 1-64 characters of `[A-Za-z0-9._-]`, unique in the fleet
    /// (default: `<hostname>-<pid>`).
    pub instance: Option<String>,
    /// The URL the other instances reach this one's HTTP at (`http://host:port`) [default:
    /// `http://` + the bound address; required when listening on 0.0.0.0 or ::].
    pub advertise_http: Option<String>,
    /// A file holding the fleet's shared secret (at least 32 bytes; the same file on every
    /// instance): members prove membership with it, and forwarded requests carry a signed
    /// assertion of the caller instead of the caller's token (`service::fleet_key`).
    pub secret_file: Option<PathBuf>,
    /// Start a fleet without a secret: every zenoh peer that announces itself is a member.
    /// Only for a network nobody else can reach; said at start.
    pub trusted_network: bool,
    /// How long a member may be silent before the others count it gone, and take over what
    /// it held once its heartbeat stopped as long (`service::fleet_heartbeat`), in ms.
    pub lease_ms: u64,
}

impl Default for FleetConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            instance: None,
            advertise_http: None,
            secret_file: None,
            trusted_network: false,
            lease_ms: crate::service::fleet::DEFAULT_LEASE_MS,
        }
    }
}

impl Default for ServeConfig {
    fn default() -> Self {
        Self {
            listen: "127.0.0.1:8080".into(),
            state_dir: PathBuf::from("factord-state"),
            max_body_bytes: 256 << 20,
            http: HttpConfig::default(),
            zenoh_enabled: true,
            zenoh: ZenohConfig {
                listen: vec!["tcp/127.0.0.1:7447".into()],
                connect: Vec::new(),
                multicast: false,
                prefix: "factord".into(),
                config_file: None,
                principal: None,
            },
            limits: Limits::default(),
            journal: crate::journal::JournalConfig::default(),
            auth: AuthConfig::default(),
            shutdown_timeout_ms: 10_000,
            fleet: FleetConfig::default(),
            factor_types: Vec::new(),
            sessions: Vec::new(),
        }
    }
}

/// Bearer tokens for HTTP (see `transport::http::auth`).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AuthConfig {
    /// `label token` or `token` per line; `FACTORD_TOKENS` (comma-separated) adds more.
    pub tokens_file: Option<PathBuf>,
    /// Require tokens: `true`, `false`, or absent for "when HTTP listens beyond loopback".
    /// `false` beyond loopback is refused: an open back-end on the network is never the intent.
    pub required: Option<bool>,
    /// Token labels that may read `GET /metrics` (every tenant's figures). Absent: the only
    /// label when there is one; with several labels, nobody (the server warns at start).
    pub operators: Option<Vec<String>>,
}

#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("authentication: {0}")]
    Auth(String),
    #[error("config file {file}: {message}")]
    Config { file: PathBuf, message: String },
    #[error("state directory {dir}: {message}")]
    StateDir { dir: PathBuf, message: String },
    #[error("cannot listen on {addr}: {source}")]
    Listen {
        addr: String,
        source: std::io::Error,
    },
    #[error(transparent)]
    Zenoh(#[from] zenoh::ZenohError),
    #[error("HTTP server: {0}")]
    Http(std::io::Error),
    #[error("fleet: {0}")]
    Fleet(String),
}

impl ServeConfig {
    pub fn from_file(path: &Path) -> Result<Self, ServeError> {
        let text = std::fs::read_to_string(path).map_err(|e| ServeError::Config {
            file: path.into(),
            message: e.to_string(),
        })?;
        crate::service::parse_json(text.as_bytes()).map_err(|e| ServeError::Config {
            file: path.into(),
            message: match e.body.field {
                Some(f) => format!("{f}: {}", e.body.message),
                None => e.body.message,
            },
        })
    }
}

/// What a running server tells the world, written to `<state_dir>/server.json`.
#[derive(Debug, Serialize, Deserialize)]
pub struct ServerInfo {
    pub pid: u32,
    pub http: String,
    pub zenoh_listen: Vec<String>,
    pub zenoh_prefix: String,
    /// The fleet instance id (in a fleet).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
}

/// An exclusive hold on the state directory: an OS lock (`flock`) on `factord.lock`, held by the
/// open file for the process's life and released by the kernel however the process ends, so a
/// `kill -9` leaves no stale lock and two servers starting at once cannot both get it. The file
/// holds the holder's pid, for the message the next one prints; it is never removed (a removal
/// would let a third server lock a new file while a second still waits on the old one).
///
/// The instances of a fleet share the directory: each holds a *shared* lock on the file (and
/// each session's own lock, see `service::fleet`), so a server outside the fleet cannot start on
/// it, nor a fleet instance on a directory a lone server holds.
struct StateDir {
    _lock: std::fs::File,
}

impl StateDir {
    fn open(dir: &Path, shared: bool) -> Result<Self, ServeError> {
        use std::io::{Seek, Write};
        let err = |message: String| ServeError::StateDir {
            dir: dir.into(),
            message,
        };
        std::fs::create_dir_all(dir).map_err(|e| err(e.to_string()))?;
        let path = dir.join("factord.lock");
        let mut lock = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| err(format!("{}: {e}", path.display())))?;
        if shared {
            return match lock.try_lock_shared() {
                Ok(()) => Ok(Self { _lock: lock }),
                Err(std::fs::TryLockError::WouldBlock) => Err(err(format!(
                    "in use by {}, a factord outside the fleet (it holds the lock on {})",
                    lock_holder(&lock).map_or("another process".into(), |p| format!("process {p}")),
                    path.display()
                ))),
                Err(std::fs::TryLockError::Error(e)) => {
                    Err(err(format!("cannot lock {}: {e}", path.display())))
                }
            };
        }
        match lock.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let holder = match lock_holder(&lock) {
                    Some(pid) => format!("process {pid}"),
                    None => "another process".to_string(),
                };
                return Err(err(format!(
                    "in use by {holder}, another factord serving it, or a fleet (it holds the \
                     lock on {})",
                    path.display()
                )));
            }
            Err(std::fs::TryLockError::Error(e)) => {
                return Err(err(format!("cannot lock {}: {e}", path.display())))
            }
        }
        let pid = std::process::id().to_string();
        lock.set_len(0)
            .and_then(|()| lock.rewind())
            .and_then(|()| lock.write_all(pid.as_bytes()))
            .map_err(|e| err(format!("{}: {e}", path.display())))?;
        Ok(Self { _lock: lock })
    }
}

/// The process holding the `flock` on `file`, as the kernel tells it in `/proc/locks`
/// (`1: FLOCK  ADVISORY  WRITE <pid> <major>:<minor>:<inode> 0 EOF`). The pid written into the
/// file cannot say it: the holder writes it only after taking the lock, so a second server
/// starting at that moment would read the previous holder's. `None` where there is no
/// `/proc/locks` or the holder is gone.
fn lock_holder(file: &std::fs::File) -> Option<u32> {
    use std::os::unix::fs::MetadataExt;
    let inode = file.metadata().ok()?.ino().to_string();
    let locks = std::fs::read_to_string("/proc/locks").ok()?;
    locks
        .lines()
        .filter(|line| line.contains("FLOCK") && !line.contains("->"))
        .find_map(|line| {
            let fields: Vec<&str> = line.split_whitespace().collect();
            let at = fields
                .iter()
                .position(|f| f.rsplit(':').next() == Some(inode.as_str()) && f.contains(':'))?;
            fields.get(at.checked_sub(1)?)?.parse().ok()
        })
}

/// How long event streams still open after the service has stopped are kept before closing.
const STREAM_GRACE: Duration = Duration::from_millis(500);

/// Runs until `shutdown` resolves, then stops accepting, stops running solves after their
/// current iteration, closes zenoh and releases the state directory.
pub async fn run(
    config: ServeConfig,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), ServeError> {
    let instance = fleet::instance_id(&config)?;
    let mut key = match instance {
        Some(_) => fleet::fleet_key(&config.fleet)?,
        None => None,
    };
    let state = StateDir::open(&config.state_dir, instance.is_some())?;
    // Every connection is a file: use all the process may have, and cap connections below it.
    let file_limit = http_listener::raise_file_limit();
    let connection_cap = http_listener::connection_cap(&config.http, file_limit);
    let listener = tokio::net::TcpListener::bind(&config.listen)
        .await
        .map_err(|source| ServeError::Listen {
            addr: config.listen.clone(),
            source,
        })?;
    let http_addr: SocketAddr = listener.local_addr().map_err(ServeError::Http)?;
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
    if let Some(instance) = &instance {
        let http = fleet::advertised_http(&config.fleet, &http_addr)?;
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
    let tokens = tokens_for(&config.auth, &http_addr)?;
    let zenoh = if config.zenoh_enabled {
        let policy = zenoh::ZenohPolicy {
            tokens_required: tokens.is_some(),
            max_payload_bytes: config.max_body_bytes,
        };
        Some(zenoh::start(Arc::clone(&service), &config.zenoh, policy).await?)
    } else {
        None
    };
    let info = ServerInfo {
        pid: std::process::id(),
        http: http_addr.to_string(),
        zenoh_listen: if config.zenoh_enabled {
            config.zenoh.listen.clone()
        } else {
            Vec::new()
        },
        zenoh_prefix: config.zenoh.prefix.clone(),
        instance: instance.clone(),
    };
    // Per instance in a fleet, which shares the directory.
    let info_path = config.state_dir.join(match &instance {
        Some(id) => format!("server-{id}.json"),
        None => "server.json".into(),
    });
    std::fs::write(
        &info_path,
        serde_json::to_string_pretty(&info).expect("serialisable"),
    )
    .map_err(|e| ServeError::StateDir {
        dir: config.state_dir.clone(),
        message: e.to_string(),
    })?;
    tracing::info!(
        "factord {} serving HTTP on http://{http_addr} ({} workers, at most {connection_cap} \
         connections + {} for health and metrics; open-file limit {})",
        env!("CARGO_PKG_VERSION"),
        service.limits().workers,
        http_listener::RESERVE_CONNECTIONS,
        file_limit.map_or("unknown".into(), |l| l.to_string()),
    );

    let tokens_required = tokens.is_some();
    let guard = http::guard::HttpGuard::new(&config.listen, &http_addr, &config.http);
    let app = http::router(
        Arc::clone(&service),
        config.max_body_bytes,
        tokens,
        Arc::new(guard),
    );
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    tokio::spawn(async move {
        shutdown.await;
        let _ = stop_tx.send(true);
    });
    // The service stops first: new commands get 503 shutting_down, running solves stop after
    // their current iteration, queued work and jobs are dropped, and waiting requests are woken
    // with their answers. Only then can HTTP drain, because those requests are what it waits for.
    let timeout = Duration::from_millis(config.shutdown_timeout_ms);
    let (stopped_tx, mut stopped_rx) = tokio::sync::watch::channel(false);
    {
        let svc = Arc::clone(&service);
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
        listener,
        app,
        &config.http,
        connection_cap,
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
    let result: std::io::Result<()> = tokio::select! {
        () = serve => Ok(()),
        () = streams_closed => {
            tracing::info!("shutting down: closing open event streams");
            Ok(())
        }
    };
    // Idempotent: waits for the stop begun above, or stops the service if HTTP ended by itself.
    let svc = Arc::clone(&service);
    let _ = tokio::task::spawn_blocking(move || svc.shutdown(timeout)).await;
    if let Some(z) = zenoh {
        z.close().await;
    }
    let _ = std::fs::remove_file(&info_path);
    drop(state);
    tracing::info!("stopped");
    result.map_err(ServeError::Http)
}

/// The tokens HTTP requires, if any: always beyond loopback, and wherever configured.
fn tokens_for(
    auth: &AuthConfig,
    addr: &SocketAddr,
) -> Result<Option<Arc<crate::transport::http::auth::Tokens>>, ServeError> {
    use crate::transport::http::auth::Tokens;
    let mut tokens = match &auth.tokens_file {
        Some(file) => Tokens::load(file).map_err(|e| ServeError::Auth(e.to_string()))?,
        None => Tokens::default(),
    };
    if let Ok(list) = std::env::var("FACTORD_TOKENS") {
        tokens
            .extend_from_list(&list)
            .map_err(|e| ServeError::Auth(e.to_string()))?;
    }
    let beyond_loopback = !addr.ip().is_loopback();
    match auth.required {
        Some(false) if beyond_loopback => Err(ServeError::Auth(format!(
            "HTTP listens on {addr}, beyond loopback: tokens cannot be switched off there"
        ))),
        Some(false) => Ok(None),
        required if (required == Some(true) || beyond_loopback) && tokens.is_empty() => {
            Err(ServeError::Auth(format!(
                "HTTP on {addr} requires bearer tokens: give --tokens-file or FACTORD_TOKENS"
            )))
        }
        _ if tokens.is_empty() => Ok(None),
        _ => {
            if let Some(operators) = &auth.operators {
                tokens
                    .set_operators(operators)
                    .map_err(|e| ServeError::Auth(e.to_string()))?;
            }
            if tokens.metrics_closed() {
                tracing::warn!(
                    "GET /metrics answers 403 to every token: several token labels are \
                     configured and auth.operators (--operators) names none of them"
                );
            }
            tracing::info!("HTTP requires bearer tokens ({} configured)", tokens.len());
            Ok(Some(Arc::new(tokens)))
        }
    }
}

/// Resolves on Ctrl-C or SIGTERM. The SIGTERM handler is installed when this is called (inside
/// the runtime), not when the future is first polled: a SIGTERM that arrives right after start-up
/// (say, once "serving HTTP" is logged) must stop the server gracefully, not kill it.
pub fn shutdown_signal() -> impl std::future::Future<Output = ()> + Send + 'static {
    #[cfg(unix)]
    let term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).ok();
    async move {
        let ctrl_c = async {
            let _ = tokio::signal::ctrl_c().await;
        };
        #[cfg(unix)]
        let term = async move {
            match term {
                Some(mut s) => {
                    s.recv().await;
                }
                None => std::future::pending::<()>().await,
            }
        };
        #[cfg(not(unix))]
        let term = std::future::pending::<()>();
        tokio::select! {
            _ = ctrl_c => {},
            _ = term => {},
        }
    }
}
