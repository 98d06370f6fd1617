//! Requests to peers, as `swarmrec/runtime/rpc.py`'s `Caller` sends them: the request
//! counted by message type and scope before it leaves, the caller's robot id as the
//! query's attachment (the router's access rules and the receiver's scope read it),
//! congestion blocking rather than dropping, a reply's bytes counted as it arrives, an
//! `ErrorReply` read as the peer's refusal and zenoh's own error as a timeout, and
//! every failure counted in `swarmrec_peer_failures_total` by endpoint and reason.
//!
//! A request to an endpoint this process serves (the caller's own robot's, or another
//! robot's hosted beside it) is served on the caller's thread when its result is first
//! asked for (`LocalEndpoints`), so the requests started after it are already on their
//! way meanwhile; the others go to other processes only (zenoh's `Locality::Remote`).
//! zenoh would otherwise serve a co-hosted robot's endpoint inside `get`, before the
//! requests after it leave.
//!
//! Nothing here runs on zenoh's thread: a caller waits for its replies, and zenoh's one
//! thread must stay free to deliver them (`Endpoint::blocking`).

use std::sync::{Arc, OnceLock};
use std::time::Duration;

use prost::Message;
use zenoh::handlers::FifoChannelHandler;
use zenoh::qos::CongestionControl;
use zenoh::query::{ConsolidationMode, QueryTarget, Reply};
use zenoh::sample::Locality;
use zenoh::Wait;

use crate::metrics::{scope_between, ServiceMetrics};
use crate::pb;
use crate::runtime::{declared, encoding, request_key, schema_of, Dispatcher, LocalEndpoints};
use crate::wirecheck::unknown_field;

/// Why a request got no usable reply (`NoReply`, `ReplyTimeout`, `RemoteError`).
#[derive(Debug, Clone, PartialEq)]
pub enum CallError {
    /// Nobody answered (no service on the key).
    NoReply,
    /// zenoh gave up waiting (after this many seconds).
    Timeout(f64),
    /// The peer refused (its ErrorReply), or its reply was not the message asked for.
    Remote { code: i32, message: String },
}

impl CallError {
    /// The `reason` label of `swarmrec_peer_failures_total`.
    pub fn reason(&self) -> &'static str {
        match self {
            CallError::NoReply => "no_reply",
            CallError::Timeout(_) => "timeout",
            CallError::Remote { .. } => "error",
        }
    }

    fn malformed(message: String) -> CallError {
        CallError::Remote {
            code: pb::ErrorCode::Malformed as i32,
            message,
        }
    }
}

impl std::fmt::Display for CallError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CallError::NoReply => write!(f, "no service answered"),
            CallError::Timeout(s) => write!(f, "no answer in {s} s"),
            CallError::Remote { code, message } => {
                let name = pb::ErrorCode::try_from(*code).map_or("UNKNOWN", |c| c.as_str_name());
                write!(f, "{name}: {message}")
            }
        }
    }
}

pub struct Caller {
    robot: u32,
    timeout: Duration,
    max_size: usize,
    metrics: Arc<ServiceMetrics>,
    local: Arc<LocalEndpoints>,
    session: OnceLock<zenoh::Session>,
}

enum Way {
    Remote(FifoChannelHandler<Reply>),
    Local {
        serve: Arc<Dispatcher>,
        payload: Vec<u8>,
        schema: String,
    },
    /// zenoh refused to send it (the session is closing).
    Unsent,
}

/// A request in flight; its replies are collected when asked for.
pub struct Pending<'a> {
    caller: &'a Caller,
    target: Option<u32>,
    endpoint: &'static str,
    way: Way,
}

/// A request to an endpoint of this process is served when its result is asked for; one
/// dropped unasked is still served (its reply unread), as zenoh would have delivered it.
impl Drop for Pending<'_> {
    fn drop(&mut self) {
        if let Way::Local { serve, payload, schema } = std::mem::replace(&mut self.way, Way::Unsent) {
            let _ = serve.serve_local(&payload, &schema, self.caller.robot);
        }
    }
}

/// One reply: its bytes, or why there is none.
pub type Outcome = Result<Vec<u8>, CallError>;

impl Caller {
    pub fn new(
        robot: u32,
        timeout: Duration,
        max_size: usize,
        metrics: Arc<ServiceMetrics>,
        local: Arc<LocalEndpoints>,
    ) -> Caller {
        Caller {
            robot,
            timeout,
            max_size,
            metrics,
            local,
            session: OnceLock::new(),
        }
    }

    pub fn attach(&self, session: &zenoh::Session) {
        let _ = self.session.set(session.clone());
    }

    fn scope(&self, target: Option<u32>) -> &'static str {
        scope_between(self.robot, target)
    }

    pub fn count_failure(&self, endpoint: &str, reason: &str) {
        self.metrics
            .registry
            .inc(self.metrics.peer_failures, &[endpoint, reason], 1.0);
    }

    /// Sends `request` (short schema name `schema`) to `key` and returns at once.
    /// `scatter` asks every matching service (no consolidation).
    pub fn start<M: Message>(
        &self,
        key: &str,
        schema: &'static str,
        request: &M,
        target: Option<u32>,
        endpoint: &'static str,
        scatter: bool,
    ) -> Pending<'_> {
        self.start_bytes(key, schema, request.encode_to_vec(), target, endpoint, scatter)
    }

    /// `start` with the request already serialized (a replaying detector's frames are).
    pub fn start_bytes(
        &self,
        key: &str,
        schema: &'static str,
        payload: Vec<u8>,
        target: Option<u32>,
        endpoint: &'static str,
        scatter: bool,
    ) -> Pending<'_> {
        self.metrics.count_sent(schema, self.scope(target), payload.len());
        let local = match target {
            Some(t) if !scatter => self.local.find(key, t),
            _ => None,
        };
        let way = if let Some(serve) = local {
            Way::Local {
                serve,
                payload,
                schema: format!("swarmrec.v1.{schema}"),
            }
        } else if let Some((session, key)) = self
            .session
            .get()
            // A caller-bound endpoint's request names its sender in the key (`CALLER_BOUND`).
            .and_then(|s| Some((s, declared(s, &request_key(key, self.robot))?)))
        {
            let mut get = session
                .get(key)
                .payload(payload)
                .encoding(encoding(schema))
                .attachment(self.robot.to_string())
                .timeout(self.timeout)
                .congestion_control(CongestionControl::Block);
            if scatter {
                get = get.target(QueryTarget::All).consolidation(ConsolidationMode::None);
            } else {
                // Every endpoint this process serves was found above (`LocalEndpoints`):
                // zenoh need not look for one in this session.
                get = get.allowed_destination(Locality::Remote);
            }
            get.wait().map_or(Way::Unsent, Way::Remote)
        } else {
            Way::Unsent
        };
        Pending {
            caller: self,
            target,
            endpoint,
            way,
        }
    }
}

impl Pending<'_> {
    /// Every reply (a scatter's), each checked to be `expected` (short schema name) or an
    /// ErrorReply; empty when nobody answered.
    pub fn gather(mut self, expected: &str) -> Vec<Outcome> {
        match std::mem::replace(&mut self.way, Way::Unsent) {
            Way::Unsent => Vec::new(),
            Way::Local { serve, payload, schema } => {
                let (name, data, ok) = serve.serve_local(&payload, &schema, self.caller.robot);
                vec![self.outcome(ok, data, &format!("swarmrec.v1.{name}"), expected)]
            }
            Way::Remote(replies) => {
                let mut out = Vec::new();
                while let Ok(reply) = replies.recv() {
                    out.push(match reply.result() {
                        Ok(s) => {
                            let data = s.payload().to_bytes().into_owned();
                            self.outcome(true, data, &schema_of(Some(s.encoding())), expected)
                        }
                        Err(e) => {
                            let data = e.payload().to_bytes().into_owned();
                            self.outcome(false, data, &schema_of(Some(e.encoding())), expected)
                        }
                    });
                }
                out
            }
        }
    }

    fn outcome(&self, ok: bool, data: Vec<u8>, schema: &str, expected: &str) -> Outcome {
        let c = self.caller;
        let scope = c.scope(self.target);
        let short = schema.rsplit('.').next().unwrap_or_default();
        if ok {
            c.metrics.count_received(short, scope, data.len());
            let full = format!("swarmrec.v1.{expected}");
            if !schema.is_empty() && schema != full {
                return Err(CallError::malformed(format!("expected {full}, got {schema}")));
            }
            if data.len() > c.max_size {
                return Err(CallError::malformed(format!(
                    "message of {} bytes exceeds the limit of {}",
                    data.len(),
                    c.max_size
                )));
            }
            if let Some(path) = unknown_field(&full, &data) {
                return Err(CallError::malformed(format!(
                    "{path} holds fields its schema does not have (another message's bytes?)"
                )));
            }
            return Ok(data);
        }
        if schema == "swarmrec.v1.ErrorReply" {
            c.metrics.count_received("ErrorReply", scope, data.len());
            return match pb::ErrorReply::decode(data.as_slice()) {
                Ok(e) => Err(CallError::Remote {
                    code: e.code,
                    message: e.message,
                }),
                Err(e) => Err(CallError::malformed(e.to_string())),
            };
        }
        // Not one of ours: zenoh's own error reply, whose only word for a timeout is its text.
        let text = String::from_utf8_lossy(&data);
        if text.to_lowercase().contains("timeout") {
            return Err(CallError::Timeout(c.timeout.as_secs_f64()));
        }
        Err(CallError::Remote {
            code: pb::ErrorCode::Unspecified as i32,
            message: text.chars().take(200).collect(),
        })
    }

    /// The one reply, decoded; a failure is counted by its reason.
    pub fn result<M: Message + Default>(self, expected: &str) -> Result<M, CallError> {
        let (caller, endpoint) = (self.caller, self.endpoint);
        let first = self.gather(expected).into_iter().next();
        let outcome = match first {
            None => Err(CallError::NoReply),
            Some(Ok(data)) => M::decode(data.as_slice()).map_err(|e| CallError::malformed(format!("{expected}: {e}"))),
            Some(Err(e)) => Err(e),
        };
        if let Err(e) = &outcome {
            caller.count_failure(endpoint, e.reason());
        }
        outcome
    }
}
