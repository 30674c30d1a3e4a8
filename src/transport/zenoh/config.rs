//! The zenoh peer's configuration: what `factord serve` takes, the zenoh `Config` built from it,
//! and who zenoh peers are (the [`Caller`] their commands run as).

use crate::service::Caller;

#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ZenohConfig {
    /// Endpoints to listen on, e.g. `tcp/0.0.0.0:7447`.
    pub listen: Vec<String>,
    /// Routers or peers to connect to.
    pub connect: Vec<String>,
    /// Multicast scouting for other peers on the LAN.
    pub multicast: bool,
    /// First chunk of every key expression.
    pub prefix: String,
    /// A zenoh JSON5 configuration to start from (access control, TLS, authentication: see
    /// `docker/zenoh-secure.json5`); the settings above are applied on top of it.
    pub config_file: Option<std::path::PathBuf>,
    /// The principal (a token label, as in the tokens file) that every zenoh peer acts as: it
    /// reaches the sessions that label owns, and owns the sessions it creates. Only with
    /// zenoh's own authentication in `config_file` (user/password, or mutual TLS on every
    /// endpoint): zenoh then decides who is a peer at all, and its ACL what each may do.
    /// Without it, and with HTTP tokens on, zenoh peers are anonymous: they reach only unowned
    /// sessions (see `service::caller`).
    pub principal: Option<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum ZenohError {
    #[error("zenoh configuration `{key}`: {message}")]
    Config { key: String, message: String },
    #[error("zenoh: {0}")]
    Zenoh(String),
}

pub(super) fn zenoh_error(e: impl std::fmt::Display) -> ZenohError {
    ZenohError::Zenoh(e.to_string())
}

pub(super) fn config(cfg: &ZenohConfig) -> Result<zenoh::Config, ZenohError> {
    let mut config = match &cfg.config_file {
        Some(path) => zenoh::Config::from_file(path).map_err(|e| ZenohError::Config {
            key: path.display().to_string(),
            message: e.to_string(),
        })?,
        None => zenoh::Config::default(),
    };
    let json = |v: &Vec<String>| serde_json::to_string(v).expect("strings serialise");
    for (key, value) in [
        ("mode", "\"peer\"".to_string()),
        ("scouting/multicast/enabled", cfg.multicast.to_string()),
        ("scouting/gossip/enabled", "true".to_string()),
        ("listen/endpoints", json(&cfg.listen)),
        ("connect/endpoints", json(&cfg.connect)),
    ] {
        config
            .insert_json5(key, &value)
            .map_err(|e| ZenohError::Config {
                key: key.into(),
                message: e.to_string(),
            })?;
    }
    Ok(config)
}

/// A fleet's members notice a member gone when its links' lease runs out: `lease` instead of
/// zenoh's 10 s, with zenoh's four keep-alives per lease (a stopped host is then noticed within
/// about `lease`, see `service::fleet`). On top of a `config_file`, as the settings above are.
pub(super) fn set_fleet_lease(
    config: &mut zenoh::Config,
    lease: std::time::Duration,
) -> Result<(), ZenohError> {
    let key = "transport/link/tx/lease";
    config
        .insert_json5(key, &lease.as_millis().to_string())
        .map_err(|e| ZenohError::Config {
            key: key.into(),
            message: e.to_string(),
        })
}

/// Whether zenoh authenticates every peer before it may send anything: user/password on every
/// link, or mutual TLS with only TLS endpoints (a plain `tcp/` endpoint beside it is open).
fn authenticated(config: &zenoh::Config, cfg: &ZenohConfig) -> bool {
    let set = |key: &str| {
        config
            .get_json(key)
            .is_ok_and(|v| v != "null" && v != "false" && v != "\"\"")
    };
    let usrpwd = set("transport/auth/usrpwd/dictionary_file");
    let mtls = set("transport/link/tls/enable_mtls")
        && !cfg.listen.is_empty()
        && cfg
            .listen
            .iter()
            .chain(&cfg.connect)
            .all(|e| e.starts_with("tls/"));
    usrpwd || mtls
}

/// Who zenoh peers are: see [`ZenohConfig::principal`]. With HTTP tokens on and zenoh open,
/// peers are anonymous, and the operator is told so.
pub(super) fn caller(
    config: &zenoh::Config,
    cfg: &ZenohConfig,
    tokens_required: bool,
) -> Result<Caller, ZenohError> {
    match (&cfg.principal, authenticated(config, cfg)) {
        (Some(label), true) => Ok(Caller::Principal(label.as_str().into())),
        (Some(_), false) => Err(ZenohError::Config {
            key: "zenoh.principal".into(),
            message: "needs zenoh's own authentication in zenoh.config_file \
                      (transport/auth/usrpwd/dictionary_file, or transport/link/tls/enable_mtls \
                      with only tls/ endpoints): otherwise any peer would act as that principal"
                .into(),
        }),
        (None, _) if tokens_required => {
            tracing::warn!(
                "HTTP requires bearer tokens but zenoh peers are anonymous: any zenoh peer can \
                 create, read, write and delete the sessions created over zenoh, and sessions \
                 created with a token are invisible over zenoh (404, not published). Secure \
                 zenoh (user/password or mutual TLS) and set zenoh.principal to reach them"
            );
            Ok(Caller::Anonymous)
        }
        (None, _) => Ok(Caller::Trusted),
    }
}
