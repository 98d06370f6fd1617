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
//! * **bytes on each link to another router** (the mesh topology, docs/mesh.md): zenoh's
//!   own transport counters (`zenoh_{tx,rx}_per_transport_bytes_total`, relayed traffic
//!   included), summed by the neighbour's certificate name and kept for links that closed,
//!   read with the access-control drops.
//! * **bytes of each message type on each link to another router**: zenoh's per-key payload
//!   histograms (`zenoh_{tx,rx}_network_message_payload_per_key_per_transport_bytes_sum`,
//!   for the key expressions of the bus setting `stats_keys`, one per message type), summed
//!   by neighbour, direction, key and zenoh message (query, reply, put); read only for the
//!   page `<metrics>/keys`, which a mesh's deployment reads while its links do not change.
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

/// A line of zenoh's per-transport byte counters for a link to another router:
/// `(peer, direction, bytes)`, the peer named by its certificate (`remote_cn`), or by its
/// zenoh id where it presented none (an insecure swarm).
pub fn router_link_bytes(line: &str) -> Option<(String, &'static str, f64)> {
    let (peer, direction, _head, value) = router_line(
        line,
        "zenoh_tx_per_transport_bytes_total",
        "zenoh_rx_per_transport_bytes_total",
    )?;
    Some((peer, direction, value))
}

/// A line of the metric `tx` or `rx` (by name) about a link to another router:
/// `(peer, direction, head, value)`, the peer named by its certificate (`remote_cn`), or
/// by its zenoh id where it presented none.
fn router_line<'a>(line: &'a str, tx: &str, rx: &str) -> Option<(String, &'static str, &'a str, f64)> {
    if line.starts_with('#') || !line.contains("remote_whatami=\"router\"") {
        return None;
    }
    let (head, value) = line.rsplit_once(' ')?;
    let name = head.split('{').next()?;
    let direction = if name == tx {
        "sent"
    } else if name == rx {
        "received"
    } else {
        return None;
    };
    let peer = match label(head, "remote_cn").filter(|cn| !cn.is_empty()) {
        Some(cn) => cn,
        None => format!("zid:{}", label(head, "remote_zid").unwrap_or_default()),
    };
    Some((peer, direction, head, value.trim().parse::<f64>().ok()?))
}

/// A line of zenoh's per-key payload histograms for a link to another router:
/// `(peer, direction, key, message, bytes)` (the histogram's sum), the peer named as in
/// [`router_link_bytes`].
pub fn router_key_bytes(line: &str) -> Option<(String, &'static str, String, String, f64)> {
    let (peer, direction, head, value) = router_line(
        line,
        "zenoh_tx_network_message_payload_per_key_per_transport_bytes_sum",
        "zenoh_rx_network_message_payload_per_key_per_transport_bytes_sum",
    )?;
    let key = label(head, "key")?;
    let message = label(head, "message").unwrap_or_default();
    Some((peer, direction, key, message, value))
}

/// The links of zenoh's router graph (its admin space's `router/linkstate/north`, Graphviz
/// text: `0 [ label = "<zid>" ]` nodes and `0 -- 1 [ label = "<weight>" ]` edges) as pairs
/// of zenoh ids, each pair in order.
pub fn linkstate_edges(dot: &str) -> std::collections::BTreeSet<(String, String)> {
    let mut nodes: BTreeMap<&str, String> = BTreeMap::new();
    let mut edges = std::collections::BTreeSet::new();
    for line in dot.lines().map(str::trim) {
        let Some((head, attrs)) = line.split_once('[') else {
            continue;
        };
        let head = head.trim();
        if let Some((a, b)) = head.split_once("--") {
            edges.insert((a.trim().to_string(), b.trim().to_string()));
        } else if let Some(zid) = attrs.split('"').nth(1) {
            // `label = "<zid>" ]`: the text between the first two quotes.
            nodes.insert(head, zid.to_string());
        }
    }
    edges
        .into_iter()
        .filter_map(|(a, b)| {
            let (za, zb) = (nodes.get(a.as_str())?.clone(), nodes.get(b.as_str())?.clone());
            Some(if za <= zb { (za, zb) } else { (zb, za) })
        })
        .collect()
}

pub struct Router {
    metrics: Arc<ServiceMetrics>,
    refused_handshakes: Metric,
    denied_messages: Metric,
    link_bytes: Metric,
    key_bytes: Metric,
    neighbours: Metric,
    graph_links: Metric,
    zid: Metric,
    /// Every router it was ever linked to: those not linked now are listed at 0.
    known: Mutex<std::collections::BTreeSet<String>>,
    /// Every link of the router graph it ever saw: those gone are listed at 0.
    known_links: Mutex<std::collections::BTreeSet<(String, String)>>,
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
        let link_bytes = metrics.registry.counter(
            "swarmrec_router_link_bytes",
            "Bytes on the links to other routers (a mesh), as zenoh's transports counted them, by the \
             neighbour's certificate name and direction (sent to it, received from it); relayed traffic included",
            &["peer", "direction"],
        );
        let key_bytes = metrics.registry.counter(
            "swarmrec_router_key_bytes",
            "Payload bytes on the links to other routers (a mesh) by message type: zenoh's per-key \
             counts for each key expression of the bus setting stats_keys, by neighbour, direction, \
             key and zenoh message (query, reply, put); relayed traffic included, framing not",
            &["peer", "direction", "key", "message"],
        );
        let neighbours = metrics.registry.gauge(
            "swarmrec_router_neighbours",
            "Links to another router now (a mesh's router, at each scrape), by the neighbour's \
             zenoh id: 1 while linked, 0 after a link it had closed",
            &["peer_zid"],
        );
        let graph_links = metrics.registry.gauge(
            "swarmrec_router_graph_links",
            "The links between routers in this router's view of the router graph now (zenoh's link \
             state, at each scrape), by the two routers' zenoh ids: 1 while in it, 0 after it left",
            &["a", "b"],
        );
        let zid = metrics
            .registry
            .gauge("swarmrec_router_zid", "This router's zenoh id", &["zid"]);
        Router {
            metrics,
            refused_handshakes,
            denied_messages,
            link_bytes,
            key_bytes,
            neighbours,
            graph_links,
            zid,
            known_links: Mutex::new(Default::default()),
            known: Mutex::new(Default::default()),
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
    /// router's own thread ([`Router::follow_denials`]) every second, and at each scrape.
    ///
    /// A scrape also reads zenoh's counters and link state now (the router's admin space:
    /// a few milliseconds), so that what it says of its links to other routers is as of the
    /// scrape: a mesh's deployment reads them between two lock-step steps to know when every
    /// router follows a step's radio graph and what each link carried (docs/mesh.md).
    fn refresh_metrics(&self) {
        for (reason, n) in lock(&REFUSED).iter() {
            self.metrics.registry.set(self.refused_handshakes, &[reason], *n as f64);
        }
        self.copy_denials(false);
        self.copy_neighbours();
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
                    router.copy_denials(false);
                    drop(router);
                    std::thread::sleep(every);
                }
            });
    }

    /// Its page of links, link state and zenoh id, as of now (without zenoh's counters,
    /// which are costly to read: they are the full page's, `refresh_metrics`).
    pub fn mesh_page(&self) -> String {
        self.copy_neighbours();
        self.metrics.registry.render()
    }

    /// Its page with the bytes of each message type on its links, as of now (zenoh's per-key
    /// counts). Only on this page, which a mesh's deployment reads while its links do not
    /// change: read at every scrape, during link changes too, they left 10-robot meshes at a
    /// 4 m range with a router whose admin space stopped answering (in both benchmark runs
    /// and two single runs of three); read here only, the benchmark passed.
    pub fn keys_page(&self) -> String {
        self.copy_denials(true);
        self.metrics.registry.render()
    }

    /// Which routers it is linked to now (its admin space's sessions to routers, by zenoh
    /// id) and its view of the router graph.
    fn copy_neighbours(&self) {
        let Some(session) = self.session.get() else { return };
        let own = session.zid().to_string();
        let now: std::collections::BTreeSet<String> = self
            .admin_json("router")
            .and_then(|v| v.get("sessions").cloned())
            .and_then(|v| v.as_array().cloned())
            .unwrap_or_default()
            .iter()
            .filter(|s| s.get("whatami").and_then(|w| w.as_str()) == Some("router"))
            .filter_map(|s| s.get("peer").and_then(|p| p.as_str()).map(str::to_string))
            .collect();
        let mut known = lock(&self.known);
        known.extend(now.iter().cloned());
        for peer in known.iter() {
            let linked = if now.contains(peer) { 1.0 } else { 0.0 };
            self.metrics.registry.set(self.neighbours, &[peer], linked);
        }
        drop(known);
        self.metrics.registry.set(self.zid, &[&own], 1.0);
        let Some(dot) = self.admin("router/linkstate/north") else {
            return;
        };
        let edges = linkstate_edges(&String::from_utf8_lossy(&dot));
        let mut known_links = lock(&self.known_links);
        known_links.extend(edges.iter().cloned());
        for (a, b) in known_links.iter() {
            let present = if edges.contains(&(a.clone(), b.clone())) {
                1.0
            } else {
                0.0
            };
            self.metrics.registry.set(self.graph_links, &[a, b], present);
        }
    }

    /// zenoh's access-control drops as they are now (sessions that left included).
    /// With `per_key`, also the bytes of each message type (zenoh's per-key histograms).
    fn copy_denials(&self, per_key: bool) {
        let registry = &self.metrics.registry;
        // zenoh's selector parameters are separated by `;`.
        let selector = format!(
            "router/metrics?compression=false;descriptors=false;per_key={per_key};per_link=false;\
             disconnected=true"
        );
        let Some(text) = self.admin(&selector) else { return };
        let mut denied: BTreeMap<(String, &'static str, String), f64> = BTreeMap::new();
        let mut links: BTreeMap<(String, &'static str), f64> = BTreeMap::new();
        let mut by_key: BTreeMap<(String, &'static str, String, String), f64> = BTreeMap::new();
        for line in String::from_utf8_lossy(&text).lines() {
            if let Some((peer, direction, key, message, n)) = router_key_bytes(line) {
                // Summed over priorities and over the transports to one neighbour.
                *by_key.entry((peer, direction, key, message)).or_insert(0.0) += n;
                continue;
            }
            if let Some((peer, direction, n)) = router_link_bytes(line) {
                // Summed over the transports to one neighbour (a link that closed and came back).
                *links.entry((peer, direction)).or_insert(0.0) += n;
                continue;
            }
            if let Some((identity, direction, message, n)) = access_control_drop(line) {
                // Summed over priorities and over the sessions of one name (a client that
                // reconnects keeps its count).
                *denied.entry((identity, direction, message)).or_insert(0.0) += n;
            }
        }
        for ((identity, direction, message), n) in denied {
            registry.set(self.denied_messages, &[&identity, direction, &message], n);
        }
        for ((peer, direction), n) in links {
            registry.set(self.link_bytes, &[&peer, direction], n);
        }
        for ((peer, direction, key, message), n) in by_key {
            registry.set(self.key_bytes, &[&peer, direction, &key, &message], n);
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
    fn router_graph_links_as_ordered_zid_pairs() {
        // As zenoh 1.10.2's admin space writes a three-router chain.
        let dot = "graph {\n    0 [ label = \"b8\" ]\n    1 [ label = \"f2\" ]\n    2 [ label = \"65\" ]\n    \
                   1 -- 0 [ label = \"100.13\" ]\n    2 -- 1 [ label = \"100.49\" ]\n}\n";
        let edges: Vec<(String, String)> = linkstate_edges(dot).into_iter().collect();
        assert_eq!(
            edges,
            vec![
                ("65".to_string(), "f2".to_string()),
                ("b8".to_string(), "f2".to_string())
            ]
        );
        assert!(linkstate_edges("graph {\n    0 [ label = \"b8\" ]\n}\n").is_empty());
    }

    #[test]
    fn link_bytes_by_neighbour_and_direction() {
        // Lines as zenoh 1.10.2 writes them (seen from a router of a three-router chain).
        let tx = r#"zenoh_tx_per_transport_bytes_total{local_id="d7",local_whatami="router",protocol="tls",remote_zid="76",remote_whatami="router",remote_group="",remote_cn="r1.router.lab",disconnected="false"} 11068"#;
        assert_eq!(
            router_link_bytes(tx),
            Some(("r1.router.lab".to_string(), "sent", 11068.0))
        );
        let rx = r#"zenoh_rx_per_transport_bytes_total{local_id="d7",local_whatami="router",protocol="tcp",remote_zid="76",remote_whatami="router",remote_group="",remote_cn="",disconnected="true"} 1040"#;
        assert_eq!(router_link_bytes(rx), Some(("zid:76".to_string(), "received", 1040.0)));
        // Not a link to a router: a client's transport, or another family.
        for line in [
            r#"zenoh_tx_per_transport_bytes_total{remote_whatami="client",remote_cn="r1.verifier.lab"} 5"#,
            r#"zenoh_tx_network_message_payload_per_transport_bytes_sum{remote_whatami="router",remote_cn="x"} 5"#,
            "# TYPE zenoh_tx_per_transport_bytes_total counter",
        ] {
            assert_eq!(router_link_bytes(line), None, "{line}");
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
    fn bytes_by_key_are_read_from_the_per_key_histograms_of_links_to_routers() {
        let tx = r#"zenoh_tx_network_message_payload_per_key_per_transport_bytes_sum{local_id="41",local_whatami="router",space="user",priority="data",message="query",shm="false",remote_zid="9f",remote_whatami="router",remote_cn="r2.router.lab",key="swarmrec/v1/lab/index-shard/*/query/**"} 3072"#;
        assert_eq!(
            router_key_bytes(tx),
            Some((
                "r2.router.lab".to_string(),
                "sent",
                "swarmrec/v1/lab/index-shard/*/query/**".to_string(),
                "query".to_string(),
                3072.0
            ))
        );
        // Not counted: a client's transport, the histogram's count, lines without a key.
        for line in [
            r#"zenoh_tx_network_message_payload_per_key_per_transport_bytes_sum{message="query",remote_whatami="client",key="k"} 5"#,
            r#"zenoh_tx_network_message_payload_per_key_per_transport_bytes_count{message="query",remote_whatami="router",key="k"} 5"#,
            r#"zenoh_rx_network_message_payload_per_key_per_transport_bytes_sum{message="reply",remote_whatami="router"} 5"#,
        ] {
            assert_eq!(router_key_bytes(line), None, "{line}");
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
