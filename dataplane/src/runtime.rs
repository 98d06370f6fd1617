//! The compiled runner: what `swarmrec/runtime/runner.py` does for a Python service,
//! on one zenoh session per process with requests served in zenoh's callback.
//!
//! There is no thread hand-off per message: a query is checked, decoded, handled,
//! answered and counted on the zenoh thread that received it (with the
//! single-threaded zenoh runtime, the process's one runtime thread). A handler's
//! work is bounded by the hostile-input limits before it starts, so it never blocks
//! that thread for long.
//!
//! The contract is the Python runner's, and the behaviour tests run against both:
//! keys `swarmrec/v1/<swarm>/<kind>/<robot>/<endpoint>`, replies on the service's own
//! key with the encoding `application/protobuf;swarmrec.v1.<Reply>`, refusals as an
//! `ErrorReply` error reply with the same codes, bytes counted by message type and
//! scope, every refusal counted in `swarmrec_rejected_requests_total`, the `info`
//! endpoint, and the liveliness token declared last and dropped first.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use prost::Message;
use zenoh::bytes::{Encoding, ZBytes};
use zenoh::query::Query;
use zenoh::Wait;

use crate::metrics::{scope_between, ServiceMetrics};
use crate::pb;
use crate::wirecheck::unknown_field;

/// Key of a service's endpoint, `swarmrec/v1/<swarm>/<kind>/<robot>/<endpoint>`
/// (`swarmrec.runtime.keys.endpoint`).
pub fn endpoint_key(swarm: &str, kind: &str, robot: u32, name: &str) -> String {
    format!("swarmrec/v1/{swarm}/{kind}/{robot}/{name}")
}

/// Endpoints that act for the robot that calls them (`keys.CALLER_BOUND` in Python): a
/// request to one goes to `<endpoint key>/<caller's robot>`, which the router's access
/// control lets each certificate use with its own robot(s) only, and the service takes
/// the caller from the key, not from the attachment.
pub const CALLER_BOUND: [(&str, &str); 7] = [
    ("index-shard", "query"),
    ("index-shard", "store"),
    ("index-shard", "adopt"),
    ("place-owner", "query"),
    ("place-owner", "store_copy"),
    ("place-owner", "adopt_table"),
    ("place-owner", "store_entries"),
];

/// Whether `kind`'s endpoint `name` takes its caller from the key.
pub fn caller_bound(kind: &str, name: &str) -> bool {
    CALLER_BOUND.contains(&(kind, name))
}

/// The key a request to endpoint `key` goes to: with the caller's robot appended when the
/// endpoint is caller-bound.
pub fn request_key(key: &str, caller: u32) -> String {
    let parts: Vec<&str> = key.split('/').collect();
    if parts.len() == 6 && caller_bound(parts[3], parts[5]) {
        format!("{key}/{caller}")
    } else {
        key.to_string()
    }
}

/// The caller's robot a caller-bound request's key names (its seventh chunk).
pub fn bound_caller(key: &str) -> Option<u32> {
    let parts: Vec<&str> = key.split('/').collect();
    robot_id(parts.get(6).filter(|_| parts.len() == 7)?.as_bytes())
}

/// A robot id written in decimal digits (at most 10, within u32), as a request's key or
/// attachment names its sender; None for anything else.
fn robot_id(raw: &[u8]) -> Option<u32> {
    if raw.is_empty() || raw.len() > 10 || !raw.iter().all(u8::is_ascii_digit) {
        return None;
    }
    std::str::from_utf8(raw)
        .ok()?
        .parse::<u64>()
        .ok()
        .and_then(|r| u32::try_from(r).ok())
}

/// At most this many key expressions are declared (a swarm's endpoints: robots x a few);
/// past it, keys are sent as strings.
const DECLARED_KEYS: usize = 4096;

/// `key`, declared to the router once per process (one session a process), for the
/// requests and events this process sends.
///
/// Why: a query on a key no one declared is routed by matching it against the router's
/// whole key tree, every time (`Resource::get_matches`); a declared key has a resource
/// whose route the router computes once and keeps. The services declare one queryable
/// per service (`.../<robot>/*`, routes.rs), so only their callers and publishers can
/// make the keys they use. It also puts a number on the wire instead of the key.
pub fn declared(session: &zenoh::Session, key: &str) -> Option<zenoh::key_expr::KeyExpr<'static>> {
    type Keys = Mutex<HashMap<String, zenoh::key_expr::KeyExpr<'static>>>;
    static KEYS: OnceLock<Keys> = OnceLock::new();
    let mut keys = lock(KEYS.get_or_init(Keys::default));
    if let Some(k) = keys.get(key) {
        return Some(k.clone());
    }
    if keys.len() < DECLARED_KEYS {
        if let Ok(k) = session.declare_keyexpr(key.to_owned()).wait() {
            keys.insert(key.to_owned(), k.clone());
            return Some(k);
        }
    }
    // Not declared (too many keys, or the session is closing): the string goes; None for
    // a string that is no key (the request is then not sent, as `get` refused it before).
    zenoh::key_expr::KeyExpr::try_from(key.to_owned()).ok()
}

/// Key of a service's liveliness token, `swarmrec/v1/<swarm>/alive/<kind>/<robot>`
/// (`swarmrec.runtime.keys.alive`).
pub fn alive_key(swarm: &str, kind: &str, robot: u32) -> String {
    format!("swarmrec/v1/{swarm}/alive/{kind}/{robot}")
}

/// A liveliness subscriber on `swarmrec/v1/<swarm>/<what>/<kind>/*` (the tokens already
/// declared too) calling `on(robot, declared)` for each token that comes or goes; it lives
/// as long as the returned handle.
pub fn watch_tokens(
    session: &zenoh::Session,
    swarm: &str,
    what: &str,
    kind: &str,
    on: impl Fn(u32, bool) + Send + Sync + 'static,
) -> anyhow::Result<Box<dyn std::any::Any + Send>> {
    let key = format!("swarmrec/v1/{swarm}/{what}/{kind}/*");
    let sub = session
        .liveliness()
        .declare_subscriber(&key)
        .history(true)
        .callback(move |sample| {
            let id = sample
                .key_expr()
                .as_str()
                .rsplit('/')
                .next()
                .and_then(|s| s.parse::<u32>().ok());
            if let Some(id) = id {
                on(id, sample.kind() == zenoh::sample::SampleKind::Put);
            }
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("liveliness subscriber {key}: {e}"))?;
    Ok(Box::new(sub))
}

/// Locks `m`, and still when another thread panicked holding it: what it guards is kept
/// consistent at every step, and a handler's panic is answered INTERNAL, not fatal.
pub fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// A refusal: the `swarmrec.v1.ErrorCode` to answer with, and why.
#[derive(Debug, Clone)]
pub struct RequestError {
    pub code: pb::ErrorCode,
    pub message: String,
}

impl RequestError {
    pub fn new(code: pb::ErrorCode, message: impl Into<String>) -> RequestError {
        RequestError {
            code,
            message: message.into(),
        }
    }
    pub fn invalid(message: impl Into<String>) -> RequestError {
        RequestError::new(pb::ErrorCode::InvalidArgument, message)
    }
    pub fn too_large(what: &str, value: u64, limit: u64, setting: &str) -> RequestError {
        RequestError::new(
            pb::ErrorCode::TooLarge,
            format!("{what}: {value}, more than the limit of {limit} (setting {setting})"),
        )
    }
}

pub type Handled = Result<(&'static str, Vec<u8>), RequestError>;

/// A request's handler: (payload, caller's robot) -> the reply's short schema name and bytes.
pub type Handler = Box<dyn Fn(&[u8], Option<u32>) -> Handled + Send + Sync>;

/// One endpoint: its name, the request's short schema name, and the handler
/// (payload, caller's robot) -> (reply's short schema name, reply bytes).
pub struct Endpoint {
    pub name: &'static str,
    pub request: &'static str,
    pub handler: Handler,
    /// The handler waits on peers (a descriptor's two-step query): it is served on a
    /// thread of its own, never on zenoh's, whose one thread must stay free to receive
    /// the replies it waits for.
    pub blocking: bool,
}

/// A compiled service, as the runner drives it.
pub trait Service: Send + Sync {
    fn endpoints(self: Arc<Self>) -> Vec<Endpoint>;
    /// What the service says of itself beyond kind, robot, version and swarm.
    fn member_info(&self) -> pb::MemberInfo;
    /// Called once the session is open, before the endpoints are declared: a service
    /// that asks peers or watches liveliness keeps the session.
    fn attach(&self, _session: &zenoh::Session) -> anyhow::Result<()> {
        Ok(())
    }
    /// Called once the service serves (token declared): a descriptor learns the swarm's
    /// placement and starts retrying its pending stores.
    fn serving(self: Arc<Self>) {}
    /// Called on SIGTERM while the service still serves (token and endpoints up): an index
    /// shard hands its groups on first.
    fn drain(&self) {}
    /// Called after the endpoints are gone, before the session closes.
    fn close(&self) {}
    /// Called when Prometheus scrapes, before the page is written: a service whose
    /// counters live elsewhere (the router's, in zenoh) copies them into its registry.
    fn refresh_metrics(&self) {}
}

/// Decodes `data` as `M` (`schema` its full name): MALFORMED when it does not parse or
/// holds fields the schema lacks, as the Python runner's decode and `check_fields` do.
pub fn decode<M: Message + Default>(data: &[u8], schema: &str) -> Result<M, RequestError> {
    let msg = M::decode(data).map_err(|e| {
        RequestError::new(
            pb::ErrorCode::Malformed,
            format!("{} bytes do not decode as {schema}: {e}", data.len()),
        )
    })?;
    if let Some(path) = unknown_field(schema, data) {
        return Err(RequestError::new(
            pb::ErrorCode::Malformed,
            format!("{path} holds fields its schema does not have (another message's bytes?)"),
        ));
    }
    Ok(msg)
}

/// A required field's absence (proto3 reads it as 0), as `MissingFieldError` says it.
pub fn missing(message: &str, field: &str) -> RequestError {
    RequestError::invalid(format!("{message} has no {field}; it is required"))
}

pub fn error_name(code: pb::ErrorCode) -> &'static str {
    code.as_str_name()
}

/// CPU time of the calling thread, seconds.
pub fn thread_cpu_s() -> f64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes the timespec we pass and nothing else.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// Warnings of one text logged at most this many times a window (`WARNING_WINDOW`), as the
/// Python runner's `WarningBudget`: a flood of refused input is counted in full by the
/// metrics and must not also be a log line each.
pub const WARNING_BURST: u32 = 20;
pub const WARNING_WINDOW: Duration = Duration::from_secs(10);

/// Per message text: (window start, let through in it, dropped since the last let through).
type Budget = HashMap<String, (Instant, u32, u64)>;

/// JSON lines on stderr, the Python services' log format.
#[derive(Clone)]
pub struct Log {
    pub kind: String,
    pub robot: u32,
    pub level: u8,
    budget: Arc<Mutex<Budget>>,
}

impl Log {
    pub fn new(kind: &str, robot: u32, level: &str) -> Log {
        let level = match level.to_ascii_uppercase().as_str() {
            "DEBUG" => 10,
            "WARNING" => 30,
            "ERROR" => 40,
            _ => 20,
        };
        Log {
            kind: kind.to_string(),
            robot,
            level,
            budget: Arc::default(),
        }
    }

    /// Whether a warning of text `msg` may be logged now, and how many like it were not
    /// since the last one that was.
    fn within_budget(&self, msg: &str) -> Option<u64> {
        let now = Instant::now();
        let mut seen = lock(&self.budget);
        if seen.len() > 1024 && !seen.contains_key(msg) {
            seen.clear(); // texts are few; a runaway set of them is dropped
        }
        let entry = seen.entry(msg.to_string()).or_insert((now, 0, 0));
        if now.duration_since(entry.0) >= WARNING_WINDOW {
            entry.0 = now;
            entry.1 = 0;
        }
        if entry.1 >= WARNING_BURST {
            entry.2 += 1;
            return None;
        }
        entry.1 += 1;
        Some(std::mem::take(&mut entry.2))
    }

    pub fn emit(&self, level: u8, msg: &str, mut fields: serde_json::Value) {
        if level < self.level {
            return;
        }
        if level == 30 {
            match self.within_budget(msg) {
                None => return,
                Some(0) => {}
                Some(dropped) => {
                    if let serde_json::Value::Object(f) = &mut fields {
                        f.insert("not_logged".into(), dropped.into());
                    }
                }
            }
        }
        let name = match level {
            10 => "DEBUG",
            30 => "WARNING",
            40 => "ERROR",
            _ => "INFO",
        };
        let ts = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        let mut entry = serde_json::json!({
            "ts": (ts * 1000.0).round() / 1000.0, "level": name, "service": self.kind,
            "robot": self.robot, "msg": msg,
        });
        if let (Some(e), serde_json::Value::Object(extra)) = (entry.as_object_mut(), fields) {
            e.extend(extra);
        }
        eprintln!("{entry}");
    }

    pub fn info(&self, msg: &str, fields: serde_json::Value) {
        self.emit(20, msg, fields);
    }
    pub fn warning(&self, msg: &str, fields: serde_json::Value) {
        self.emit(30, msg, fields);
    }
}

/// The caller's robot id from a query's attachment (decimal digits, at most 10);
/// None for a client outside the swarm.
pub fn caller_robot(attachment: Option<&ZBytes>) -> Option<u32> {
    robot_id(&attachment?.to_bytes())
}

pub fn schema_of(encoding: Option<&Encoding>) -> String {
    let text = encoding.map(|e| e.to_string()).unwrap_or_default();
    text.split_once(';').map(|(_, s)| s.to_string()).unwrap_or_default()
}

pub fn encoding(short: &str) -> Encoding {
    Encoding::APPLICATION_PROTOBUF.with_schema(format!("swarmrec.v1.{short}"))
}

/// Everything one endpoint's callback needs.
pub struct Dispatcher {
    pub endpoint: Endpoint,
    /// The service's own key of this endpoint: replies go out on it, never on the
    /// query's (maybe wildcard) key, since the router lets a robot reply on its own keys only.
    pub key: String,
    /// `key` declared to the router (`declared`): replies name it by number.
    pub reply_key: Option<zenoh::key_expr::KeyExpr<'static>>,
    pub robot: u32,
    pub max_message_bytes: usize,
    pub metrics: Arc<ServiceMetrics>,
    pub log: Log,
    /// The caller is the robot the request's key names (`CALLER_BOUND`); the reply goes
    /// out on the request's own key, declared (`declared`) the first time.
    pub bound: bool,
    /// The session the replies go out on (to declare a caller-bound request's key).
    pub session: zenoh::Session,
}

impl Dispatcher {
    /// Who sent a request on `key` (None: a call from this process, whose caller is
    /// given): the attachment's robot, or for a caller-bound endpoint the key's, which the
    /// router checked against the sender's certificate (an attachment that says otherwise
    /// is refused).
    fn caller(&self, key: Option<&str>, claimed: Option<u32>) -> Result<Option<u32>, RequestError> {
        let Some(key) = key.filter(|_| self.bound) else {
            return Ok(claimed);
        };
        let denied = |m: String| RequestError::new(pb::ErrorCode::PermissionDenied, m);
        let Some(named) = bound_caller(key) else {
            return Err(denied(format!(
                "{} takes its caller from the key: send it to {}/<robot>",
                self.endpoint.name, self.key
            )));
        };
        match claimed {
            Some(c) if c != named => Err(denied(format!(
                "the request's key names robot {named} as its sender, its attachment {c}"
            ))),
            _ => Ok(Some(named)),
        }
    }

    fn answer(&self, data: &[u8], schema: &str, caller: Option<u32>, key: Option<&str>, scope: &str) -> Handled {
        // Who sent it, first: as the Python runner, a request that names no caller or another
        // one is refused before anything else is read.
        let caller = self.caller(key, caller)?;
        let ep = &self.endpoint;
        self.metrics.count_received(ep.request, scope, data.len());
        let expected = format!("swarmrec.v1.{}", ep.request);
        if !schema.is_empty() && schema != expected {
            return Err(RequestError::invalid(format!(
                "{} takes {expected}, got {schema}",
                ep.name
            )));
        }
        if data.len() > self.max_message_bytes {
            return Err(RequestError::new(
                pb::ErrorCode::TooLarge,
                format!(
                    "message of {} bytes exceeds the limit of {}",
                    data.len(),
                    self.max_message_bytes
                ),
            ));
        }
        (ep.handler)(data, caller)
    }

    /// Serves one query on the calling thread; never panics the runtime: a handler's
    /// panic is answered INTERNAL.
    pub fn serve(&self, query: Query) {
        let (t0, c0) = (Instant::now(), thread_cpu_s());
        let caller = caller_robot(query.attachment());
        let scope = scope_between(self.robot, caller);
        let data = query.payload().map(|p| p.to_bytes().into_owned()).unwrap_or_default();
        let schema = schema_of(query.encoding());
        let (name, payload, ok) = self.handle(&data, &schema, caller, Some(query.key_expr().as_str()), scope);
        let size = payload.len();
        let sent = if ok {
            match &self.reply_key {
                // A caller-bound request is answered on its own key (the caller in it), which
                // the service's certificate may reply on (`<kind>/<robot>/**`).
                _ if self.bound => match declared(&self.session, query.key_expr().as_str()) {
                    Some(key) => query.reply(key, payload),
                    None => query.reply(query.key_expr().clone(), payload),
                },
                Some(key) => query.reply(key.clone(), payload),
                None => query.reply(&self.key, payload),
            }
            .encoding(encoding(name))
            .wait()
        } else {
            query.reply_err(payload).encoding(encoding(name)).wait()
        };
        if sent.is_ok() {
            self.metrics.count_sent(name, scope, size);
        }
        drop(query); // finishes the query: the caller need not wait for its timeout
        self.observe(t0, c0);
    }

    /// Refuses `query` at once (UNAVAILABLE): `queued` requests wait for this endpoint's thread.
    pub fn refuse_busy(&self, query: Query, queued: usize) {
        let caller = caller_robot(query.attachment());
        let scope = scope_between(self.robot, caller);
        let size = query.payload().map_or(0, |p| p.len());
        self.metrics.count_received(self.endpoint.request, scope, size);
        let code = error_name(pb::ErrorCode::Unavailable);
        let m = &self.metrics;
        m.registry.inc(m.rejected, &[self.endpoint.name, code], 1.0);
        let payload = pb::ErrorReply {
            code: pb::ErrorCode::Unavailable as i32,
            message: format!(
                "{queued} requests are waiting for {}: try again later",
                self.endpoint.name
            ),
        }
        .encode_to_vec();
        let size = payload.len();
        if query.reply_err(payload).encoding(encoding("ErrorReply")).wait().is_ok() {
            self.metrics.count_sent("ErrorReply", scope, size);
        }
    }

    /// A call from a service of the same robot in this process (`LocalEndpoints`), served
    /// on the caller's thread: (reply's short schema name, bytes, a reply or an ErrorReply).
    pub fn serve_local(&self, data: &[u8], schema: &str, caller: u32) -> (&'static str, Vec<u8>, bool) {
        let (t0, c0) = (Instant::now(), thread_cpu_s());
        let scope = scope_between(self.robot, Some(caller));
        let (name, payload, ok) = self.handle(data, schema, Some(caller), None, scope);
        self.metrics.count_sent(name, scope, payload.len());
        self.observe(t0, c0);
        (name, payload, ok)
    }

    fn observe(&self, t0: Instant, c0: f64) {
        let m = &self.metrics;
        m.registry
            .observe(m.request_seconds, &[self.endpoint.name], t0.elapsed().as_secs_f64());
        let cpu = thread_cpu_s() - c0;
        m.registry.inc(m.request_cpu_seconds, &[self.endpoint.name], cpu);
        m.add_cost(self.endpoint.name, cpu);
    }

    /// The reply to one request: (short schema name, bytes, a reply or an ErrorReply).
    fn handle(
        &self,
        data: &[u8],
        schema: &str,
        caller: Option<u32>,
        key: Option<&str>,
        scope: &str,
    ) -> (&'static str, Vec<u8>, bool) {
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            self.answer(data, schema, caller, key, scope)
        }))
        .unwrap_or_else(|_| Err(RequestError::new(pb::ErrorCode::Internal, "the handler panicked")));
        match outcome {
            Ok((name, payload)) => (name, payload, true),
            Err(e) => {
                let code = error_name(e.code);
                let m = &self.metrics;
                m.registry.inc(m.rejected, &[self.endpoint.name, code], 1.0);
                let mut reason = e.message.clone();
                reason.truncate(300);
                let fields = serde_json::json!({"endpoint": self.endpoint.name, "code": code, "sender": caller, "reason": reason});
                if e.code == pb::ErrorCode::Internal {
                    self.log.emit(40, "handler failed", fields);
                } else {
                    self.log.warning("rejected request", fields);
                }
                let mut message = e.message;
                if message.chars().count() > 1000 {
                    message = message.chars().take(999).collect::<String>() + "…";
                }
                (
                    "ErrorReply",
                    pb::ErrorReply {
                        code: e.code as i32,
                        message,
                    }
                    .encode_to_vec(),
                    false,
                )
            }
        }
    }
}

/// The endpoints this process serves, by key, for calls that stay in the process
/// (`LocalEndpoints` of the Python runner): a descriptor's calls to its own robot's
/// verifier and shard, and to those of the robots hosted beside it, are served on its
/// thread, with no message.
#[derive(Default)]
pub struct LocalEndpoints {
    served: std::sync::Mutex<std::collections::HashMap<String, (u32, Arc<Dispatcher>)>>,
}

impl LocalEndpoints {
    pub fn add(&self, key: &str, robot: u32, d: Arc<Dispatcher>) {
        let mut served = lock(&self.served);
        served.insert(key.to_string(), (robot, d));
    }

    pub fn clear(&self) {
        lock(&self.served).clear();
    }

    /// The endpoint at `key` when it belongs to `robot`.
    pub fn find(&self, key: &str, robot: u32) -> Option<Arc<Dispatcher>> {
        let served = lock(&self.served);
        served.get(key).filter(|(r, _)| *r == robot).map(|(_, d)| d.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warnings_of_one_text_are_logged_at_a_bounded_rate() {
        let log = Log::new("verifier", 3, "INFO");
        let passed = (0..1500)
            .filter(|_| log.within_budget("rejected request").is_some())
            .count();
        assert_eq!(passed, WARNING_BURST as usize);
        assert_eq!(log.within_budget("another text"), Some(0));
        // The next window's first says how many were not logged.
        lock(&log.budget).get_mut("rejected request").unwrap().0 -= WARNING_WINDOW;
        assert_eq!(
            log.within_budget("rejected request"),
            Some(1500 - u64::from(WARNING_BURST))
        );
        assert_eq!(log.within_budget("rejected request"), Some(0));
    }

    #[test]
    fn a_request_to_a_caller_bound_endpoint_names_its_sender_last() {
        let store = endpoint_key("lab", "index-shard", 3, "store");
        assert_eq!(request_key(&store, 2), "swarmrec/v1/lab/index-shard/3/store/2");
        let verify = endpoint_key("lab", "verifier", 3, "verify");
        assert_eq!(request_key(&verify, 2), verify);
        assert_eq!(bound_caller(&request_key(&store, 2)), Some(2));
        for key in [
            store.clone(),
            format!("{store}/x"),
            format!("{store}/2/3"),
            format!("{store}/*"),
            format!("{store}/99999999999"),
        ] {
            assert_eq!(bound_caller(&key), None, "{key}");
        }
        // The same endpoints as the Python services' keys.CALLER_BOUND.
        assert!(caller_bound("index-shard", "adopt") && caller_bound("place-owner", "query"));
        assert!(!caller_bound("index-shard", "lookup") && !caller_bound("verifier", "store"));
    }
}
