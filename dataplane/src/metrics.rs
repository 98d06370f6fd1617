//! Prometheus metrics of a compiled service: the same families, names, labels and
//! help texts as the Python runner's (`swarmrec/runtime/metrics.py`), rendered in
//! the text exposition format, and the process's HTTP endpoint with its probe pages.
//!
//! Counting is a few adds under an uncontended lock per message; rendering happens
//! only when scraped.

use std::collections::{BTreeMap, HashMap};
use std::fmt::Write as _;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Request latencies on loopback are 0.2-5 ms; the Python runner's buckets.
pub const LATENCY_BUCKETS: [f64; 13] = [
    0.0002, 0.0005, 0.001, 0.002, 0.003, 0.005, 0.0075, 0.01, 0.02, 0.05, 0.1, 0.5, 2.0,
];

#[derive(Clone, Copy, PartialEq)]
enum Kind {
    Counter,
    Gauge,
    Histogram,
}

struct Family {
    name: &'static str,
    help: &'static str,
    kind: Kind,
    labels: &'static [&'static str],
    /// Label values -> value (counter, gauge) or the histogram's buckets, sum, count.
    series: BTreeMap<Vec<String>, Series>,
}

#[derive(Clone)]
enum Series {
    Value(f64),
    Histogram {
        buckets: [u64; LATENCY_BUCKETS.len()],
        sum: f64,
        count: u64,
    },
}

/// One service's metric families (a registry of its own, like each Python service's).
pub struct Registry {
    families: Mutex<Vec<Family>>,
}

/// A page of the metrics endpoint: its text, rendered when scraped.
pub type Page = Arc<dyn Fn() -> String + Send + Sync>;

/// Handle of one family in a [`Registry`].
#[derive(Clone, Copy)]
pub struct Metric(usize);

impl Registry {
    pub fn new() -> Registry {
        Registry {
            families: Mutex::new(Vec::new()),
        }
    }

    fn add(&self, name: &'static str, help: &'static str, kind: Kind, labels: &'static [&'static str]) -> Metric {
        let mut families = self.families.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        families.push(Family {
            name,
            help,
            kind,
            labels,
            series: BTreeMap::new(),
        });
        Metric(families.len() - 1)
    }

    pub fn counter(&self, name: &'static str, help: &'static str, labels: &'static [&'static str]) -> Metric {
        self.add(name, help, Kind::Counter, labels)
    }

    pub fn gauge(&self, name: &'static str, help: &'static str, labels: &'static [&'static str]) -> Metric {
        self.add(name, help, Kind::Gauge, labels)
    }

    pub fn histogram(&self, name: &'static str, help: &'static str, labels: &'static [&'static str]) -> Metric {
        self.add(name, help, Kind::Histogram, labels)
    }

    fn with<R>(&self, m: Metric, labels: &[&str], f: impl FnOnce(&mut Series) -> R) -> R {
        let mut families = self.families.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let fam = &mut families[m.0];
        debug_assert_eq!(fam.labels.len(), labels.len(), "{}", fam.name);
        let key: Vec<String> = labels.iter().map(|s| s.to_string()).collect();
        let empty = if fam.kind == Kind::Histogram {
            Series::Histogram {
                buckets: [0; LATENCY_BUCKETS.len()],
                sum: 0.0,
                count: 0,
            }
        } else {
            Series::Value(0.0)
        };
        f(fam.series.entry(key).or_insert(empty))
    }

    pub fn inc(&self, m: Metric, labels: &[&str], by: f64) {
        self.with(m, labels, |s| {
            if let Series::Value(v) = s {
                *v += by;
            }
        });
    }

    pub fn set(&self, m: Metric, labels: &[&str], to: f64) {
        self.with(m, labels, |s| *s = Series::Value(to));
    }

    pub fn observe(&self, m: Metric, labels: &[&str], value: f64) {
        self.with(m, labels, |s| {
            if let Series::Histogram { buckets, sum, count } = s {
                for (b, le) in buckets.iter_mut().zip(LATENCY_BUCKETS) {
                    if value <= le {
                        *b += 1;
                    }
                }
                *sum += value;
                *count += 1;
            }
        });
    }

    /// The text exposition format, as prometheus_client writes it (counters as `_total`).
    pub fn render(&self) -> String {
        let families = self.families.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let mut out = String::new();
        for fam in families.iter() {
            let (name, kind) = match fam.kind {
                Kind::Counter => (format!("{}_total", fam.name), "counter"),
                Kind::Gauge => (fam.name.to_string(), "gauge"),
                Kind::Histogram => (fam.name.to_string(), "histogram"),
            };
            let _ = writeln!(out, "# HELP {name} {}", fam.help);
            let _ = writeln!(out, "# TYPE {name} {kind}");
            if fam.labels.is_empty() && fam.series.is_empty() && fam.kind != Kind::Histogram {
                let _ = writeln!(out, "{name} 0.0");
            }
            for (values, series) in &fam.series {
                let labels = label_text(fam.labels, values, None);
                match series {
                    Series::Value(v) => {
                        let _ = writeln!(out, "{name}{labels} {}", number(*v));
                    }
                    Series::Histogram { buckets, sum, count } => {
                        for (b, le) in buckets.iter().zip(LATENCY_BUCKETS) {
                            let l = label_text(fam.labels, values, Some(&number(le)));
                            let _ = writeln!(out, "{name}_bucket{l} {}", number(*b as f64));
                        }
                        let l = label_text(fam.labels, values, Some("+Inf"));
                        let _ = writeln!(out, "{name}_bucket{l} {}", number(*count as f64));
                        let _ = writeln!(out, "{name}_count{labels} {}", number(*count as f64));
                        let _ = writeln!(out, "{name}_sum{labels} {}", number(*sum));
                    }
                }
            }
        }
        out
    }
}

impl Default for Registry {
    fn default() -> Self {
        Registry::new()
    }
}

fn number(v: f64) -> String {
    if v.fract() == 0.0 && v.abs() < 1e15 {
        format!("{v:.1}")
    } else {
        format!("{v}")
    }
}

fn label_text(names: &[&str], values: &[String], le: Option<&str>) -> String {
    let mut parts: Vec<String> = names
        .iter()
        .zip(values)
        .map(|(n, v)| {
            format!(
                "{n}=\"{}\"",
                v.replace('\\', "\\\\").replace('"', "\\\"").replace('\n', "\\n")
            )
        })
        .collect();
    if let Some(le) = le {
        parts.push(format!("le=\"{le}\""));
    }
    if parts.is_empty() {
        String::new()
    } else {
        format!("{{{}}}", parts.join(","))
    }
}

/// The families every service exports (`ServiceMetrics` in the Python runner).
pub struct ServiceMetrics {
    pub registry: Registry,
    pub bytes_sent: Metric,
    pub bytes_received: Metric,
    pub messages_sent: Metric,
    pub messages_received: Metric,
    pub request_seconds: Metric,
    pub request_cpu_seconds: Metric,
    pub rejected: Metric,
    #[allow(dead_code)] // exported (zero) like every service's; the verifier calls no peer
    pub peer_failures: Metric,
    pub ready: Metric,
    /// (calls, CPU seconds) served per endpoint since start: what an index shard reports
    /// to the coordinator as a store's cost against a query's.
    costs: Mutex<HashMap<&'static str, (u64, f64)>>,
}

impl ServiceMetrics {
    pub fn new(kind: &str, robot: u32, swarm: &str) -> ServiceMetrics {
        let r = Registry::new();
        let info = r.gauge(
            "swarmrec_service_info",
            "The service behind this endpoint",
            &["robot", "service", "swarm"],
        );
        r.set(info, &[&robot.to_string(), kind, swarm], 1.0);
        let m = ServiceMetrics {
            bytes_sent: r.counter(
                "swarmrec_message_bytes_sent",
                "Payload bytes sent, by message type and scope",
                &["message", "scope"],
            ),
            bytes_received: r.counter(
                "swarmrec_message_bytes_received",
                "Payload bytes received, by message type and scope",
                &["message", "scope"],
            ),
            messages_sent: r.counter(
                "swarmrec_messages_sent",
                "Messages sent, by message type and scope",
                &["message", "scope"],
            ),
            messages_received: r.counter(
                "swarmrec_messages_received",
                "Messages received, by message type and scope",
                &["message", "scope"],
            ),
            request_seconds: r.histogram(
                "swarmrec_request_duration_seconds",
                "Time to serve a request (or handle a subscribed message), by endpoint",
                &["endpoint"],
            ),
            request_cpu_seconds: r.counter(
                "swarmrec_request_cpu_seconds",
                "CPU time of the serving thread to serve requests (or handle subscribed messages), by endpoint",
                &["endpoint"],
            ),
            rejected: r.counter(
                "swarmrec_rejected_requests",
                "Requests (and subscribed messages) refused with an error, by endpoint and code",
                &["endpoint", "code"],
            ),
            peer_failures: r.counter(
                "swarmrec_peer_failures",
                "Requests to peers that failed, by endpoint and reason",
                &["endpoint", "reason"],
            ),
            ready: r.gauge(
                "swarmrec_service_ready",
                "1 while the service serves (liveliness token declared), 0 while starting or stopping",
                &[],
            ),
            registry: r,
            costs: Mutex::new(HashMap::new()),
        };
        m.registry.set(m.ready, &[], 0.0);
        m
    }

    pub fn count_sent(&self, message: &str, scope: &str, size: usize) {
        self.registry.inc(self.bytes_sent, &[message, scope], size as f64);
        self.registry.inc(self.messages_sent, &[message, scope], 1.0);
    }

    /// Adds one served request's CPU time to `endpoint`'s running cost.
    pub fn add_cost(&self, endpoint: &'static str, cpu_s: f64) {
        let mut costs = self.costs.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let c = costs.entry(endpoint).or_insert((0, 0.0));
        c.0 += 1;
        c.1 += cpu_s;
    }

    /// (calls, CPU seconds) of `endpoint` so far.
    pub fn cost(&self, endpoint: &str) -> (u64, f64) {
        let costs = self.costs.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        costs.get(endpoint).copied().unwrap_or((0, 0.0))
    }

    pub fn count_received(&self, message: &str, scope: &str, size: usize) {
        self.registry.inc(self.bytes_received, &[message, scope], size as f64);
        self.registry.inc(self.messages_received, &[message, scope], 1.0);
    }
}

/// Scope of a message between this robot and another (None: a client outside the swarm).
pub fn scope_between(own: u32, other: Option<u32>) -> &'static str {
    match other {
        None => "client",
        Some(r) if r == own => "robot",
        Some(_) => "swarm",
    }
}

/// One process's HTTP endpoint: each service's registry at its path, `/ready` (200 once
/// every hosted service serves) and `/healthz` (200 while the process answers).
pub struct MetricsServer {
    pub port: u16,
    pub host: String,
    ready: Arc<AtomicBool>,
    stopping: Arc<AtomicBool>,
}

impl MetricsServer {
    /// Binds `host:port` (0: a free port) and serves `pages` (path -> registry) in a thread.
    pub fn start(host: &str, port: u16, pages: Vec<(String, Page)>) -> std::io::Result<MetricsServer> {
        let listener = TcpListener::bind((host, port))?;
        let port = listener.local_addr()?.port();
        let ready = Arc::new(AtomicBool::new(false));
        let stopping = Arc::new(AtomicBool::new(false));
        let (r, s) = (ready.clone(), stopping.clone());
        std::thread::Builder::new().name("metrics-http".into()).spawn(move || {
            for stream in listener.incoming() {
                if s.load(Ordering::Relaxed) {
                    return;
                }
                if let Ok(stream) = stream {
                    let _ = serve_one(stream, &pages, r.load(Ordering::Relaxed));
                }
            }
        })?;
        Ok(MetricsServer {
            port,
            host: host.to_string(),
            ready,
            stopping,
        })
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://{}:{}{}", self.host, self.port, path)
    }

    pub fn set_ready(&self, ready: bool) {
        self.ready.store(ready, Ordering::Relaxed);
    }

    pub fn close(&self) {
        self.stopping.store(true, Ordering::Relaxed);
        let _ = TcpStream::connect((self.host.as_str(), self.port)); // wakes the accept loop
    }
}

fn serve_one(mut stream: TcpStream, pages: &[(String, Page)], ready: bool) -> std::io::Result<()> {
    stream.set_read_timeout(Some(Duration::from_secs(2)))?;
    let mut reader = BufReader::new(stream.try_clone()?);
    let mut line = String::new();
    // The request line, bounded: a client that sends a huge line gets a 400.
    reader.by_ref().take(8192).read_line(&mut line)?;
    loop {
        let mut header = String::new();
        if reader.by_ref().take(8192).read_line(&mut header)? == 0 || header == "\r\n" || header == "\n" {
            break;
        }
    }
    let path = line
        .split_whitespace()
        .nth(1)
        .unwrap_or("")
        .split('?')
        .next()
        .unwrap_or("");
    let (status, ctype, body) = match path {
        "/healthz" => ("200 OK", "text/plain", "ok\n".to_string()),
        "/ready" if ready => ("200 OK", "text/plain", "ready\n".to_string()),
        "/ready" => ("503 Service Unavailable", "text/plain", "not ready\n".to_string()),
        _ => match pages.iter().find(|(p, _)| p == path) {
            Some((_, render)) => ("200 OK", "text/plain; version=0.0.4; charset=utf-8", render()),
            None => ("404 Not Found", "text/plain", "not found\n".to_string()),
        },
    };
    write!(
        stream,
        "HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )?;
    stream.flush()
}
