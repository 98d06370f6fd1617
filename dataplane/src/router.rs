//! The router, compiled: a zenoh session in router mode (the same routing runtime as
//! zenohd and as the Python router, `swarmrec/services/router.py`), which also counts
//! what it refuses, something the Python binding cannot see (docs/security.md):
//!
//! * **refused handshakes**: a TLS connection the router would not accept (no client
//!   certificate, one from another CA, expired, not yet valid, plaintext on a TLS port,
//!   a handshake that never ends). zenoh logs each such failure of its TLS listener as a
//!   warning and nothing else; the host's log callback hands them here
//!   ([`observe_zenoh_record`]), where each is counted by reason and logged as one
//!   budgeted line.
//! * **denied messages**: what the access control dropped, per certificate name and
//!   direction. zenoh counts these itself (its `stats` feature, the drop reason
//!   `access-control`, labelled by the remote certificate's common name); they are read
//!   from the router's own admin space every second (`follow_denials`), kept for sessions
//!   that have left.
//!
//! It has no endpoint of its own beyond `info`.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, OnceLock};

use zenoh::Wait;

use crate::metrics::{Metric, ServiceMetrics};
use crate::pb;
use crate::runtime::{lock, Endpoint, Log, Service};

/// What zenoh's TLS listener says when it drops a connection it accepted on TCP
/// (zenoh-link-tls 1.10, `accept_task`): the handshake failed, timed out or the client was
/// not one the server verifier accepts. The hint is zenoh's, for the other cause of the
/// same branch (out of file descriptors).
const TLS_ACCEPT_FAILED: &str = "Hint: increase the system open file limit";
/// zenoh-link-tls's words for an accepted handshake whose certificate names no one.
const TLS_NO_NAME: &str = "Error getting client cert common name";

/// Refused handshakes by reason, counted from zenoh's log records (any thread).
static REFUSED: Mutex<BTreeMap<&'static str, u64>> = Mutex::new(BTreeMap::new());
/// The router's log, once it serves (refusals are logged as its own budgeted lines).
static ROUTER_LOG: OnceLock<Log> = OnceLock::new();

/// The reason a TLS handshake failed, from the error's text (rustls' and tls-listener's
/// words): a short, closed set, so that the label's values stay few.
pub fn handshake_reason(text: &str) -> &'static str {
    let t = text.to_ascii_lowercase();
    if t.contains("unknownissuer") || t.contains("unknown issuer") || t.contains("badsignature") {
        "unknown_issuer"
    } else if t.contains("notvalidyet") || t.contains("not valid yet") {
        "not_yet_valid"
    } else if t.contains("expired") {
        "expired"
    } else if t.contains("no certificates") || t.contains("nocertificatespresented") {
        "no_certificate"
    } else if t.contains("timed out") || t.contains("timeout") || t.contains("elapsed") {
        "timeout"
    } else if t.contains("corrupt message") || t.contains("invalidcontenttype") || t.contains("invalid content") {
        "not_tls"
    } else if t.contains("received fatal alert") {
        // The client gave up: it did not trust the router's certificate (another CA's client).
        "client_aborted"
    } else if t.contains("certificate") || t.contains("cert") {
        "bad_certificate"
    } else if t.contains("too many open files") {
        "out_of_files"
    } else {
        "other"
    }
}

/// Whether a zenoh log record is a refused handshake; if so it is counted (and logged as
/// the router's own line) and zenoh's own line should not be written: its text carries
/// the peer's details, so one line per attacker connection would escape the log budget.
pub fn observe_zenoh_record(target: &str, message: &str) -> bool {
    if !target.starts_with("zenoh_link_tls") {
        return false;
    }
    let reason = if message.contains(TLS_ACCEPT_FAILED) {
        handshake_reason(message)
    } else if message.contains(TLS_NO_NAME) {
        "no_common_name"
    } else {
        return false;
    };
    *lock(&REFUSED).entry(reason).or_insert(0) += 1;
    if let Some(log) = ROUTER_LOG.get() {
        // One text for every refusal: the log's budget (20 a text per 10 s) bounds them.
        log.warning(
            "refused a TLS handshake",
            serde_json::json!({"reason": reason, "detail": message.chars().take(200).collect::<String>()}),
        );
    }
    true
}

/// One access-control drop count from zenoh's metrics text (OpenMetrics, as the admin
/// space's `router/metrics` writes it with `stats`): `(identity, direction, message, count)`.
/// zenoh keeps a histogram of dropped payload sizes per transport,
/// `zenoh_<rx|tx>_network_message_dropped_payload_per_transport_bytes`, labelled with the drop
/// `reason`, the message type and the remote's certificate name (`remote_cn`); its `_count`
/// is the number of messages.
pub fn access_control_drop(line: &str) -> Option<(String, &'static str, String, f64)> {
    if line.starts_with('#') || !line.contains("reason=\"access-control\"") {
        return None;
    }
    let (head, value) = line.rsplit_once(' ')?;
    let name = head.split('{').next()?;
    let direction = match name {
        "zenoh_rx_network_message_dropped_payload_per_transport_bytes_count" => "received",
        "zenoh_tx_network_message_dropped_payload_per_transport_bytes_count" => "sent",
        _ => return None,
    };
    let identity = label(head, "remote_cn")
        .filter(|cn| !cn.is_empty())
        .unwrap_or_else(|| "(no certificate)".to_string());
    let message = label(head, "message").unwrap_or_default();
    let count = value.trim().parse::<f64>().ok()?;
    Some((identity, direction, message, count))
}

/// The value of label `name` in a metric line's label set, unescaped (quotes and backslashes).
fn label(head: &str, name: &str) -> Option<String> {
    let start = head.find(&format!("{name}=\""))? + name.len() + 2;
    let mut out = String::new();
    let mut chars = head[start..].chars();
    while let Some(c) = chars.next() {
        match c {
            '\\' => out.push(chars.next()?),
            '"' => return Some(out),
            c => out.push(c),
        }
    }
    None
}

pub struct Router {
    metrics: Arc<ServiceMetrics>,
    refused_handshakes: Metric,
    denied_messages: Metric,
    session: OnceLock<zenoh::Session>,
    log: Log,
}

impl Router {
    pub fn new(metrics: Arc<ServiceMetrics>, log: Log) -> Router {
        let refused_handshakes = metrics.registry.counter(
            "swarmrec_router_refused_handshakes",
            "TLS connections the router refused during the handshake, by reason",
            &["reason"],
        );
        let denied_messages = metrics.registry.counter(
            "swarmrec_router_denied_messages",
            "Messages the access control dropped, by the certificate's name, direction (received from it, \
             or not sent to it) and zenoh message type",
            &["identity", "direction", "message"],
        );
        Router {
            metrics,
            refused_handshakes,
            denied_messages,
            session: OnceLock::new(),
            log,
        }
    }

    /// Where the router listens, as zenoh bound it (a port 0 replaced by the OS's), from
    /// its own admin space, as the Python runner's `router_locators` reads it.
    pub fn locators(&self) -> Vec<String> {
        self.admin_json("router")
            .and_then(|v| v.get("locators").cloned())
            .and_then(|v| serde_json::from_value::<Vec<String>>(v).ok())
            .unwrap_or_default()
    }

    fn admin(&self, selector: &str) -> Option<Vec<u8>> {
        let session = self.session.get()?;
        let zid = session.zid();
        let replies = session
            .get(format!("@/{zid}/{selector}"))
            .timeout(std::time::Duration::from_secs(2))
            .wait()
            .ok()?;
        while let Ok(reply) = replies.recv() {
            if let Ok(sample) = reply.result() {
                return Some(sample.payload().to_bytes().into_owned());
            }
        }
        None
    }

    fn admin_json(&self, selector: &str) -> Option<serde_json::Value> {
        serde_json::from_slice(&self.admin(selector)?).ok()
    }
}

impl Service for Router {
    fn endpoints(self: Arc<Self>) -> Vec<Endpoint> {
        Vec::new()
    }

    fn member_info(&self) -> pb::MemberInfo {
        pb::MemberInfo::default()
    }

    fn attach(&self, session: &zenoh::Session) -> anyhow::Result<()> {
        let _ = self.session.set(session.clone());
        let _ = ROUTER_LOG.set(self.log.clone());
        Ok(())
    }

    /// The refused handshakes counted so far. zenoh's drop counters are copied by the
    /// router's own thread ([`Router::follow_denials`]), never while a scrape or a probe
    /// waits: the metrics endpoint serves one request at a time, and the probes use it too.
    fn refresh_metrics(&self) {
        for (reason, n) in lock(&REFUSED).iter() {
            self.metrics.registry.set(self.refused_handshakes, &[reason], *n as f64);
        }
    }
}

impl Router {
    /// Copies zenoh's access-control drops into the registry every `every`, on a thread of
    /// its own, until the process ends.
    pub fn follow_denials(self: &Arc<Self>, every: std::time::Duration) {
        let me = Arc::downgrade(self);
        let _ = std::thread::Builder::new()
            .name("router-denials".into())
            .spawn(move || {
                while let Some(router) = me.upgrade() {
                    router.copy_denials();
                    drop(router);
                    std::thread::sleep(every);
                }
            });
    }

    /// zenoh's access-control drops as they are now (sessions that left included).
    fn copy_denials(&self) {
        let registry = &self.metrics.registry;
        // zenoh's selector parameters are separated by `;`.
        let selector = "router/metrics?compression=false;descriptors=false;per_key=false;per_link=false;\
                        disconnected=true";
        let Some(text) = self.admin(selector) else { return };
        let mut denied: BTreeMap<(String, &'static str, String), f64> = BTreeMap::new();
        for line in String::from_utf8_lossy(&text).lines() {
            if let Some((identity, direction, message, n)) = access_control_drop(line) {
                // Summed over priorities and over the sessions of one name (a client that
                // reconnects keeps its count).
                *denied.entry((identity, direction, message)).or_insert(0.0) += n;
            }
        }
        for ((identity, direction, message), n) in denied {
            registry.set(self.denied_messages, &[&identity, direction, &message], n);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reasons_of_rustls_errors() {
        let cases = [
            ("invalid peer certificate: UnknownIssuer. Hint: ...", "unknown_issuer"),
            ("invalid peer certificate: Expired. Hint", "expired"),
            ("invalid peer certificate: ExpiredContext { time: .. }", "expired"),
            ("invalid peer certificate: NotValidYet", "not_yet_valid"),
            ("peer sent no certificates", "no_certificate"),
            ("received corrupt message of type InvalidContentType", "not_tls"),
            ("TLS handshake timed out", "timeout"),
            ("received fatal alert: DecryptError. Hint", "client_aborted"),
            ("something else entirely", "other"),
        ];
        for (text, reason) in cases {
            assert_eq!(handshake_reason(text), reason, "{text}");
        }
    }

    #[test]
    fn access_control_drops_by_identity_and_direction() {
        // Lines as zenoh 1.10.2 writes them (seen from a router with a denied put).
        let rx = r#"zenoh_rx_network_message_dropped_payload_per_transport_bytes_count{local_id="41",local_whatami="router",priority="data",message="put",protocol="",reason="access-control",remote_zid="1d",remote_whatami="client",remote_group="",remote_cn="r1.verifier.probe",disconnected="true"} 5"#;
        assert_eq!(
            access_control_drop(rx),
            Some(("r1.verifier.probe".to_string(), "received", "put".to_string(), 5.0))
        );
        let tx = r#"zenoh_tx_network_message_dropped_payload_per_transport_bytes_count{message="query",reason="access-control",remote_cn="a\"b"} 2"#;
        assert_eq!(
            access_control_drop(tx),
            Some(("a\"b".to_string(), "sent", "query".to_string(), 2.0))
        );
        let plain = r#"zenoh_rx_network_message_dropped_payload_per_transport_bytes_count{message="put",reason="access-control",remote_cn=""} 1"#;
        assert_eq!(
            access_control_drop(plain).map(|d| d.0),
            Some("(no certificate)".to_string())
        );
        // Not counted: the totals over transports (the same drops again), another reason,
        // the histogram's other series, descriptors.
        for line in [
            r#"zenoh_rx_network_message_dropped_payload_bytes_count{message="put",reason="access-control"} 5"#,
            r#"zenoh_tx_network_message_dropped_payload_per_transport_bytes_count{reason="congestion",remote_cn="x"} 2"#,
            r#"zenoh_rx_network_message_dropped_payload_per_transport_bytes_sum{reason="access-control",remote_cn="x"} 9.0"#,
            "# HELP zenoh_rx_network_message_dropped_payload_per_transport_bytes reason=\"access-control\"",
        ] {
            assert_eq!(access_control_drop(line), None, "{line}");
        }
    }

    #[test]
    fn only_tls_accept_failures_are_refusals() {
        assert!(!observe_zenoh_record("zenoh_transport::unicast", TLS_ACCEPT_FAILED));
        assert!(!observe_zenoh_record("zenoh_link_tls::unicast", "Closing TLS link"));
        let before = lock(&REFUSED).get("unknown_issuer").copied().unwrap_or(0);
        assert!(observe_zenoh_record(
            "zenoh_link_tls::unicast",
            "invalid peer certificate: UnknownIssuer. Hint: increase the system open file limit."
        ));
        assert_eq!(lock(&REFUSED).get("unknown_issuer").copied(), Some(before + 1));
    }
}
