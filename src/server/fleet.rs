//! `factord serve --fleet`: what an instance needs to join a fleet, checked before anything
//! starts: zenoh (membership and routing) and the journal (the shared state directory), an
//! instance id, and the URL the other instances reach its HTTP at.

use std::net::SocketAddr;

use super::{FleetConfig, ServeConfig, ServeError};
use crate::service::fleet::valid_instance_id;
use crate::service::fleet_key::FleetKey;

/// This instance's id when the fleet is on (`None` when off); refuses a fleet without zenoh
/// or without the journal.
pub(super) fn instance_id(config: &ServeConfig) -> Result<Option<String>, ServeError> {
    if !config.fleet.enabled {
        return Ok(None);
    }
    if !config.zenoh_enabled {
        return Err(ServeError::Fleet(
            "needs zenoh (instances find each other and route sessions over it): remove \
             --no-zenoh"
                .into(),
        ));
    }
    if !config.journal.enabled {
        return Err(ServeError::Fleet(
            "needs the journal (sessions move between instances through the shared state \
             directory): remove --no-journal"
                .into(),
        ));
    }
    let lease = crate::service::fleet::LEASE_MS_RANGE;
    if !lease.contains(&config.fleet.lease_ms) {
        return Err(ServeError::Fleet(format!(
            "fleet.lease_ms is {}; it must be {}-{} (ms)",
            config.fleet.lease_ms,
            lease.start(),
            lease.end()
        )));
    }
    let id = match &config.fleet.instance {
        Some(id) if valid_instance_id(id) => id.clone(),
        Some(id) => {
            return Err(ServeError::Fleet(format!(
                "instance id `{id}` is not 1-64 characters of [A-Za-z0-9._-]"
            )))
        }
        None => default_instance_id(),
    };
    Ok(Some(id))
}

/// The fleet's secret from `secret_file`; without one, a fleet starts only when told its
/// network is trusted, and says so.
pub(super) fn fleet_key(fleet: &FleetConfig) -> Result<Option<FleetKey>, ServeError> {
    match (&fleet.secret_file, fleet.trusted_network) {
        (Some(path), _) => FleetKey::from_file(path)
            .map(Some)
            .map_err(|e| ServeError::Fleet(e.to_string())),
        (None, true) => {
            tracing::warn!(
                "fleet: no secret (--fleet-trusted-network): every zenoh peer that declares                  `<p>/@fleet/<id>` is taken for an instance, receives sessions and the                  requests forwarded to them with their bearer tokens; run it so only on a                  network nobody else can reach"
            );
            Ok(None)
        }
        (None, false) => Err(ServeError::Fleet(
            "needs a shared secret to tell its instances from any other zenoh peer: give              every instance --fleet-secret-file (the same file of at least 32 bytes), or              --fleet-trusted-network on a network nobody else can reach"
                .into(),
        )),
    }
}

/// `<hostname>-<pid>`, the host name cut to what an id may hold.
fn default_instance_id() -> String {
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_else(|| "factord".into());
    let host: String = host
        .trim()
        .chars()
        .map(|c| match c {
            'A'..='Z' | 'a'..='z' | '0'..='9' | '.' | '_' | '-' => c,
            _ => '-',
        })
        .take(48)
        .collect();
    let host = if host.is_empty() {
        "factord".into()
    } else {
        host
    };
    format!("{host}-{}", std::process::id())
}

/// The URL the other instances reach this one's HTTP at: configured, or `http://` + the bound
/// address, which must then be one they can reach (not 0.0.0.0 or ::).
pub(super) fn advertised_http(
    fleet: &FleetConfig,
    bound: &SocketAddr,
) -> Result<String, ServeError> {
    if let Some(url) = &fleet.advertise_http {
        let rest = url.strip_prefix("http://").ok_or_else(|| {
            ServeError::Fleet(format!("advertise_http `{url}`: expected http://host:port"))
        })?;
        let rest = rest.trim_end_matches('/');
        if rest.is_empty() || rest.contains('/') {
            return Err(ServeError::Fleet(format!(
                "advertise_http `{url}`: expected http://host:port, without a path"
            )));
        }
        return Ok(url.trim_end_matches('/').to_string());
    }
    if bound.ip().is_unspecified() {
        return Err(ServeError::Fleet(format!(
            "HTTP listens on {bound}, which other instances cannot connect to: give \
             --advertise-http http://<this host's name or address>:{}",
            bound.port()
        )));
    }
    Ok(format!("http://{bound}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fleet_lease_is_bounded() {
        let mut config = ServeConfig::default();
        config.fleet.enabled = true;
        config.fleet.instance = Some("a".into());
        assert_eq!(
            config.fleet.lease_ms,
            crate::service::fleet::DEFAULT_LEASE_MS
        );
        assert!(instance_id(&config).is_ok());
        for bad in [0, 499, 60_001] {
            config.fleet.lease_ms = bad;
            let refused = instance_id(&config).unwrap_err().to_string();
            assert!(refused.contains("fleet.lease_ms"), "{refused}");
        }
        config.fleet.lease_ms = 500;
        assert!(instance_id(&config).is_ok());
    }

    #[test]
    fn a_fleet_needs_zenoh_the_journal_and_a_valid_id() {
        let mut config = ServeConfig::default();
        assert_eq!(instance_id(&config).unwrap(), None);
        config.fleet.enabled = true;
        let id = instance_id(&config).unwrap().unwrap();
        assert!(valid_instance_id(&id), "{id}");
        config.fleet.instance = Some("has space".into());
        assert!(instance_id(&config).is_err());
        config.fleet.instance = Some("a-1.b_2".into());
        assert_eq!(instance_id(&config).unwrap().as_deref(), Some("a-1.b_2"));
        config.zenoh_enabled = false;
        assert!(instance_id(&config)
            .unwrap_err()
            .to_string()
            .contains("zenoh"));
        config.zenoh_enabled = true;
        config.journal.enabled = false;
        assert!(instance_id(&config)
            .unwrap_err()
            .to_string()
            .contains("journal"));
    }

    #[test]
    fn the_advertised_url_is_required_beyond_a_concrete_address() {
        let fleet = FleetConfig::default();
        let any: SocketAddr = "0.0.0.0:8080".parse().unwrap();
        let lo: SocketAddr = "127.0.0.1:8080".parse().unwrap();
        assert!(advertised_http(&fleet, &any)
            .unwrap_err()
            .to_string()
            .contains("--advertise-http"));
        assert_eq!(
            advertised_http(&fleet, &lo).unwrap(),
            "http://127.0.0.1:8080"
        );
        let given = FleetConfig {
            advertise_http: Some("http://factord-1:8080/".into()),
            ..FleetConfig::default()
        };
        assert_eq!(
            advertised_http(&given, &any).unwrap(),
            "http://factord-1:8080"
        );
        let bad = FleetConfig {
            advertise_http: Some("factord-1:8080".into()),
            ..FleetConfig::default()
        };
        assert!(advertised_http(&bad, &any).is_err());
    }
}
