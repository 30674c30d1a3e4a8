//! The binding's subscriptions: odometry, absolute poses, IMU samples, loop closures and
//! landmark sightings, in the order they arrive, decoded from CDR, checked (`bounds`), turned
//! into batches by the [`Keyframer`] (pose graphs; closures and sightings in `closures`) or
//! fusion messages by the [`WindowFeed`] (sliding windows), and executed as any client's
//! commands.
//!
//! A message that cannot be used (larger than `max_body_bytes`, not CDR of the expected type, a
//! value out of bounds, a stamp not after its topic's previous one, a bad covariance, a prior
//! before any keyframe, a closure or sighting with no keyframe near its stamp — unless it is
//! ahead of odometry, or a closure between robots ahead of the other robot's keyframes: then it
//! waits for its keyframe) is counted and reported on the session's error stream (SSE, zenoh
//! `out/errors`) with code `ros2_bad_message`; nothing of it reaches the session.

use std::io::Read;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use tokio::sync::watch;
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;

use super::attachment::{self, Attachment, AttachmentError};
use super::bounds::{self, BadValue, Stamps, Stream};
use super::cdr_codec;
use super::keyframes::{stamp_ns, Keyframer, MessageError};
use super::messages::{
    Imu, LandmarkSighting, LoopClosure, Odometry, PoseWithCovarianceStamped, RobotLoopClosure, IMU,
    LANDMARK_SIGHTING, LOOP_CLOSURE, ODOMETRY, POSE_WITH_COVARIANCE_STAMPED, ROBOT_LOOP_CLOSURE,
};
use super::robot_nodes::RobotNode;
use super::tf::TfBroadcaster;
use super::window_feed::{Feed, WindowFeed};
use crate::api::wire::Batch;
use crate::api::{ApplyBatch, Fusion};
use crate::service::{Caller, Command, Delivery, Service, ServiceError};

pub(super) type Samples = Subscriber<FifoChannelHandler<Sample>>;

/// Why a ROS message was not used.
#[derive(Debug, thiserror::Error)]
enum Unusable {
    /// Refused on its size alone, before a byte of it is copied or decoded, as factord's own
    /// keys refuse a put beyond `max_body_bytes` (`transport::zenoh::oversized`).
    #[error("the payload has {len} bytes; the limit is {limit} (max_body_bytes)")]
    TooLarge { len: usize, limit: usize },
    #[error(transparent)]
    Cdr(#[from] cdr_codec::CdrError),
    #[error(transparent)]
    Value(#[from] BadValue),
    #[error(transparent)]
    Message(#[from] MessageError),
    #[error(transparent)]
    Attachment(#[from] AttachmentError),
}

/// What turns messages into commands: keyframes of a pose graph, or a window's fusion feed.
pub(super) enum Feeder {
    Graph(Keyframer),
    /// Boxed: several times a keyframer's size (clippy: large_enum_variant).
    Window(Box<WindowFeed>),
}

/// The binding's input topics.
#[derive(Clone, Copy)]
pub(super) enum Topic {
    Odometry,
    Prior,
    Imu,
    LoopClosure,
    Landmark,
    RobotLoopClosure,
}

/// A decoded message (its values still to check: [`Message::checked_stamp`]).
#[derive(Clone)]
pub(super) enum Message {
    /// Boxed: an odometry message (pose and twist with their covariances) is the largest.
    Odometry(Box<Odometry>),
    Prior(PoseWithCovarianceStamped),
    Imu(Imu),
    LoopClosure(LoopClosure),
    Landmark(LandmarkSighting),
    RobotLoopClosure(RobotLoopClosure),
}

impl Topic {
    fn field(self) -> &'static str {
        match self {
            Topic::Odometry => "ros2.odometry_topic",
            Topic::Prior => "ros2.prior_topic",
            Topic::Imu => "ros2.imu_topic",
            Topic::LoopClosure => "ros2.loop_closure_topic",
            Topic::Landmark => "ros2.landmark_topic",
            Topic::RobotLoopClosure => "ros2.robot_loop_closure_topic",
        }
    }

    /// The stream whose stamps must increase; none for closures and sightings, which attach
    /// to keyframes already made (several sightings share their keyframe's stamp).
    fn stream(self) -> Option<Stream> {
        match self {
            Topic::Odometry => Some(Stream::Odometry),
            Topic::Prior => Some(Stream::Prior),
            Topic::Imu => Some(Stream::Imu),
            Topic::LoopClosure | Topic::Landmark | Topic::RobotLoopClosure => None,
        }
    }

    /// The message of a `len`-byte payload of this topic, read from `payload`.
    fn decode(self, payload: impl Read, len: usize) -> Result<Message, cdr_codec::CdrError> {
        use cdr_codec::decode_from;
        Ok(match self {
            Topic::Odometry => {
                Message::Odometry(Box::new(decode_from(payload, len, ODOMETRY.name)?))
            }
            Topic::Prior => {
                let name = POSE_WITH_COVARIANCE_STAMPED.name;
                Message::Prior(decode_from(payload, len, name)?)
            }
            Topic::Imu => Message::Imu(decode_from(payload, len, IMU.name)?),
            Topic::LoopClosure => {
                Message::LoopClosure(decode_from(payload, len, LOOP_CLOSURE.name)?)
            }
            Topic::Landmark => {
                Message::Landmark(decode_from(payload, len, LANDMARK_SIGHTING.name)?)
            }
            Topic::RobotLoopClosure => {
                Message::RobotLoopClosure(decode_from(payload, len, ROBOT_LOOP_CLOSURE.name)?)
            }
        })
    }
}

/// Loop closures and sightings held until odometry makes their keyframes, at most.
const MAX_AHEAD: usize = 1000;

impl Message {
    /// For a closure or a sighting, the newest stamp it needs a keyframe at.
    fn keyframe_stamp(&self) -> Option<f64> {
        match self {
            Message::LoopClosure(m) => Some(m.from_stamp.seconds().max(m.to_stamp.seconds())),
            Message::Landmark(m) => Some(m.header.stamp.seconds()),
            // The other robot's keyframe is older, or made by its own node.
            Message::RobotLoopClosure(m) => Some(m.to_stamp.seconds()),
            _ => None,
        }
    }

    /// Its stamp in seconds, once its values are within bounds (not yet the stamp's order).
    fn checked_stamp(&self) -> Result<f64, BadValue> {
        match self {
            Message::Odometry(m) => bounds::odometry(m),
            Message::Prior(m) => bounds::prior(m),
            Message::Imu(m) => bounds::imu(m),
            Message::LoopClosure(m) => bounds::loop_closure(m),
            Message::Landmark(m) => bounds::landmark(m),
            Message::RobotLoopClosure(m) => bounds::loop_closure(&m.closure()),
        }
    }
}

pub(super) struct Inputs {
    pub service: Arc<Service>,
    pub caller: Arc<Caller>,
    pub session: String,
    pub feeder: Feeder,
    pub odometry: Samples,
    pub priors: Option<Samples>,
    pub imu: Option<Samples>,
    pub loop_closures: Option<Samples>,
    pub landmarks: Option<Samples>,
    pub robot_loop_closures: Option<Samples>,
    /// A robot's node: its robot, and how closures between robots find the other one.
    pub robot: Option<RobotNode>,
    /// Told of every odometry message used and every keyframe made (`map → odom` on `/tf`).
    pub tf: Option<Arc<TfBroadcaster>>,
    /// Messages refused so far (reported with each refusal).
    pub refused: Arc<AtomicU64>,
    /// The largest payload taken, `max_body_bytes` as for factord's own keys.
    pub max_payload: usize,
    /// The newest stamp used on each topic.
    pub stamps: Stamps,
    /// Closures and sightings ahead of odometry, waiting for their keyframes (see
    /// [`Inputs::hold_if_ahead`]).
    pub ahead: Vec<(Topic, Message)>,
    /// A robot's node: moves when any node's keyframe batch is taken by the session.
    pub keyframes_taken: Option<watch::Receiver<u64>>,
}

/// rmw_zenoh always attaches one; a sample without (a plain zenoh put) is taken, one with
/// something else is not from rmw_zenoh and is refused, on its length before it is copied.
fn check_attachment(sample: &Sample) -> Result<(), AttachmentError> {
    match sample.attachment() {
        None => Ok(()),
        Some(a) if a.len() != attachment::ENCODED_SIZE => Err(AttachmentError { len: a.len() }),
        Some(a) => Attachment::decode(&a.to_bytes()).map(drop),
    }
}

/// The robot a closure between robots starts at, when `node` takes it (it ends at the node's
/// robot); `None` when it is another node's. A closure that names no robot of the binding is
/// refused by the node it ends at, or by the first node when it ends at no robot.
fn robot_closure_from(
    node: Option<&RobotNode>,
    m: &RobotLoopClosure,
) -> Result<Option<u8>, MessageError> {
    let Some(node) = node else {
        return Ok(None);
    };
    let unknown = |field, name: &str| MessageError::UnknownRobot {
        field,
        name: name.to_string(),
    };
    match (
        node.robot_named(&m.from_robot),
        node.robot_named(&m.to_robot),
    ) {
        (from, Some(to)) if to == node.robot => from
            .map(Some)
            .ok_or_else(|| unknown("from_robot", &m.from_robot)),
        (_, Some(_)) => Ok(None),
        (_, None) if node.first => Err(unknown("to_robot", &m.to_robot)),
        (_, None) => Ok(None),
    }
}

/// When the next keyframe of any robot's node is taken (never, outside a node per robot).
async fn keyframe_taken(taken: &mut Option<watch::Receiver<u64>>) {
    let Some(taken) = taken else {
        return std::future::pending().await;
    };
    // Every node holds the sender (in its shared keyframes): it closes only with the binding.
    if taken.changed().await.is_err() {
        std::future::pending::<()>().await;
    }
}

/// The next sample of an optional subscription (never, without one).
async fn next(samples: &Option<Samples>) -> Result<Sample, zenoh::Error> {
    match samples {
        Some(samples) => samples.recv_async().await,
        None => std::future::pending().await,
    }
}

impl Inputs {
    /// Takes messages until the subscriptions end (the binding is dropped).
    pub async fn run(mut self) {
        loop {
            let (sample, topic) = tokio::select! {
                s = self.odometry.recv_async() => (s, Topic::Odometry),
                s = next(&self.priors) => (s, Topic::Prior),
                s = next(&self.imu) => (s, Topic::Imu),
                s = next(&self.loop_closures) => (s, Topic::LoopClosure),
                s = next(&self.landmarks) => (s, Topic::Landmark),
                s = next(&self.robot_loop_closures) => (s, Topic::RobotLoopClosure),
                // Another robot's keyframe was taken: closures held for it may enter.
                _ = keyframe_taken(&mut self.keyframes_taken), if !self.ahead.is_empty() => {
                    self.retry_ahead().await;
                    continue;
                }
            };
            let Ok(sample) = sample else { return };
            match self.use_sample(topic, &sample).await {
                Ok(commands) => {
                    let keyframed = matches!(topic, Topic::Odometry) && !commands.is_empty();
                    for command in commands {
                        self.deliver(Ok(command)).await;
                    }
                    if keyframed {
                        self.announce_keyframe();
                    }
                    if keyframed && !self.ahead.is_empty() {
                        self.retry_ahead().await;
                    }
                }
                Err(unusable) => self.refuse(unusable, topic).await,
            }
        }
    }

    /// A closure or sighting whose keyframe is not there yet, stamped after the newest
    /// odometry used: its topic is not odometry's, and it may well arrive first (a front-end
    /// publishes a sighting as the odometry of its pose goes out). Held, not refused, until
    /// odometry makes a keyframe; `Ok(false)` when it is not ahead.
    fn hold_if_ahead(
        &mut self,
        topic: Topic,
        message: &Message,
        error: &MessageError,
    ) -> Result<bool, MessageError> {
        let waiting = matches!(
            error,
            MessageError::NoKeyframeNear { .. } | MessageError::NoKeyframeYet
        );
        let newest = self.stamps.newest(Stream::Odometry);
        let ahead = match (message.keyframe_stamp(), newest) {
            (Some(t), Some(newest)) => t > newest,
            (Some(_), None) => true,
            (None, _) => false,
        } || self.ahead_of_other_robot(message);
        if !(waiting && ahead) {
            return Ok(false);
        }
        if self.ahead.len() >= MAX_AHEAD {
            return Err(MessageError::TooManyAhead {
                held: self.ahead.len(),
            });
        }
        self.ahead.push((topic, message.clone()));
        Ok(true)
    }

    /// A closure between robots stamped, at the robot it starts from, after that robot's
    /// newest keyframe (or before its first): its odometry may lag this robot's, and the
    /// closure waits for the keyframe (retried when any node's keyframe is taken).
    fn ahead_of_other_robot(&self, message: &Message) -> bool {
        let (Message::RobotLoopClosure(m), Some(node)) = (message, &self.robot) else {
            return false;
        };
        let Some(from) = node.robot_named(&m.from_robot) else {
            return false;
        };
        node.keyframes
            .newest(from)
            .is_none_or(|newest| stamp_ns(m.from_stamp.seconds()) > newest)
    }

    /// This node's keyframe batch was taken by the session: the other nodes may now take the
    /// closures they hold for it. (This node retries its own right after.)
    fn announce_keyframe(&mut self) {
        if let Some(node) = &self.robot {
            node.keyframes.announce_taken();
        }
        if let Some(taken) = &mut self.keyframes_taken {
            taken.mark_unchanged();
        }
    }

    /// After a keyframe: the held closures and sightings again, in their order (each is held
    /// again while still ahead of odometry).
    async fn retry_ahead(&mut self) {
        for (topic, message) in std::mem::take(&mut self.ahead) {
            match self.take(message).await {
                Ok(commands) => {
                    for command in commands {
                        self.deliver(Ok(command)).await;
                    }
                }
                Err(unusable) => self.refuse(unusable, topic).await,
            }
        }
    }

    /// The commands a sample makes: its size and attachment checked before anything of it is
    /// copied, then decoded as it is read, its values and stamp checked, and taken.
    async fn use_sample(
        &mut self,
        topic: Topic,
        sample: &Sample,
    ) -> Result<Vec<Command>, Unusable> {
        let payload = sample.payload();
        let (len, limit) = (payload.len(), self.max_payload);
        if len > limit {
            return Err(Unusable::TooLarge { len, limit });
        }
        check_attachment(sample)?;
        let message = topic.decode(payload.reader(), len)?;
        let t = message.checked_stamp()?;
        if let Some(stream) = topic.stream() {
            self.stamps.check(stream, t)?;
        }
        let commands = self.take(message).await?;
        if let Some(stream) = topic.stream() {
            self.stamps.record(stream, t);
        }
        Ok(commands)
    }

    /// The commands a message makes, in order (none while odometry has not moved enough).
    async fn take(&mut self, message: Message) -> Result<Vec<Command>, Unusable> {
        let session = &self.session;
        let graph = |batch: Option<Batch>| {
            batch
                .map(|batch| {
                    Command::ApplyBatch(ApplyBatch {
                        session: session.clone(),
                        batch,
                        wait: false,
                    })
                })
                .into_iter()
                .collect()
        };
        let fusion = |feed: Feed| -> Vec<Command> {
            feed.batches
                .into_iter()
                .map(|messages| {
                    Command::Fusion(Fusion {
                        session: session.clone(),
                        messages,
                    })
                })
                .collect()
        };
        Ok(match (message, &mut self.feeder) {
            (Message::Odometry(odometry), feeder) => {
                let (commands, keyframes) = match feeder {
                    Feeder::Graph(keyframer) => {
                        let batch = keyframer.on_odometry(&odometry)?;
                        let keyframe = batch.as_ref().and(keyframer.last_keyframe());
                        (graph(batch), keyframe.into_iter().collect())
                    }
                    Feeder::Window(feed) => {
                        let feed = feed.on_odometry(&odometry)?;
                        let keyframes = feed.keyframes.clone();
                        (fusion(feed), keyframes)
                    }
                };
                if let Some(tf) = &self.tf {
                    let header = &odometry.header;
                    tf.on_odometry(header.stamp, &header.frame_id, &keyframes)
                        .await;
                }
                commands
            }
            (Message::Prior(prior), feeder) => match feeder {
                Feeder::Graph(keyframer) => graph(Some(keyframer.on_prior(&prior)?)),
                Feeder::Window(feed) => fusion(feed.on_prior(&prior)?),
            },
            (Message::Imu(imu), Feeder::Window(feed)) => {
                let feed = feed.on_imu(&imu)?;
                if let (Some(tf), false) = (&self.tf, feed.keyframes.is_empty()) {
                    tf.on_keyframes(&feed.keyframes).await;
                }
                fusion(feed)
            }
            (Message::LoopClosure(closure), Feeder::Graph(keyframer)) => {
                match keyframer.on_loop_closure(&closure) {
                    Ok(batch) => graph(Some(batch)),
                    Err(e) => {
                        return self.held_or(Topic::LoopClosure, Message::LoopClosure(closure), e)
                    }
                }
            }
            (Message::Landmark(sighting), Feeder::Graph(keyframer)) => {
                match keyframer.on_landmark(&sighting) {
                    Ok(batch) => graph(Some(batch)),
                    Err(e) => return self.held_or(Topic::Landmark, Message::Landmark(sighting), e),
                }
            }
            (Message::RobotLoopClosure(m), Feeder::Graph(keyframer)) => {
                let Some(from) = robot_closure_from(self.robot.as_ref(), &m)? else {
                    return Ok(Vec::new());
                };
                match keyframer.on_robot_loop_closure(from, &m.closure()) {
                    Ok(batch) => graph(Some(batch)),
                    Err(e) => {
                        return self.held_or(
                            Topic::RobotLoopClosure,
                            Message::RobotLoopClosure(m),
                            e,
                        )
                    }
                }
            }
            // A pose graph's binding subscribes to no IMU, a window's to no closures or
            // landmarks (`Ros2Binding::check_kind`), robots' nodes feed pose graphs only.
            (Message::Imu(_), Feeder::Graph(_))
            | (
                Message::LoopClosure(_) | Message::Landmark(_) | Message::RobotLoopClosure(_),
                Feeder::Window(_),
            ) => Vec::new(),
        })
    }

    /// No commands when `message` is held for its keyframe, else its error.
    fn held_or(
        &mut self,
        topic: Topic,
        message: Message,
        error: MessageError,
    ) -> Result<Vec<Command>, Unusable> {
        match self.hold_if_ahead(topic, &message, &error)? {
            true => Ok(Vec::new()),
            false => Err(error.into()),
        }
    }

    async fn refuse(&self, unusable: Unusable, topic: Topic) {
        let refused = self.refused.fetch_add(1, Ordering::Relaxed) + 1;
        let (session, field) = (&self.session, topic.field());
        match unusable {
            // A robot does not send these by mistake: the operator should know (each costs the
            // sender at least `max_body_bytes`, so they cannot flood the log).
            Unusable::TooLarge { .. } => {
                tracing::warn!(session, field, "ROS message refused: {unusable}")
            }
            _ => tracing::debug!(session, field, "ROS message refused: {unusable}"),
        }
        let error = ServiceError::bad_request(
            "ros2_bad_message",
            topic.field(),
            format!("{unusable} ({refused} ROS message(s) refused in this binding)"),
        );
        self.deliver(Err(error)).await;
    }

    /// As any transport's message: executed, a rejection on the session's error stream.
    async fn deliver(&self, decoded: Result<Command, ServiceError>) {
        let delivery = Delivery::decoded(&self.session, decoded);
        if let Err(e) = self.service.deliver_decoded(&self.caller, delivery).await {
            tracing::debug!(session = self.session, "ROS input without a session: {e}");
        }
    }
}
