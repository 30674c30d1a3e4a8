//! A fleet: several `factord serve` instances sharing one state directory form one service.
//! Each session has exactly one owner, the instance [`placement::owner`] names among the live
//! instances; only the owner loads it, holding its lock ([`SessionLock`]) so that no two
//! instances ever write one journal. The transports ask [`Service::route`] where a session's
//! commands go: here, to another instance, or nowhere yet (it is moving: 503 `session_moving`,
//! Retry-After 1). Who is live comes from the transport (zenoh liveliness) through
//! [`Fleet::member_up`] and [`Fleet::member_down`]; adopting and releasing sessions when that
//! changes is `fleet_moves.rs`.
//!
//! Names: an unnamed creation is named by the instance that receives it, before it is routed,
//! from one counter in `<state_dir>/fleet-names` taken under an OS lock, so `s<n>` never
//! collides across instances. Deletion tombstones cannot collide: only the lock holder of a
//! session renames its directory.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, RwLock};

use serde::Serialize;
use tokio::sync::{watch, Notify};

use super::fleet_heartbeat::Heartbeats;
use super::fleet_key::FleetKey;
pub use super::fleet_lock::LockError;
use super::fleet_lock::SessionLock;
use super::placement;
use super::{Caller, Service, ServiceError};
use crate::journal::{epoch, SessionDir};

/// Another live instance, as it announced itself.
#[derive(Clone, Debug, Default)]
pub struct Member {
    /// Where its HTTP is reached (its advertised URL), once known.
    pub http: Option<String>,
}

/// Where a session's commands go.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Route {
    /// Run them here: the session is loaded here, or it does not exist and this instance
    /// would own it (a creation; anything else answers 404).
    Local,
    /// To the owning instance.
    Remote {
        instance: String,
        http: Option<String>,
    },
    /// Nowhere right now: being released here or adopted by its owner.
    Moving,
}

/// What an instance tells the fleet about itself (zenoh: `<p>/@fleet/<instance>/info`).
#[derive(Clone, Debug, Serialize, serde::Deserialize)]
pub struct FleetInfo {
    pub instance: String,
    pub http: String,
    /// Whether this instance has learnt the membership (it places sessions only then).
    pub settled: bool,
    /// The live instances it knows, itself included, with the HTTP URL of each (once known).
    pub live: BTreeMap<String, Option<String>>,
    /// The sessions loaded here, as the asking caller may see them.
    pub sessions: Vec<serde_json::Value>,
    pub load: FleetLoad,
    /// Whether this instance serves the fleet's `<p>/rpc` now (one instance at a time does).
    #[serde(default)]
    pub rpc_gateway: bool,
}

#[derive(Clone, Debug, Serialize, serde::Deserialize)]
pub struct FleetLoad {
    pub sessions: usize,
    pub busy_workers: usize,
    pub queued: usize,
}

/// This instance's view of the fleet.
pub struct Fleet {
    instance: String,
    http: String,
    state_dir: PathBuf,
    /// The other live instances.
    members: RwLock<BTreeMap<String, Member>>,
    /// The membership was learnt (placement is meaningful); before, unknown sessions are moving.
    settled: AtomicBool,
    /// The lock of every session loaded here.
    pub(super) locks: Mutex<HashMap<String, SessionLock>>,
    /// Sessions being released here.
    pub(super) moving: Mutex<HashSet<String>>,
    /// Session directories whose adoption failed for good (unreadable): answered as absent.
    pub(super) broken: Mutex<HashSet<String>>,
    /// The names of the sessions loaded here (the transports declare their routes from it).
    loaded: watch::Sender<BTreeSet<String>>,
    /// Membership changed: rebalance now.
    pub(super) changed: Notify,
    /// This instance serves the fleet's `<p>/rpc` (set by the transport that serves it).
    rpc_gateway: AtomicBool,
    /// The fleet's secret; `None` on a trusted network.
    key: Option<Arc<FleetKey>>,
    /// How long a member may be silent before it counts as gone (zenoh's transport lease) and,
    /// when its heartbeat stopped as long, as stopped (see `fleet_heartbeat`).
    lease: std::time::Duration,
    heartbeats: Arc<Heartbeats>,
}

/// The default of [`Fleet::lease`]: a stopped host is noticed, and its sessions served by
/// another instance, within about twice this.
pub const DEFAULT_LEASE_MS: u64 = 2000;
/// The bounds of `--fleet-lease-ms`: below 500 ms a loaded machine's scheduling delays would
/// pass for stopped hosts; above 60 s a stopped host's sessions wait a minute.
pub const LEASE_MS_RANGE: std::ops::RangeInclusive<u64> = 500..=60_000;

/// Held while this instance serves the fleet's `<p>/rpc`: on the state directory the fleet
/// shares, the kernel lets one instance at a time hold it, so two instances that each believe
/// they were elected (their views of the membership differ for a moment) cannot both serve.
/// Dropping it releases it.
/// It also holds an ownership epoch of `<state_dir>/fleet-gateway/` (see `journal::epoch`):
/// a successor takes the gateway over from a stopped instance, whose OS lock stays held,
/// by claiming the next epoch, and the stopped one, should it resume, answers nothing once it
/// sees its epoch is over ([`GatewayFence::superseded`]).
#[derive(Debug)]
pub struct GatewayLock {
    /// `None` when taken over from a stopped instance that still holds the OS lock.
    _lock: Option<SessionLock>,
    fence: GatewayFence,
}

/// The gateway's ownership epoch, checked before every command it runs.
#[derive(Clone, Debug)]
pub struct GatewayFence {
    dir: PathBuf,
    epoch: u64,
}

impl GatewayFence {
    /// Another instance serves the fleet's rpc now: answer nothing more.
    pub fn superseded(&self) -> bool {
        epoch::superseded(&self.dir, self.epoch)
    }
}

impl GatewayLock {
    pub fn fence(&self) -> GatewayFence {
        self.fence.clone()
    }
}

impl Drop for GatewayLock {
    /// Stepping down cleanly: the successor need not wait to see this instance stopped.
    fn drop(&mut self) {
        if !self.fence.superseded() {
            let _ = epoch::release(&self.fence.dir, self.fence.epoch);
        }
    }
}

/// An instance id: 1-64 characters of `[A-Za-z0-9._-]`.
pub fn valid_instance_id(id: &str) -> bool {
    (1..=64).contains(&id.len())
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

impl Fleet {
    pub fn instance(&self) -> &str {
        &self.instance
    }

    pub fn http(&self) -> &str {
        &self.http
    }

    /// The fleet's secret, with which members prove membership; `None` on a network
    /// declared trusted (`fleet.trusted_network`), where every announced peer is a member.
    pub fn key(&self) -> Option<&FleetKey> {
        self.key.as_deref()
    }

    /// Instance `id` is live (announced, or its URL learnt).
    pub fn member_up(&self, id: &str, member: Member) {
        if id == self.instance {
            return;
        }
        let mut members = self.members.write().unwrap_or_else(|p| p.into_inner());
        let known = members.insert(id.to_string(), member).is_some();
        drop(members);
        if !known {
            tracing::info!(instance = id, "fleet: instance joined");
            self.changed.notify_one();
        }
    }

    /// Instance `id` is gone (its liveliness token vanished).
    pub fn member_down(&self, id: &str) {
        let removed = self
            .members
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .remove(id)
            .is_some();
        if removed {
            tracing::info!(instance = id, "fleet: instance left");
            self.changed.notify_one();
        }
    }

    /// The membership is known: sessions may be placed, adopted and released from now on.
    pub fn set_settled(&self) {
        if !self.settled.swap(true, Ordering::SeqCst) {
            self.changed.notify_one();
        }
    }

    pub fn settled(&self) -> bool {
        self.settled.load(Ordering::SeqCst)
    }

    /// Takes the rpc gateway's lock (`<state_dir>/fleet-gateway.lock`), without waiting, or
    /// takes the gateway over from a stopped instance that holds it; then claims the next
    /// ownership epoch of the gateway (see [`GatewayLock`]).
    pub fn gateway_lock(&self) -> Result<GatewayLock, LockError> {
        let dir = self.state_dir.join("fleet-gateway");
        std::fs::create_dir_all(&dir)?;
        let lock = match SessionLock::try_acquire_file(&self.state_dir.join("fleet-gateway.lock")) {
            Ok(lock) => Some(lock),
            Err(LockError::Held) if self.may_take_over(epoch::current(&dir)?, &dir) => {
                tracing::warn!("fleet: taking the rpc gateway over from a stopped instance");
                None
            }
            Err(e) => return Err(e),
        };
        let next = epoch::current(&dir)?.map_or(0, |(n, _)| n) + 1;
        if !epoch::claim(&dir, next, &self.instance)? {
            return Err(LockError::Held);
        }
        Ok(GatewayLock {
            _lock: lock,
            fence: GatewayFence { dir, epoch: next },
        })
    }

    /// Whether what `latest` (a directory's latest ownership claim, see `journal::epoch`)
    /// holds may be taken over although its OS lock is held: its holder handed it over
    /// cleanly, or is gone from the membership and has stopped (`fleet_heartbeat`).
    pub(super) fn may_take_over(&self, latest: Option<(u64, String)>, dir: &Path) -> bool {
        let Some((n, holder)) = latest else {
            return false; // a creation between its lock and its claim
        };
        epoch::released(dir, n)
            || (holder != self.instance
                && self.member(&holder).is_none()
                && self.heartbeats.stalled(&holder))
    }

    /// How long a silent member takes to count as gone (zenoh's transport lease).
    pub fn lease(&self) -> std::time::Duration {
        self.lease
    }

    /// Records whether this instance serves the fleet's `<p>/rpc` (shown in its info).
    pub fn set_rpc_gateway(&self, serving: bool) {
        self.rpc_gateway.store(serving, Ordering::SeqCst);
    }

    /// The live instances, this one included, sorted.
    pub fn live(&self) -> Vec<String> {
        let members = self.members.read().unwrap_or_else(|p| p.into_inner());
        let mut live: Vec<String> = members.keys().cloned().collect();
        live.push(self.instance.clone());
        live.sort();
        live
    }

    pub fn member(&self, id: &str) -> Option<Member> {
        self.members
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .get(id)
            .cloned()
    }

    /// The instance that owns session `name` now.
    pub fn owner_of(&self, name: &str) -> String {
        let live = self.live();
        placement::owner(name, live.iter().map(String::as_str))
            .unwrap_or(&self.instance)
            .to_string()
    }

    /// The sessions loaded here, as they change.
    pub fn loaded(&self) -> watch::Receiver<BTreeSet<String>> {
        self.loaded.subscribe()
    }

    pub(super) fn set_loaded(&self, name: &str, loaded: bool) {
        self.loaded.send_if_modified(|set| {
            if loaded {
                set.insert(name.to_string())
            } else {
                set.remove(name)
            }
        });
    }

    pub(super) fn is_moving(&self, name: &str) -> bool {
        self.moving
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .contains(name)
    }

    fn session_dir(&self, name: &str) -> PathBuf {
        SessionDir::sessions_root(&self.state_dir).join(name)
    }

    /// Takes the lock of new session `name`, whose directory this instance just created.
    pub(super) fn lock_created(&self, name: &str) -> Result<(), ServiceError> {
        match SessionLock::try_acquire(&self.session_dir(name)) {
            Ok(lock) => {
                self.locks
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .insert(name.to_string(), lock);
                Ok(())
            }
            // Another instance took it in the instant since its directory appeared: it
            // believes it owns the name (the membership is changing) and has loaded it.
            Err(LockError::Held | LockError::Gone) => Err(moving(name)),
            Err(LockError::Io(e)) => Err(ServiceError::unavailable(
                "journal_failed",
                format!("cannot lock the directory of session `{name}`: {e}"),
                5,
            )),
        }
    }

    /// Makes sure this instance holds the lock of session `name`, loaded here: one taken over
    /// from a stopped instance is locked once that instance lets go. Returns whether it is held.
    pub(super) fn lock_loaded(&self, name: &str) -> bool {
        let mut locks = self.locks.lock().unwrap_or_else(|p| p.into_inner());
        if locks.contains_key(name) {
            return true;
        }
        match SessionLock::try_acquire(&self.session_dir(name)) {
            Ok(lock) => {
                locks.insert(name.to_string(), lock);
                true
            }
            Err(_) => false,
        }
    }

    /// Drops the lock of session `name` (deleted or released here).
    pub(super) fn unlock(&self, name: &str) {
        self.locks
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .remove(name);
    }

    /// A name for an unnamed creation, unique across the fleet: `s<n>` from the shared counter
    /// in `<state_dir>/fleet-names` (taken under its OS lock), past every name on disk.
    pub fn generate_name(&self) -> Result<String, ServiceError> {
        let failed = |e: std::io::Error| {
            ServiceError::unavailable(
                "journal_failed",
                format!("cannot take a session name from the fleet's counter: {e}"),
                5,
            )
        };
        let path = self.state_dir.join("fleet-names");
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(failed)?;
        file.lock().map_err(failed)?;
        let mut text = String::new();
        file.read_to_string(&mut text).map_err(failed)?;
        let mut n: u64 = text.trim().parse().unwrap_or(1).max(1);
        while self.session_dir(&format!("s{n}")).exists() {
            n += 1;
        }
        file.set_len(0)
            .and_then(|()| file.rewind())
            .and_then(|()| file.write_all((n + 1).to_string().as_bytes()))
            .and_then(|()| file.sync_data())
            .map_err(failed)?;
        Ok(format!("s{n}"))
    }
}

pub use crate::session::moving;

impl Service {
    /// Makes this service instance `instance` of a fleet whose HTTP is reached at `http`.
    /// Needs the journal (the shared state directory); call before [`Self::recover_sessions`].
    /// `key`: the fleet's secret (`None`: a trusted network, every announced peer a member).
    /// `lease`: see [`Fleet::lease`].
    pub fn join_fleet(
        self: &Arc<Self>,
        instance: &str,
        http: &str,
        key: Option<FleetKey>,
        lease: std::time::Duration,
    ) -> Option<Arc<Fleet>> {
        let (state_dir, _) = self.journal.clone()?;
        let heartbeats = Heartbeats::start(&state_dir, instance, lease);
        let fleet = Arc::new(Fleet {
            instance: instance.to_string(),
            http: http.to_string(),
            state_dir,
            members: RwLock::new(BTreeMap::new()),
            settled: AtomicBool::new(false),
            locks: Mutex::new(HashMap::new()),
            moving: Mutex::new(HashSet::new()),
            broken: Mutex::new(HashSet::new()),
            loaded: watch::channel(BTreeSet::new()).0,
            changed: Notify::new(),
            rpc_gateway: AtomicBool::new(false),
            key: key.map(Arc::new),
            lease,
            heartbeats,
        });
        if self.fleet.set(Arc::clone(&fleet)).is_err() {
            return self.fleet.get().cloned();
        }
        let weak = Arc::downgrade(&fleet);
        self.observe_sessions(Box::new(move |session| {
            if let Some(fleet) = weak.upgrade() {
                fleet.set_loaded(&session.name, true);
            }
        }));
        self.start_rebalancing(Arc::clone(&fleet));
        Some(fleet)
    }

    pub fn fleet(&self) -> Option<&Arc<Fleet>> {
        self.fleet.get()
    }

    /// In a fleet, this instance's id: the owner of every session loaded here (what stats and
    /// the session list name, so a client sees where a session lives).
    pub fn owning_instance(&self) -> Option<String> {
        self.fleet().map(|f| f.instance().to_string())
    }

    /// Where the commands of session `name` go (always here outside a fleet).
    pub fn route(&self, name: &str) -> Route {
        let Some(fleet) = self.fleet() else {
            return Route::Local;
        };
        if fleet.is_moving(name) {
            return Route::Moving;
        }
        if self.session(name).is_ok() {
            return Route::Local;
        }
        if !fleet.settled() {
            return Route::Moving;
        }
        let owner = fleet.owner_of(name);
        if owner != fleet.instance {
            let http = fleet.member(&owner).and_then(|m| m.http);
            return Route::Remote {
                instance: owner,
                http,
            };
        }
        let broken = fleet
            .broken
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .contains(name);
        // Its directory is on disk but not loaded yet: being adopted here.
        if !broken && fleet.session_dir(name).join("session.json").exists() {
            return Route::Moving;
        }
        Route::Local
    }

    /// What this instance tells the fleet: its sessions as `caller` sees them, and its load.
    pub fn fleet_info(&self, caller: &Caller) -> Option<FleetInfo> {
        let fleet = self.fleet()?;
        let health = self.health(caller);
        let sessions: Vec<serde_json::Value> = self
            .sessions()
            .iter()
            .filter(|s| caller.may_see(s))
            .map(|s| serde_json::to_value(s.info()).expect("session info serialises"))
            .collect();
        let live = fleet
            .live()
            .into_iter()
            .map(|id| {
                let http = match id == fleet.instance {
                    true => Some(fleet.http.clone()),
                    false => fleet.member(&id).and_then(|m| m.http),
                };
                (id, http)
            })
            .collect();
        Some(FleetInfo {
            instance: fleet.instance.clone(),
            http: fleet.http.clone(),
            settled: fleet.settled(),
            live,
            load: FleetLoad {
                sessions: sessions.len(),
                busy_workers: health.busy_workers,
                queued: health.queued,
            },
            sessions,
            rpc_gateway: fleet.rpc_gateway.load(Ordering::SeqCst),
        })
    }
}

/// The session list of several instances' answers, merged (each session once) and sorted.
pub fn merge_session_lists(
    lists: impl IntoIterator<Item = Vec<serde_json::Value>>,
) -> Vec<serde_json::Value> {
    let mut all: BTreeMap<String, serde_json::Value> = BTreeMap::new();
    for list in lists {
        for info in list {
            if let Some(name) = info.get("session").and_then(|s| s.as_str()) {
                all.entry(name.to_string()).or_insert(info);
            }
        }
    }
    all.into_values().collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::api::wire::CreateSession;
    use crate::journal::JournalConfig;
    use crate::service::{Command, Limits, Recording};

    fn instance(dir: &std::path::Path, id: &str) -> (Arc<Service>, Arc<Fleet>) {
        let journal = Some((dir.to_path_buf(), JournalConfig::default()));
        let service = Service::with_journal(Limits::default(), journal);
        let fleet = service
            .join_fleet(
                id,
                &format!("http://{id}:8080"),
                None,
                std::time::Duration::from_millis(DEFAULT_LEASE_MS),
            )
            .unwrap();
        (service, fleet)
    }

    #[tokio::test(flavor = "multi_thread")]
    async fn two_instances_agree_on_owners_names_and_locks() {
        let dir = std::env::temp_dir().join(format!("factord-fleet-unit-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let (a, fa) = instance(&dir, "a");
        let (b, fb) = instance(&dir, "b");
        // Before the membership is known nothing is placed.
        assert_eq!(a.route("robot"), Route::Moving);
        fa.member_up(
            "b",
            Member {
                http: Some("http://b:8080".into()),
            },
        );
        fb.member_up(
            "a",
            Member {
                http: Some("http://a:8080".into()),
            },
        );
        fa.set_settled();
        fb.set_settled();
        let names: Vec<String> = (0..40).map(|i| format!("r{i}")).collect();
        for name in &names {
            let owner = placement::owner(name, ["a", "b"]).unwrap();
            let (here, there) = if owner == "a" { (&a, &b) } else { (&b, &a) };
            assert_eq!(here.route(name), Route::Local, "{name}");
            assert_eq!(
                there.route(name),
                Route::Remote {
                    instance: owner.into(),
                    http: Some(format!("http://{owner}:8080"))
                },
                "{name}"
            );
        }
        // The owner creates it and holds its lock; the other sees it exists, and does not load it.
        let name = names
            .iter()
            .find(|n| placement::owner(n, ["a", "b"]) == Some("a"))
            .unwrap();
        let request = CreateSession {
            session: Some(name.clone()),
            kind: "pose_graph_2d".into(),
            options: None,
            auto_optimize: Default::default(),
            ros2: None,
            factor_types: vec![],
            robots: None,
            outliers: Default::default(),
            max_update_ms: None,
        };
        a.execute(
            &Caller::Trusted,
            Command::CreateSession(request.clone()),
            Recording::History,
        )
        .await
        .unwrap();
        let session_dir = SessionDir::sessions_root(&dir).join(name);
        assert!(matches!(
            SessionLock::try_acquire(&session_dir),
            Err(LockError::Held)
        ));
        let refused = b
            .execute(
                &Caller::Trusted,
                Command::CreateSession(request),
                Recording::History,
            )
            .await
            .unwrap_err();
        assert_eq!(refused.body.code, "session_exists");
        assert!(fa.loaded().borrow().contains(name));
        // Generated names never collide, whichever instance draws them.
        let mut drawn = HashSet::new();
        for k in 0..20 {
            let fleet = if k % 2 == 0 { &fa } else { &fb };
            assert!(drawn.insert(fleet.generate_name().unwrap()));
        }
        // When a leaves, b owns everything; a session a still holds stays a's until released.
        fb.member_down("a");
        assert!(
            matches!(b.route(name), Route::Moving),
            "a holds its lock: b adopts it later"
        );
        drop((a, b));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
