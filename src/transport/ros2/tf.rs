//! The `map → odom` correction on `/tf`, as a ROS localisation node publishes it (AMCL,
//! slam_toolbox): the transform that takes the robot's odometry frame to the optimised map,
//! so that `map → odom → base_link` puts the robot where the optimiser says while odometry
//! keeps its own smooth frame.
//!
//! The correction is `T_map_odom = T_map_k · T_odom_k⁻¹` for the newest solved keyframe `k`:
//! its optimised pose times the inverse of the odometry pose that made it.
//!
//! Stamps. A transform is valid for lookups up to its stamp; consumers look up the robot at its
//! newest odometry time, so the correction is stamped with the newest odometry stamp plus
//! `transform_tolerance` (AMCL's name for the same future-dating) and re-published as odometry
//! arrives (at most every [`MIN_PERIOD_NS`] of odometry time) and after every solve. Stamps
//! strictly increase, as tf2 drops a transform whose stamp it already holds.

use std::collections::BTreeMap;

use nalgebra::Isometry3;
use tokio::sync::Mutex;

use super::cdr_codec;
use super::messages::{Header, TfMessage, Time, Transform, TransformStamped};
use super::outputs::{se3_estimate, RosPublisher};
use crate::api::wire::VariableValue;
use crate::variables::Key;

/// At most one odometry-driven publication per 20 ms of odometry time (slam_toolbox's default
/// `transform_publish_period`); solves publish regardless.
const MIN_PERIOD_NS: i64 = 20_000_000;

/// Keyframes' odometry poses kept for solves that lag the keyframer (a solve corrects by the
/// newest keyframe it holds, then the older ones are dropped).
const MAX_PENDING_KEYFRAMES: usize = 1024;

/// The frame odometry is published in when its header leaves `frame_id` empty (REP 105).
const DEFAULT_ODOM_FRAME: &str = "odom";

pub(super) struct TfBroadcaster {
    map_frame: String,
    tolerance_ns: i64,
    /// A robot's node names its child frame (`robot_odom_frame`) whatever odometry says.
    odom_frame_fixed: bool,
    state: Mutex<State>,
}

struct State {
    publisher: RosPublisher,
    /// Odometry poses of the keyframes a solve has not yet covered, by key.
    keyframes: BTreeMap<Key, Isometry3<f64>>,
    odom_frame: String,
    newest_odometry_ns: Option<i64>,
    map_from_odom: Option<Isometry3<f64>>,
    last_published_ns: Option<i64>,
    /// Odometry time of the last odometry-driven publication.
    last_odometry_publication_ns: Option<i64>,
}

impl TfBroadcaster {
    pub fn new(publisher: RosPublisher, map_frame: String, tolerance_seconds: f64) -> Self {
        Self {
            map_frame,
            tolerance_ns: (tolerance_seconds * 1e9).round() as i64,
            odom_frame_fixed: false,
            state: Mutex::new(State {
                publisher,
                keyframes: BTreeMap::new(),
                odom_frame: DEFAULT_ODOM_FRAME.into(),
                newest_odometry_ns: None,
                map_from_odom: None,
                last_published_ns: None,
                last_odometry_publication_ns: None,
            }),
        }
    }

    /// The correction's child frame is `odom_frame`, not odometry's `header.frame_id` (a
    /// robot's node: its `robot_odom_frame`).
    pub fn with_odom_frame(mut self, odom_frame: String) -> Self {
        self.odom_frame_fixed = true;
        self.state.get_mut().odom_frame = odom_frame;
        self
    }

    /// An odometry message was used; `keyframes`: those it made, with their odometry poses.
    pub async fn on_odometry(
        &self,
        stamp: Time,
        frame_id: &str,
        keyframes: &[(Key, Isometry3<f64>)],
    ) {
        let mut state = self.state.lock().await;
        let stamp_ns = stamp.nanoseconds();
        if !self.odom_frame_fixed && !frame_id.is_empty() && state.odom_frame != frame_id {
            state.odom_frame = frame_id.to_string();
        }
        state.newest_odometry_ns = Some(
            state
                .newest_odometry_ns
                .map_or(stamp_ns, |n| n.max(stamp_ns)),
        );
        state.remember(keyframes);
        let due = state
            .last_odometry_publication_ns
            .is_none_or(|last| stamp_ns - last >= MIN_PERIOD_NS);
        if due && state.map_from_odom.is_some() {
            state.last_odometry_publication_ns = Some(stamp_ns);
            self.publish(&mut state).await;
        }
    }

    /// Keyframes made later than their odometry message (a window's, once the IMU covers them).
    pub async fn on_keyframes(&self, keyframes: &[(Key, Isometry3<f64>)]) {
        self.state.lock().await.remember(keyframes);
    }

    /// A solve's estimate: the correction from its newest keyframe whose odometry pose is known.
    pub async fn on_solve(&self, estimate: &[VariableValue]) {
        let mut state = self.state.lock().await;
        let newest = estimate.iter().rev().find_map(|v| {
            let odometry = state.keyframes.get(&v.key)?;
            Some((v.key, se3_estimate(v)? * odometry.inverse()))
        });
        let Some((key, map_from_odom)) = newest else {
            return;
        };
        state.map_from_odom = Some(map_from_odom);
        state.keyframes = state.keyframes.split_off(&key);
        self.publish(&mut state).await;
    }

    async fn publish(&self, state: &mut State) {
        let (Some(correction), Some(odometry_ns)) = (state.map_from_odom, state.newest_odometry_ns)
        else {
            return;
        };
        let stamp_ns = (odometry_ns + self.tolerance_ns)
            .max(state.last_published_ns.map_or(i64::MIN, |last| last + 1));
        state.last_published_ns = Some(stamp_ns);
        let message = TfMessage {
            transforms: vec![TransformStamped {
                header: Header {
                    stamp: Time::from_nanoseconds(stamp_ns),
                    frame_id: self.map_frame.clone(),
                },
                child_frame_id: state.odom_frame.clone(),
                transform: Transform::from(&correction),
            }],
        };
        state.publisher.put(cdr_codec::encode(&message)).await;
    }
}

impl TfBroadcaster {
    /// Puts `transforms` as one message on the same topic (a session's robots' frames, see
    /// `robot_tf`, stamped there).
    pub async fn put_transforms(&self, transforms: Vec<TransformStamped>) {
        let message = TfMessage { transforms };
        let mut state = self.state.lock().await;
        state.publisher.put(cdr_codec::encode(&message)).await;
    }
}

impl State {
    fn remember(&mut self, keyframes: &[(Key, Isometry3<f64>)]) {
        self.keyframes.extend(keyframes.iter().copied());
        while self.keyframes.len() > MAX_PENDING_KEYFRAMES {
            self.keyframes.pop_first();
        }
    }
}
