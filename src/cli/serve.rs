//! `factord serve`: the service's flags and environment variables, laid over the config file.
//!
//! Settings come from defaults, then `--config`, then `FACTORD_*` environment variables, then
//! flags (clap resolves flag over environment; `overlay` puts both over the file).

use std::path::PathBuf;

use factord::journal::Fsync;
use factord::server::{self, ServeConfig};

use super::logging::{self, parse_log_filter, LogFilter, LogFormat};
use super::CliError;

/// Settings come from defaults, then `--config`, then `FACTORD_*` environment variables, then
/// flags.
#[derive(clap::Args)]
pub struct ServeArgs {
    /// JSON config file (the fields of `ServeConfig`, see docs/guide/operations.md).
    #[arg(long, env = "FACTORD_CONFIG")]
    config: Option<PathBuf>,
    /// HTTP address [default: 127.0.0.1:8080]
    #[arg(long, env = "FACTORD_LISTEN")]
    listen: Option<String>,
    /// State directory [default: ./factord-state]
    #[arg(long, env = "FACTORD_STATE_DIR")]
    state_dir: Option<PathBuf>,
    /// zenoh endpoints to listen on (repeatable) [default: tcp/127.0.0.1:7447]
    #[arg(long, env = "FACTORD_ZENOH_LISTEN", value_delimiter = ',')]
    zenoh_listen: Option<Vec<String>>,
    /// zenoh routers or peers to connect to (repeatable)
    #[arg(long, env = "FACTORD_ZENOH_CONNECT", value_delimiter = ',')]
    zenoh_connect: Option<Vec<String>>,
    /// Multicast scouting: on | off [default: off]
    #[arg(long, env = "FACTORD_ZENOH_MULTICAST", value_parser = parse_on_off)]
    zenoh_multicast: Option<bool>,
    /// A zenoh JSON5 configuration to start from (access control, TLS endpoints); the
    /// --zenoh-* settings apply on top of it.
    #[arg(long, env = "FACTORD_ZENOH_CONFIG")]
    zenoh_config: Option<PathBuf>,
    /// The token label every zenoh peer acts as (needs zenoh's own authentication in
    /// --zenoh-config: user/password, or mutual TLS); without it and with tokens on, zenoh
    /// peers reach only unowned sessions.
    #[arg(long, env = "FACTORD_ZENOH_PRINCIPAL")]
    zenoh_principal: Option<String>,
    /// Do not start the zenoh peer (HTTP only).
    #[arg(long, env = "FACTORD_NO_ZENOH")]
    no_zenoh: bool,
    /// When journal appends reach the disk: always (fsync before every acknowledgement) |
    /// interval (fsync in the background every journal.interval_ms) | never [default: always]
    #[arg(long, env = "FACTORD_FSYNC", value_parser = parse_fsync)]
    fsync: Option<Fsync>,
    /// Bearer tokens for HTTP, `label token` or `token` per line (FACTORD_TOKENS adds
    /// comma-separated ones); required automatically when --listen is beyond loopback.
    #[arg(long, env = "FACTORD_TOKENS_FILE")]
    tokens_file: Option<PathBuf>,
    /// Token labels (comma-separated) that may read GET /metrics, which shows every tenant's
    /// figures [default: the only label when there is one, else nobody]
    #[arg(long, env = "FACTORD_OPERATORS", value_delimiter = ',')]
    operators: Option<Vec<String>>,
    /// Keep sessions in memory only (no journal, nothing recovered at start).
    #[arg(long, env = "FACTORD_NO_JOURNAL")]
    no_journal: bool,
    /// Solver worker threads [default: number of cores]
    #[arg(long, env = "FACTORD_WORKERS")]
    workers: Option<usize>,
    /// Largest request body in bytes [default: 268435456]
    #[arg(long, env = "FACTORD_MAX_BODY_BYTES")]
    max_body_bytes: Option<usize>,
    /// Join a fleet: several instances on one shared state directory, joined by zenoh, form
    /// one service (needs zenoh and the journal; see docs/guide/fleets.md).
    /// [env FACTORD_FLEET: 1, true, on, yes; 0, false, off, no]
    #[arg(long, env = "FACTORD_FLEET", value_parser = clap::builder::FalseyValueParser::new())]
    fleet: bool,
    /// This instance's id in the fleet, unique, [A-Za-z0-9._-] [default: <hostname>-<pid>]
    #[arg(long, env = "FACTORD_INSTANCE_ID")]
    instance_id: Option<String>,
    /// The URL the other fleet instances reach this one's HTTP at, http://host:port
    /// [default: http://<listen address>; required when listening on 0.0.0.0]
    #[arg(long, env = "FACTORD_ADVERTISE_HTTP")]
    advertise_http: Option<String>,
    /// A file with the fleet's shared secret (at least 32 bytes, the same on every instance):
    /// members prove membership with it; a fleet refuses to start without one unless
    /// --fleet-trusted-network is given
    #[arg(long, env = "FACTORD_FLEET_SECRET_FILE")]
    fleet_secret_file: Option<PathBuf>,
    /// Run a fleet without a secret: any zenoh peer that announces itself joins it (only on a
    /// network nobody else can reach) [env FACTORD_FLEET_TRUSTED_NETWORK: 1, true, on, yes]
    #[arg(long, env = "FACTORD_FLEET_TRUSTED_NETWORK", value_parser = clap::builder::FalseyValueParser::new())]
    fleet_trusted_network: bool,
    /// How long a fleet member may be silent before the others count it gone (zenoh's link
    /// lease), and, when its heartbeat on the state directory stopped as long, take its
    /// sessions and the rpc gateway over, 500-60000 [default: 2000]
    #[arg(long, env = "FACTORD_FLEET_LEASE_MS", value_parser = clap::value_parser!(u64).range(500..=60_000))]
    fleet_lease_ms: Option<u64>,
    /// Log filter: a level (error | warn | info | debug | trace | off) or RUST_LOG-style
    /// directives, e.g. factord=debug,zenoh=warn
    #[arg(long, env = "FACTORD_LOG", default_value = "info", value_parser = parse_log_filter)]
    log: LogFilter,
    /// Log lines as text (coloured only on a terminal) or as one JSON object per line
    #[arg(long, env = "FACTORD_LOG_FORMAT", value_enum, default_value = "text")]
    log_format: LogFormat,
}

fn parse_on_off(s: &str) -> Result<bool, String> {
    match s {
        "on" | "true" | "1" => Ok(true),
        "off" | "false" | "0" => Ok(false),
        _ => Err(format!("expected on or off, got `{s}`")),
    }
}

fn parse_fsync(s: &str) -> Result<Fsync, String> {
    match s {
        "always" => Ok(Fsync::Always),
        "interval" => Ok(Fsync::Interval),
        "never" => Ok(Fsync::Never),
        _ => Err(format!("`{s}`: expected always, interval or never")),
    }
}

pub fn run(args: ServeArgs) -> Result<(), CliError> {
    logging::init(&args.log, args.log_format)?;
    let mut config = match &args.config {
        Some(path) => ServeConfig::from_file(path)?,
        None => ServeConfig::default(),
    };
    overlay(args, &mut config);
    // zenoh needs the multi-threaded runtime.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(CliError::Runtime)?;
    // The signal handlers are installed inside the runtime, before the server starts.
    Ok(runtime.block_on(async { server::run(config, server::shutdown_signal()).await })?)
}

/// Puts every flag (or its environment variable) that was given over the file's settings.
fn overlay(args: ServeArgs, config: &mut ServeConfig) {
    if let Some(v) = args.listen {
        config.listen = v;
    }
    if let Some(v) = args.state_dir {
        config.state_dir = v;
    }
    if let Some(v) = args.zenoh_listen {
        config.zenoh.listen = v;
    }
    if let Some(v) = args.zenoh_connect {
        config.zenoh.connect = v;
    }
    if let Some(v) = args.zenoh_multicast {
        config.zenoh.multicast = v;
    }
    if args.no_zenoh {
        config.zenoh_enabled = false;
    }
    if let Some(v) = args.zenoh_config {
        config.zenoh.config_file = Some(v);
    }
    if let Some(v) = args.zenoh_principal {
        config.zenoh.principal = Some(v);
    }
    if let Some(v) = args.workers {
        config.limits.workers = v.max(1);
    }
    if let Some(v) = args.max_body_bytes {
        config.max_body_bytes = v;
    }
    if let Some(v) = args.fsync {
        config.journal.fsync = v;
    }
    if args.no_journal {
        config.journal.enabled = false;
    }
    if let Some(v) = args.tokens_file {
        config.auth.tokens_file = Some(v);
    }
    if let Some(v) = args.operators {
        config.auth.operators = Some(v);
    }
    if args.fleet {
        config.fleet.enabled = true;
    }
    if let Some(v) = args.instance_id {
        config.fleet.instance = Some(v);
    }
    if let Some(v) = args.advertise_http {
        config.fleet.advertise_http = Some(v);
    }
    if let Some(v) = args.fleet_secret_file {
        config.fleet.secret_file = Some(v);
    }
    if args.fleet_trusted_network {
        config.fleet.trusted_network = true;
    }
    if let Some(v) = args.fleet_lease_ms {
        config.fleet.lease_ms = v;
    }
}
