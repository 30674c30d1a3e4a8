//! The robot side of the fusion experiment (a client, used by `factord fusion-eval --stream` and
//! the tests): streams [`FusionInputs`] to a running `factord serve` over
//! zenoh (`factord/<session>/in/fusion`), one keyframe's messages at a time once the previous
//! keyframe's state has come back on `factord/<session>/out/state`, and collects those states.

use std::time::{Duration, Instant};

use serde_json::{json, Value};

use super::experiment::{experiment_messages, Estimate, FusionInputs, PoseJson};

/// A zenoh peer connected to `endpoint` (no scouting).
async fn connect(endpoint: &str) -> Result<zenoh::Session, String> {
    let mut config = zenoh::Config::default();
    for (key, value) in [
        ("mode", "\"peer\"".to_string()),
        ("scouting/multicast/enabled", "false".into()),
        ("connect/endpoints", format!("[\"{endpoint}\"]")),
    ] {
        config
            .insert_json5(key, &value)
            .map_err(|e| format!("zenoh config {key}: {e}"))?;
    }
    zenoh::open(config)
        .await
        .map_err(|e| format!("zenoh: cannot open a session to {endpoint}: {e}"))
}

/// `factord/rpc` with `command`, retried while the server's queryable is not yet known.
async fn rpc(z: &zenoh::Session, command: &Value) -> Result<Value, String> {
    let payload = command.to_string();
    for _ in 0..50 {
        let replies = z
            .get("factord/rpc")
            .payload(payload.clone())
            .timeout(Duration::from_secs(5))
            .await
            .map_err(|e| format!("zenoh query: {e}"))?;
        if let Ok(reply) = replies.recv_async().await {
            return match reply.result() {
                Ok(sample) => serde_json::from_slice(&sample.payload().to_bytes())
                    .map_err(|e| format!("rpc reply: {e}")),
                Err(e) => Err(format!(
                    "rpc refused: {}",
                    String::from_utf8_lossy(&e.payload().to_bytes())
                )),
            };
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    Err("no factord answered on factord/rpc".into())
}

/// What becomes of the session once the inputs are streamed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AfterRun {
    /// Deleted: a measurement leaves nothing behind.
    Delete,
    /// Kept, to read its trajectory export or marginals afterwards.
    Keep,
}

/// Creates `session` (kind sliding_window), streams `inputs` and returns the published states,
/// one per keyframe, with the server's update time and the publication-to-state latency; the
/// session is deleted afterwards.
pub async fn run_over_zenoh(
    endpoint: &str,
    session: &str,
    inputs: &FusionInputs,
) -> Result<Vec<Estimate>, String> {
    stream_over_zenoh(endpoint, session, inputs, AfterRun::Delete).await
}

/// [`run_over_zenoh`], keeping the session when `after` says so.
pub async fn stream_over_zenoh(
    endpoint: &str,
    session: &str,
    inputs: &FusionInputs,
    after: AfterRun,
) -> Result<Vec<Estimate>, String> {
    let z = connect(endpoint).await?;
    rpc(
        &z,
        &json!({"op": "create_session", "session": session, "kind": "sliding_window"}),
    )
    .await?;
    let (tx, states) = std::sync::mpsc::channel::<(Instant, Value)>();
    let tx = std::sync::Mutex::new(tx);
    let subscriber = z
        .declare_subscriber(format!("factord/{session}/out/state"))
        .callback(move |sample| {
            if let Ok(v) = serde_json::from_slice(&sample.payload().to_bytes()) {
                let _ = tx
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .send((Instant::now(), v));
            }
        })
        .await
        .map_err(|e| format!("zenoh subscriber: {e}"))?;
    // The subscription must reach the server before the first state is published.
    rpc(&z, &json!({"op": "health"})).await?;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let topic = format!("factord/{session}/in/fusion");
    let (start, batches) = experiment_messages(inputs);
    let put = |messages: Value| {
        let (z, topic) = (z.clone(), topic.clone());
        async move {
            z.put(topic, json!({ "messages": messages }).to_string())
                .congestion_control(zenoh::qos::CongestionControl::Block)
                .await
                .map_err(|e| format!("zenoh put: {e}"))
        }
    };
    put(json!([start])).await?;
    let mut estimates = Vec::with_capacity(batches.len());
    for (batch, keyframe) in batches.into_iter().zip(&inputs.keyframes) {
        let sent = Instant::now();
        put(serde_json::to_value(batch).map_err(|e| e.to_string())?).await?;
        let (arrived, event) =
            tokio::task::block_in_place(|| states.recv_timeout(Duration::from_secs(10))).map_err(
                |_| {
                    format!(
                        "no state for keyframe {} within 10 s (see factord/{session}/out/errors)",
                        keyframe.key
                    )
                },
            )?;
        let state = &event["state"];
        let pose: PoseJson = serde_json::from_value(json!({
            "position": state["position"], "rotation_xyzw": state["rotation_xyzw"]
        }))
        .map_err(|e| format!("state event: {e}"))?;
        estimates.push(Estimate {
            key: keyframe.key,
            t: state["t"].as_f64().unwrap_or(keyframe.t),
            pose,
            update_seconds: event["update_seconds"].as_f64().unwrap_or(f64::NAN),
            iterations: event["iterations"].as_u64().unwrap_or(0) as usize,
            latency_seconds: Some(arrived.duration_since(sent).as_secs_f64()),
        });
    }
    drop(subscriber);
    if after == AfterRun::Delete {
        let _ = rpc(&z, &json!({"op": "delete_session", "session": session})).await;
    }
    let _ = z.close().await;
    Ok(estimates)
}
