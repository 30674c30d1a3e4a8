//! Every command sent to a fleet's `factord/rpc` runs exactly once, whatever the zenoh topology
//! between the instances and the caller (issue 52, item 1).
//!
//! zenoh routes a query to *every* matching queryable it does not rule out, and which ones it
//! rules out depends on the topology: a client connected to one peer of three reached two of
//! them, so a creation answered twice (a 409 and a success) and a batch was applied twice. The
//! fleet therefore serves `factord/rpc` from one instance at a time (its gateway); these tests
//! build each topology a user can build, with real processes, and count the replies and what
//! the session holds afterwards:
//! - peers in a mesh, the caller a peer;
//! - the guide's star (docs/guide/fleets.md; the first instance listens, the others connect to
//!   it), the caller a zenoh client (eclipse-zenoh's default mode) of the hub, and one of a
//!   spoke;
//! - every instance and the caller connected to a zenoh router (a session in `router` mode in
//!   this test process, as `zenohd` runs it), the caller a client and a peer;
//! - mixed: two instances on the router, the third a peer of the first, callers on both sides.

use crate::common;

use std::time::{Duration, Instant};

use common::fleet::{gateways, zenoh_replies, Fleet, Wiring};
use common::server::{free_port, zenoh_session};
use serde_json::{json, Value};

/// `payload` on `factord/rpc`: exactly one reply, a success; returns it. Until the fleet's
/// gateway is known to the caller's zenoh, a query may find no queryable at all (no reply):
/// that is retried, since nothing ran.
async fn once(z: &zenoh::Session, what: &str, payload: &Value) -> Value {
    let mut tries = 0;
    loop {
        let got = zenoh_replies(z, "factord/rpc", payload).await;
        match got.as_slice() {
            [] if tries < 50 => {
                tries += 1;
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            [Ok(v)] => return v.clone(),
            other => panic!("{what}: expected one successful reply, got {other:?}"),
        }
    }
}

/// `payload` on `factord/rpc`: exactly one reply, an error with `code`.
async fn refused_once(z: &zenoh::Session, what: &str, payload: &Value, code: &str) {
    let got = zenoh_replies(z, "factord/rpc", payload).await;
    match got.as_slice() {
        [Err(e)] => assert_eq!(e["error"]["code"], code, "{what}: {e}"),
        other => panic!("{what}: expected one refusal `{code}`, got {other:?}"),
    }
}

fn pose(key: u64, x: f64, fixed: bool) -> Value {
    json!({"key": key, "kind": "se2", "value": [x, 0, 0], "fixed": fixed})
}

fn odometry(from: u64) -> Value {
    json!({"type": "between_se2", "keys": [from, from + 1], "measurement": [1, 0, 0],
           "sigmas": [0.1, 0.1, 0.05]})
}

/// The commands that carry no producer numbering, each sent once through `z`: every one must
/// run once, and the session must hold exactly what was sent once.
async fn every_command_runs_once(z: &zenoh::Session, tag: &str) {
    let unnamed = once(
        z,
        "unnamed create",
        &json!({"op": "create_session", "kind": "pose_graph_2d"}),
    )
    .await;
    let generated = unnamed["session"].as_str().expect("a generated name");
    once(
        z,
        "delete of the unnamed",
        &json!({"op": "delete_session", "session": generated}),
    )
    .await;

    let name = format!("once-{tag}");
    let create = json!({"op": "create_session", "session": name, "kind": "pose_graph_2d",
                        "auto_optimize": {"policy": "manual"}});
    once(z, "named create", &create).await;
    refused_once(z, "second named create", &create, "session_exists").await;

    let first = json!({"op": "apply_batch", "session": name, "batch": {
        "variables": [pose(0, 0.0, true), pose(1, 1.0, false)], "factors": [odometry(0)]}});
    let ack = once(z, "first plain batch", &first).await;
    assert_eq!(ack["sequence"], 1, "{ack}");
    let second = json!({"op": "apply_batch", "session": name, "batch": {
        "variables": [pose(2, 2.0, false)], "factors": [odometry(1)]}});
    let ack = once(z, "second plain batch", &second).await;
    assert_eq!(ack["sequence"], 2, "{ack}");

    let types = json!({"op": "define_factor_types", "session": name,
                       "factor_types": [common::user_between_se2()]});
    once(z, "define factor types", &types).await;
    once(
        z,
        "optimize",
        &json!({"op": "optimize", "session": name, "wait": true}),
    )
    .await;
    let stats = once(z, "stats", &json!({"op": "get_stats", "session": name})).await;
    assert_eq!(stats["sequence"], 2, "{stats}");
    assert_eq!(stats["num_factors"], 2, "{stats}");
    assert_eq!(stats["num_variables"], 3, "{stats}");
    assert_eq!(
        stats["solves"], 1,
        "one optimize, no automatic solve: {stats}"
    );

    once(
        z,
        "delete",
        &json!({"op": "delete_session", "session": name}),
    )
    .await;
    refused_once(
        z,
        "stats after delete",
        &json!({"op": "get_stats", "session": name}),
        "unknown_session",
    )
    .await;
}

/// Waits until `fleet` has settled as seen through `z`, runs every command through each caller,
/// and checks that no instance panicked.
async fn check(fleet: &Fleet, callers: &[(&str, zenoh::Session)]) {
    fleet.wait_settled(&callers[0].1).await;
    for (tag, z) in callers {
        every_command_runs_once(z, tag).await;
    }
    for i in fleet.running() {
        assert!(
            !fleet.instance(i).stderr().contains("panicked"),
            "{}",
            fleet.logs()
        );
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn peers_in_a_mesh_and_a_peer_caller() {
    let fleet = Fleet::start(3, &[]);
    let peer = zenoh_session("peer", "connect", &fleet.instance(0).zenoh).await;
    check(&fleet, &[("mesh-peer", peer)]).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn the_readme_star_and_client_callers() {
    let fleet = Fleet::start_wired(3, &[], Wiring::Star);
    let hub = zenoh_session("client", "connect", &fleet.instance(0).zenoh).await;
    let spoke = zenoh_session("client", "connect", &fleet.instance(1).zenoh).await;
    let peer = zenoh_session("peer", "connect", &fleet.instance(2).zenoh).await;
    check(
        &fleet,
        &[
            ("star-hub", hub),
            ("star-spoke", spoke),
            ("star-peer", peer),
        ],
    )
    .await;
}

#[tokio::test(flavor = "multi_thread")]
async fn everyone_through_a_router() {
    let router = format!("tcp/127.0.0.1:{}", free_port());
    let _router = zenoh_session("router", "listen", &router).await;
    let fleet = Fleet::start_wired(3, &[], Wiring::Explicit(vec![vec![router.clone()]; 3]));
    let client = zenoh_session("client", "connect", &router).await;
    let peer = zenoh_session("peer", "connect", &router).await;
    check(&fleet, &[("router-client", client), ("router-peer", peer)]).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn mixed_routers_and_peers() {
    let router = format!("tcp/127.0.0.1:{}", free_port());
    let _router = zenoh_session("router", "listen", &router).await;
    let zenoh = Fleet::zenoh_endpoints(3);
    let wiring = Wiring::Explicit(vec![
        vec![router.clone()],
        vec![router.clone()],
        vec![zenoh[0].clone()],
    ]);
    let fleet = Fleet::start_on(zenoh, &[], wiring);
    let client = zenoh_session("client", "connect", &fleet.instance(2).zenoh).await;
    let peer = zenoh_session("peer", "connect", &router).await;
    check(&fleet, &[("mixed-client", client), ("mixed-peer", peer)]).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_gateway_killed_with_sigkill_is_replaced_and_commands_still_run_once() {
    let mut fleet = Fleet::start(3, &[]);
    let z = zenoh_session("client", "connect", &fleet.instance(1).zenoh).await;
    fleet.wait_settled(&z).await;
    // The smallest id serves: f1.
    let deadline = Instant::now() + Duration::from_secs(10);
    while gateways(&z).await != ["f1"] {
        assert!(Instant::now() < deadline, "f1 never became the gateway");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let killed = Instant::now();
    fleet.kill(0);
    // Until a successor serves, a command finds no queryable (no reply, nothing run); never two.
    loop {
        let got = zenoh_replies(&z, "factord/rpc", &json!({"op": "health"})).await;
        match got.len() {
            0 => assert!(
                killed.elapsed() < Duration::from_secs(10),
                "no gateway 10 s after the kill: {}",
                fleet.logs()
            ),
            1 => break,
            n => panic!("{n} replies to one health query: {got:?}"),
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    eprintln!(
        "rpc served again {:?} after the gateway's kill -9 was sent",
        killed.elapsed()
    );
    assert_eq!(gateways(&z).await, ["f2"]);
    every_command_runs_once(&z, "after-kill").await;
}
