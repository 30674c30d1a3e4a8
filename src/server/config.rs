//! What `factord serve` is told: the config file's structure (file < environment < flags, see
//! `cli::serve`), with the defaults that make `factord serve` work with no file at all.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::ServeError;
use crate::service::Limits;
use crate::transport::http::listener::HttpConfig;
use crate::transport::zenoh::ZenohConfig;

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
