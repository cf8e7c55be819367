//! `slag-edge serve --ros2`: a ROS 2 node beside the HTTP API, over DDS (RustDDS through
//! `ros2_client`), with no ROS installation.
//!
//! The node answers prompts with the same [`QueryEngine`] as `GET /query`: the same loaded
//! generation (a reload or `POST /fetch` is seen by both), the same threshold and the same
//! admission gate ([`crate::engine::admission`]). It knows nothing of HTTP. Its topics are under the node's private namespace
//! (`~/x` = `<namespace>/<node>/x`):
//!
//! | topic | type | direction |
//! |---|---|---|
//! | `~/prompt` | `std_msgs/msg/String` | subscribed: one prompt per message |
//! | `~/objects` | `vision_msgs/msg/Detection3DArray` | published: one `Detection3D` per object |
//! | `~/matches` | `sensor_msgs/msg/PointCloud2` | published: the top matches, fields x, y, z, score |
//! | `~/markers` | `visualization_msgs/msg/MarkerArray` | published: boxes and labels for RViz |
//!
//! Every published message of one answer carries the same `header`: `frame_id` from
//! [`Ros2Options::frame_id`], `stamp` the time the answer was made. QoS: the prompt subscription
//! is reliable, volatile, keep-last 10; the publishers are reliable, transient-local, keep-last
//! 1, so a subscriber that joins late still gets the last answer.
//!
//! A blank prompt or one over [`slag_common::prompt::MAX_PROMPT_BYTES`] publishes nothing: it is
//! logged and counted ([`Ros2Counters::refused`]). Prompts wait in a queue of
//! [`crate::engine::EngineOptions::scan_queue`] entries for the admission gate; a prompt that finds
//! that queue full, or that the gate turns away because HTTP queries fill it (where HTTP answers
//! 503), is dropped, logged and counted ([`Ros2Counters::dropped_busy`]).

pub mod convert;
pub mod msg;

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use futures_util::StreamExt;
use ros2_client::qos::{Durability, History, WhenFull};
use ros2_client::{Context, ContextOptions, Name, NodeName, NodeOptions, QosProfile};
use slag_common::{Error, Result};

use crate::engine::QueryEngine;
use crate::query::{Interface, QueryParams, RawQuery};
use msg::{Detection3DArray, MarkerArray, PointCloud2, RosMessage, StringMsg};

/// Default node name.
pub const DEFAULT_NODE_NAME: &str = "slag";
/// Default namespace (the root).
pub const DEFAULT_NAMESPACE: &str = "/";
/// Default `header.frame_id`.
pub const DEFAULT_FRAME_ID: &str = "map";
/// Largest DDS domain id whose RTPS ports fit in 16 bits (ROS 2's own upper bound).
pub const MAX_DOMAIN_ID: u16 = 232;
/// How to give a prompt over ROS 2 (ends the log line of a refused prompt).
const PROMPT_HINT: &str = "publish std_msgs/msg/String \"data: chair\" on ~/prompt";

/// Settings of the ROS 2 node.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ros2Options {
    /// Node name (`[A-Za-z_][A-Za-z0-9_]*`).
    pub node_name: String,
    /// Namespace: `/` or `/a/b` (absolute, no trailing slash).
    pub namespace: String,
    /// `header.frame_id` of everything published.
    pub frame_id: String,
    /// DDS domain (`ROS_DOMAIN_ID`).
    pub domain_id: u16,
}

impl Default for Ros2Options {
    /// [`DEFAULT_NODE_NAME`], [`DEFAULT_NAMESPACE`], [`DEFAULT_FRAME_ID`], domain 0.
    fn default() -> Self {
        Ros2Options {
            node_name: DEFAULT_NODE_NAME.into(),
            namespace: DEFAULT_NAMESPACE.into(),
            frame_id: DEFAULT_FRAME_ID.into(),
            domain_id: 0,
        }
    }
}

impl Ros2Options {
    /// The node's fully qualified name, e.g. `/robot1/slag`.
    pub fn node_fqn(&self) -> String {
        match self.namespace.as_str() {
            "/" => format!("/{}", self.node_name),
            ns => format!("{ns}/{}", self.node_name),
        }
    }

    /// The ROS name of the private topic `~/leaf`, e.g. `/robot1/slag/prompt`.
    pub fn topic(&self, leaf: &str) -> String {
        format!("{}/{leaf}", self.node_fqn())
    }

    /// The DDS topic name of `~/leaf` (ROS 2's `rt` prefix), e.g. `rt/robot1/slag/prompt`.
    pub fn dds_topic(&self, leaf: &str) -> String {
        format!("rt{}", self.topic(leaf))
    }

    /// Checks the names and the frame.
    ///
    /// Errors: [`Error::Param`] `ros2_node`, `ros2_namespace` or `ros2_frame_id` naming the rule
    /// broken.
    pub fn check(&self) -> Result<NodeName> {
        if self.frame_id.trim().is_empty() {
            return Err(Error::param(
                "ros2_frame_id",
                format!("{:?}", self.frame_id),
                "a tf2 frame name such as map",
            ));
        }
        let node = NodeName::new(&self.namespace, &self.node_name).map_err(|e| {
            let (name, value) = match e {
                ros2_client::names::NameError::BadSlash(..) => ("ros2_namespace", &self.namespace),
                _ if NodeName::new("/", &self.node_name).is_err() => ("ros2_node", &self.node_name),
                _ => ("ros2_namespace", &self.namespace),
            };
            Error::param(
                name,
                format!("{value:?}"),
                "a ROS 2 name: node [A-Za-z_][A-Za-z0-9_]*, namespace / or /a/b",
            )
        })?;
        // The node's name becomes part of every topic name, which refuses `__`.
        Name::new(&self.node_fqn(), "prompt").map_err(|_| {
            Error::param(
                "ros2_node",
                format!("{:?} in {:?}", self.node_name, self.namespace),
                "names without a double underscore",
            )
        })?;
        Ok(node)
    }
}

/// Reads `ROS_DOMAIN_ID` as ROS 2 does: unset or empty is domain 0.
///
/// Errors: [`Error::Param`] `ROS_DOMAIN_ID` when it is not an integer in `0..=232`.
pub fn domain_id_from_env() -> Result<u16> {
    domain_id_from(std::env::var("ROS_DOMAIN_ID").ok().as_deref())
}

/// [`domain_id_from_env`] for a given value of the variable.
///
/// Errors: as [`domain_id_from_env`].
pub fn domain_id_from(value: Option<&str>) -> Result<u16> {
    match value.map(str::trim) {
        None | Some("") => Ok(0),
        Some(v) => v
            .parse::<u16>()
            .ok()
            .filter(|d| *d <= MAX_DOMAIN_ID)
            .ok_or_else(|| {
                Error::param(
                    "ROS_DOMAIN_ID",
                    format!("{v:?}"),
                    format!("an integer in 0..={MAX_DOMAIN_ID}"),
                )
            }),
    }
}

/// What the node did with the prompts it received (all monotonic).
#[derive(Debug, Default)]
pub struct Ros2Counters {
    /// Prompts received on `~/prompt`.
    pub received: AtomicU64,
    /// Prompts answered (published on the three topics).
    pub answered: AtomicU64,
    /// Prompts refused before any model ran: blank or too long.
    pub refused: AtomicU64,
    /// Prompts dropped because the node or the admission gate was full.
    pub dropped_busy: AtomicU64,
    /// Prompts whose query failed (a model or store fault; logged).
    pub failed: AtomicU64,
    /// Answers of which at least one message could not be published.
    pub publish_failed: AtomicU64,
}

/// A snapshot of [`Ros2Counters`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct Ros2Counts {
    /// [`Ros2Counters::received`].
    pub received: u64,
    /// [`Ros2Counters::answered`].
    pub answered: u64,
    /// [`Ros2Counters::refused`].
    pub refused: u64,
    /// [`Ros2Counters::dropped_busy`].
    pub dropped_busy: u64,
    /// [`Ros2Counters::failed`].
    pub failed: u64,
    /// [`Ros2Counters::publish_failed`].
    pub publish_failed: u64,
}

impl Ros2Counters {
    /// The current counts.
    pub fn snapshot(&self) -> Ros2Counts {
        let g = |c: &AtomicU64| c.load(Ordering::SeqCst);
        Ros2Counts {
            received: g(&self.received),
            answered: g(&self.answered),
            refused: g(&self.refused),
            dropped_busy: g(&self.dropped_busy),
            failed: g(&self.failed),
            publish_failed: g(&self.publish_failed),
        }
    }
}

/// What became of one received prompt ([`PromptIntake::offer`]).
#[derive(Debug)]
pub enum Offer {
    /// Queued for the admission gate.
    Queued,
    /// Refused: blank or too long ([`Error::Query`] `text`).
    Refused(Error),
    /// Dropped: the queue is full.
    Dropped,
}

/// The first step of a received prompt: checked, then queued (bounded) or counted away.
pub struct PromptIntake {
    tx: tokio::sync::mpsc::Sender<QueryParams>,
    threshold: f32,
    counters: Arc<Ros2Counters>,
}

impl PromptIntake {
    /// An intake that queues at most `capacity` (≥ 1) prompts; the receiver takes them in order.
    pub fn new(
        capacity: usize,
        threshold: f32,
        counters: Arc<Ros2Counters>,
    ) -> (PromptIntake, tokio::sync::mpsc::Receiver<QueryParams>) {
        let (tx, rx) = tokio::sync::mpsc::channel(capacity.max(1));
        (
            PromptIntake {
                tx,
                threshold,
                counters,
            },
            rx,
        )
    }

    /// Checks `prompt` like `GET /query?text=…` (the server's threshold, default parameters)
    /// and queues it, counting and logging a refusal or a drop.
    pub fn offer(&self, prompt: String) -> Offer {
        self.counters.received.fetch_add(1, Ordering::SeqCst);
        let params = slag_common::prompt::check_prompt(&prompt, PROMPT_HINT).and_then(|()| {
            RawQuery {
                text: Some(prompt),
                ..RawQuery::default()
            }
            .validate_for(self.threshold, Interface::Cli)
        });
        let params = match params {
            Ok(p) => p,
            Err(e) => {
                let n = self.counters.refused.fetch_add(1, Ordering::SeqCst) + 1;
                tracing::warn!("ros2: prompt refused ({n} so far): {e}");
                return Offer::Refused(e);
            }
        };
        match self.tx.try_send(params) {
            Ok(()) => Offer::Queued,
            Err(_) => {
                let n = self.counters.dropped_busy.fetch_add(1, Ordering::SeqCst) + 1;
                tracing::warn!(
                    "ros2: prompt dropped, {} prompts already wait ({n} dropped so far)",
                    self.tx.max_capacity()
                );
                Offer::Dropped
            }
        }
    }
}

/// The running node: its counters and the names it uses. Dropping it leaves the node running
/// until the runtime shuts down.
pub struct Ros2Node {
    /// What the node did with the prompts it received.
    pub counters: Arc<Ros2Counters>,
    /// Its settings.
    pub options: Ros2Options,
}

fn dds_error(opts: &Ros2Options, what: &str, e: impl std::fmt::Display) -> Error {
    Error::network(
        format!("ROS 2 domain {} node {}", opts.domain_id, opts.node_fqn()),
        format!("{what}: {e}"),
    )
}

/// Starts the node on the current tokio runtime: joins the DDS domain, creates the node, its
/// subscription and publishers, and spawns the tasks that answer prompts with `engine` (a
/// [`QueryEngine`], or the state of an HTTP server, which shares its engine).
///
/// Errors: [`Error::Param`] for a bad name or frame ([`Ros2Options::check`]),
/// [`Error::Network`] when the DDS participant or an entity cannot be created (e.g. no UDP port
/// free in the domain's range). Panics outside a tokio runtime.
pub fn start(engine: impl Into<QueryEngine>, options: Ros2Options) -> Result<Ros2Node> {
    let engine = engine.into();
    let node_name = options.check()?;
    let context = Context::with_options(ContextOptions::new().domain_id(options.domain_id))
        .map_err(|e| dds_error(&options, "joining the DDS domain", e))?;
    let mut node = context
        .new_node(node_name, NodeOptions::new().enable_rosout(false))
        .map_err(|e| dds_error(&options, "creating the node", e))?;
    let (sub, publishers) = endpoints(&mut node, &options)?;
    let spinner = node
        .spinner()
        .map_err(|e| dds_error(&options, "starting the node's spinner", e))?;
    let counters = Arc::new(Ros2Counters::default());
    let (intake, queue) = PromptIntake::new(
        engine.options().scan_queue,
        engine.options().threshold,
        counters.clone(),
    );
    tokio::spawn(async move {
        if let Err(e) = spinner.spin().await {
            tracing::error!("ros2: the node's spinner stopped: {e}");
        }
    });
    // Receives prompts for as long as the process runs; the node and context live in this task.
    tokio::spawn(async move {
        let _keep = (context, node);
        let mut stream = std::pin::pin!(sub.async_stream());
        while let Some(r) = stream.next().await {
            match r {
                Ok((m, _info)) => {
                    intake.offer(m.data);
                }
                Err(e) => tracing::warn!("ros2: a prompt could not be read: {e}"),
            }
        }
    });
    let answering = Answering {
        engine,
        publishers,
        frame_id: options.frame_id.clone(),
        counters: counters.clone(),
    };
    tokio::spawn(answering.run(queue));
    tracing::info!(
        "ros2: node {} in domain {}: subscribes {}, publishes {}, {}, {} (frame {})",
        options.node_fqn(),
        options.domain_id,
        options.topic("prompt"),
        options.topic("objects"),
        options.topic("matches"),
        options.topic("markers"),
        options.frame_id
    );
    Ok(Ros2Node { counters, options })
}

/// The node's topics: the `~/prompt` subscription (reliable, volatile, keep-last 10) and the
/// publishers of `~/objects`, `~/matches` and `~/markers` (reliable, transient-local,
/// keep-last 1).
///
/// Errors: [`Error::Network`] naming the topic, subscription or publisher that could not be
/// created.
fn endpoints(
    node: &mut ros2_client::Node,
    options: &Ros2Options,
) -> Result<(ros2_client::Subscription<StringMsg>, Publishers)> {
    let fqn = options.node_fqn();
    let reliable = WhenFull::Wait(std::time::Duration::from_millis(100));
    let prompt_qos = QosProfile::subscription_default()
        .reliability_reliable(reliable)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 10 });
    let answer_qos = QosProfile::publisher_default()
        .reliability_reliable(reliable)
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 });
    let topic = |leaf: &str, ty: ros2_client::MessageTypeName, qos: &QosProfile| {
        let name = Name::new(&fqn, leaf).map_err(|e| dds_error(options, leaf, e))?;
        node.create_topic(&name, ty, qos)
            .map_err(|e| dds_error(options, &format!("topic ~/{leaf}"), e))
    };
    let t_prompt = topic("prompt", StringMsg::type_name(), &prompt_qos)?;
    let t_objects = topic("objects", Detection3DArray::type_name(), &answer_qos)?;
    let t_matches = topic("matches", PointCloud2::type_name(), &answer_qos)?;
    let t_markers = topic("markers", MarkerArray::type_name(), &answer_qos)?;
    let sub = node
        .create_subscription::<StringMsg>(&t_prompt, Some(prompt_qos.clone()))
        .map_err(|e| dds_error(options, "subscription ~/prompt", e))?;
    let publishers = Publishers {
        objects: node
            .create_publisher::<Detection3DArray>(&t_objects, Some(answer_qos.clone()))
            .map_err(|e| dds_error(options, "publisher ~/objects", e))?,
        matches: node
            .create_publisher::<PointCloud2>(&t_matches, Some(answer_qos.clone()))
            .map_err(|e| dds_error(options, "publisher ~/matches", e))?,
        markers: node
            .create_publisher::<MarkerArray>(&t_markers, Some(answer_qos))
            .map_err(|e| dds_error(options, "publisher ~/markers", e))?,
    };
    Ok((sub, publishers))
}

/// What answers the queued prompts: the query engine, the publishers, the frame of what is
/// published and the node's counters.
struct Answering {
    engine: QueryEngine,
    publishers: Publishers,
    frame_id: String,
    counters: Arc<Ros2Counters>,
}

impl Answering {
    /// Answers queued prompts one at a time, in order, through the admission gate, until the
    /// queue closes.
    async fn run(self, mut queue: tokio::sync::mpsc::Receiver<QueryParams>) {
        while let Some(params) = queue.recv().await {
            self.answer(params).await;
        }
    }

    /// Answers one prompt and publishes the answer, counting what became of it: answered,
    /// dropped (the scan queue is full), failed, or not published.
    async fn answer(&self, params: QueryParams) {
        let c = &self.counters;
        let received = std::time::Instant::now();
        match self.engine.query_one(params).await {
            Err(busy) => {
                let n = c.dropped_busy.fetch_add(1, Ordering::SeqCst) + 1;
                tracing::warn!(
                    "ros2: prompt dropped, the scan queue is full ({} waiting; {n} dropped so \
                     far)",
                    busy.waiting
                );
            }
            Ok(Ok(a)) => {
                let stamp = msg::Time::from_system(std::time::SystemTime::now());
                let m = convert::messages(&a, &self.frame_id, stamp);
                if self.publishers.publish(m).await {
                    c.answered.fetch_add(1, Ordering::SeqCst);
                } else {
                    c.publish_failed.fetch_add(1, Ordering::SeqCst);
                }
                tracing::debug!(
                    "ros2: prompt \"{}\" answered in {:.1} ms",
                    a.query.escape_debug(),
                    received.elapsed().as_secs_f64() * 1e3
                );
            }
            Ok(Err(e)) => {
                let n = c.failed.fetch_add(1, Ordering::SeqCst) + 1;
                tracing::warn!("ros2: query failed ({n} so far): {e}");
            }
        }
    }
}

/// The node's three publishers.
struct Publishers {
    objects: ros2_client::Publisher<Detection3DArray>,
    matches: ros2_client::Publisher<PointCloud2>,
    markers: ros2_client::Publisher<MarkerArray>,
}

impl Publishers {
    /// Publishes one answer's messages; `false` (each failure logged) when one could not be sent.
    async fn publish(&self, m: convert::AnswerMessages) -> bool {
        let mut ok = true;
        if let Err(e) = self.objects.async_publish(m.objects).await {
            tracing::warn!("ros2: publishing ~/objects failed: {e}");
            ok = false;
        }
        if let Err(e) = self.matches.async_publish(m.matches).await {
            tracing::warn!("ros2: publishing ~/matches failed: {e}");
            ok = false;
        }
        if let Err(e) = self.markers.async_publish(m.markers).await {
            tracing::warn!("ros2: publishing ~/markers failed: {e}");
            ok = false;
        }
        ok
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn private_topics_expand_under_the_namespace_and_node() {
        let o = Ros2Options::default();
        assert_eq!(o.topic("prompt"), "/slag/prompt");
        assert_eq!(o.dds_topic("objects"), "rt/slag/objects");
        let o = Ros2Options {
            namespace: "/robot1".into(),
            node_name: "edge".into(),
            ..Ros2Options::default()
        };
        assert_eq!(o.dds_topic("prompt"), "rt/robot1/edge/prompt");
        assert!(o.check().is_ok());
        assert_eq!(
            StringMsg::type_name().dds_msg_type(),
            "std_msgs::msg::dds_::String_"
        );
        assert_eq!(
            Detection3DArray::type_name().dds_msg_type(),
            "vision_msgs::msg::dds_::Detection3DArray_"
        );
    }

    #[test]
    fn bad_names_and_domains_are_typed_errors() {
        let bad = |o: Ros2Options| match o.check().unwrap_err() {
            Error::Param { name, .. } => name,
            e => panic!("{e}"),
        };
        let d = Ros2Options::default;
        assert_eq!(
            bad(Ros2Options {
                namespace: "robot".into(),
                ..d()
            }),
            "ros2_namespace"
        );
        assert_eq!(
            bad(Ros2Options {
                namespace: "/r/".into(),
                ..d()
            }),
            "ros2_namespace"
        );
        assert_eq!(
            bad(Ros2Options {
                node_name: "9x".into(),
                ..d()
            }),
            "ros2_node"
        );
        assert_eq!(
            bad(Ros2Options {
                node_name: "a-b".into(),
                ..d()
            }),
            "ros2_node"
        );
        assert_eq!(
            bad(Ros2Options {
                frame_id: " ".into(),
                ..d()
            }),
            "ros2_frame_id"
        );
        assert_eq!(domain_id_from(None).unwrap(), 0);
        assert_eq!(domain_id_from(Some("")).unwrap(), 0);
        assert_eq!(domain_id_from(Some("42")).unwrap(), 42);
        for v in ["233", "-1", "x"] {
            assert!(
                matches!(
                    domain_id_from(Some(v)),
                    Err(Error::Param {
                        name: "ROS_DOMAIN_ID",
                        ..
                    })
                ),
                "{v}"
            );
        }
    }

    #[test]
    fn blank_and_long_prompts_are_refused_and_a_full_queue_drops() {
        let c = Arc::new(Ros2Counters::default());
        let (intake, mut rx) = PromptIntake::new(1, 0.28, c.clone());
        assert!(matches!(intake.offer("  ".into()), Offer::Refused(_)));
        let long = "x".repeat(slag_common::prompt::MAX_PROMPT_BYTES + 1);
        assert!(matches!(
            intake.offer(long),
            Offer::Refused(Error::Query { field: "text", .. })
        ));
        assert!(matches!(intake.offer("chair".into()), Offer::Queued));
        assert!(matches!(intake.offer("table".into()), Offer::Dropped));
        let q = rx.try_recv().unwrap();
        assert_eq!(q.text, "chair");
        assert_eq!(q.threshold, Some(0.28));
        assert!(rx.try_recv().is_err());
        assert!(matches!(intake.offer("lamp".into()), Offer::Queued));
        assert_eq!(
            c.snapshot(),
            Ros2Counts {
                received: 5,
                refused: 2,
                dropped_busy: 1,
                ..Ros2Counts::default()
            }
        );
    }
}
