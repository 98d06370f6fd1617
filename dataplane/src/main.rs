//! `swarmrec-dataplane`: the compiled host of swarmrec's per-message services.
//!
//! Started by `swarmrec serve <kind>` / `swarmrec host` (never by hand: the Python CLI
//! resolves every setting and hands them over whole, `--spec-file`), it runs any set
//! of compiled services, of one robot or many, on one zenoh session, and behaves
//! towards the swarm as the Python runner does: the readiness line on stdout, JSON
//! log lines on stderr, Prometheus and probe pages over HTTP, a liveliness token per
//! service, SIGTERM/SIGINT to stop (token first, then endpoints, then the session).
//!
//! Unless the environment says otherwise, zenoh runs on one thread
//! (`ZENOH_RUNTIME`, ../shared/ZENOH.md: half the CPU per message of its default
//! pools here), and requests are served in zenoh's callbacks: no hand-off.

mod argsort;
mod association;
mod caller;
mod compute;
mod descriptor;
mod detector;
mod index;
mod metrics;
mod pb;
mod pending;
mod placement;
mod recordlog;
mod router;
mod routes;
mod routing;
mod runtime;
mod selection;
mod shard;
mod spec;
mod verifier;
mod wirecheck;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context};
use zenoh::Wait;

use crate::metrics::{MetricsServer, ServiceMetrics};
use crate::routes::Routes;
use crate::runtime::{Dispatcher, LocalEndpoints, Log, Service};
use crate::spec::HostSpec;

/// zenoh's runtime on the process's one thread, every pool handed over to it (ZENOH.md).
/// Sending too: on a thread of its own, zenoh's TLS link read and wrote one TLS stream from
/// two threads (upstream zenoh issue 2557; patched since, dataplane/vendor/README.md, for
/// the router, which keeps zenoh's pools). The Python side's
/// `SINGLE_THREAD_RUNTIME` (swarmrec/runtime/settings.py) is the same string, and the
/// zenoh configuration Python hands over deepens the send queues this runtime needs.
const SINGLE_THREAD_RUNTIME: &str =
    "(app:(worker_threads:1),rx:(handover:app),tx:(handover:app),net:(handover:app),acc:(handover:app))";

/// Requests a blocking endpoint holds waiting for its thread before it refuses more.
const BLOCKING_QUEUE: usize = 1024;

/// The kinds this binary implements (the detector in its replay mode only).
const KINDS: &[&str] = &["descriptor", "detector", "index-shard", "router", "verifier"];

fn usage() -> ! {
    eprintln!(
        "usage: swarmrec-dataplane host --spec-file PATH\n       swarmrec-dataplane kinds\n       \
         swarmrec-dataplane compute   (JSON lines on stdin: the exactness tests' entry)\n\n\
         Started by `swarmrec serve`/`swarmrec host` for the kinds it implements ({}).",
        KINDS.join(", ")
    );
    std::process::exit(2)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.first().map(String::as_str) {
        Some("kinds") => println!("{}", KINDS.join(",")),
        Some("compute") if args.len() == 1 => {
            if let Err(e) = compute::serve_lines(std::io::stdin().lock(), std::io::stdout().lock()) {
                eprintln!("compute: {e:#}");
                std::process::exit(1);
            }
        }
        Some("host") if args.len() == 3 && args[1] == "--spec-file" => {
            match read_spec(&args[2]).and_then(|spec| {
                // A router keeps zenoh's pools: it forwards messages it cannot bound (any
                // client's) into queues it does not control, and on one thread a full queue
                // waits on itself (the Python side's `on_single_runtime`, the same rule).
                let routes = spec.services.iter().any(|s| s.kind == "router");
                if !routes && std::env::var_os("ZENOH_RUNTIME").is_none() {
                    std::env::set_var("ZENOH_RUNTIME", SINGLE_THREAD_RUNTIME);
                }
                host(spec)
            }) {
                Ok(()) => {}
                Err(e) => {
                    eprintln!(
                        "{}",
                        serde_json::json!({"level": "ERROR", "service": "host", "msg": format!("{e:#}")})
                    );
                    std::process::exit(1);
                }
            }
        }
        _ => usage(),
    }
}

/// The host's spec, from the file Python wrote for this process alone (a host of many
/// services has a spec longer than one command-line argument may be); removed once read.
fn read_spec(path: &str) -> anyhow::Result<HostSpec> {
    let text = std::fs::read_to_string(path).with_context(|| format!("--spec-file {path}"))?;
    let _ = std::fs::remove_file(path);
    serde_json::from_str::<HostSpec>(&text).context("--spec-file")
}

/// zenoh's own warnings and errors (a link closed, a message it could not send) as JSON log
/// lines on stderr, like the services' (`"service": "zenoh"`): a message zenoh gives up on
/// is then in the host's log, never silent (docs/dataplane.md, "No silent loss").
fn zenoh_log(log: Log) {
    zenoh_util::init_log_with_callback(
        |meta| *meta.level() <= tracing::Level::WARN,
        move |record| {
            let level = if record.level == tracing::Level::ERROR { 40 } else { 30 };
            let msg = record.message.unwrap_or_default();
            if router::observe_zenoh_record(&record.target, &msg) {
                return; // a refused handshake: counted and logged by the router
            }
            log.emit(level, &msg, serde_json::json!({"target": record.target}));
        },
    );
}

static STOP: AtomicBool = AtomicBool::new(false);

/// Dies with the process that started this one (a Python host mixing kinds): a host killed
/// must not leave its compiled services answering.
fn die_with_parent() {
    // SAFETY: prctl with PR_SET_PDEATHSIG only sets this process's parent-death signal.
    unsafe {
        libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
    }
    // SAFETY: getppid has no preconditions.
    if unsafe { libc::getppid() } == 1 {
        std::process::exit(1); // the parent was gone before the signal was set
    }
}

/// The Python process running the compiled index shards' coordinators (placements are
/// computed by the one implementation of their rules, `swarmrec.core.placement`). It is
/// this host's child: killed or frozen, the host takes its coordinators with it; one that
/// ends on its own is started again.
struct Sidecar {
    argv: Vec<String>,
    child: Option<std::process::Child>,
    log: Log,
    next_start: std::time::Instant,
    /// Set once the coordinators said they checked their shards' placements (a JSON line
    /// `{"event": "checked"}` on their stdout): the shards are declared ready then.
    checked: Arc<AtomicBool>,
}

impl Sidecar {
    fn new(argv: Vec<String>, log: Log) -> Sidecar {
        let mut s = Sidecar {
            argv,
            child: None,
            log,
            next_start: std::time::Instant::now(),
            checked: Arc::new(AtomicBool::new(false)),
        };
        s.keep_up();
        s
    }

    fn keep_up(&mut self) {
        if self.argv.is_empty() {
            return;
        }
        if let Some(child) = &mut self.child {
            match child.try_wait() {
                Ok(None) => return,
                Ok(Some(status)) => self.log.warning(
                    "the shards' coordinator ended: starting it again",
                    serde_json::json!({"status": status.to_string()}),
                ),
                Err(e) => self
                    .log
                    .warning(&format!("the shards' coordinator: {e}"), serde_json::json!({})),
            }
            self.child = None;
            self.next_start = std::time::Instant::now() + std::time::Duration::from_secs(1);
        }
        if std::time::Instant::now() < self.next_start {
            return;
        }
        let mut cmd = std::process::Command::new(&self.argv[0]);
        cmd.args(&self.argv[1..])
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::piped());
        // SAFETY: the closure only calls prctl, which is async-signal-safe.
        unsafe {
            std::os::unix::process::CommandExt::pre_exec(&mut cmd, || {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
                Ok(())
            });
        }
        match cmd.spawn() {
            Ok(mut child) => {
                if let Some(out) = child.stdout.take() {
                    let checked = self.checked.clone();
                    let _ = std::thread::Builder::new()
                        .name("coordinator-stdout".into())
                        .spawn(move || {
                            use std::io::BufRead;
                            for line in std::io::BufReader::new(out).lines().map_while(Result::ok) {
                                let event = serde_json::from_str::<serde_json::Value>(&line).ok();
                                if event.as_ref().and_then(|e| e.get("event")).and_then(|e| e.as_str())
                                    == Some("checked")
                                {
                                    checked.store(true, Ordering::SeqCst);
                                }
                            }
                        });
                }
                self.child = Some(child);
            }
            Err(e) => {
                self.log.emit(
                    40,
                    &format!("the shards' coordinator did not start: {e}"),
                    serde_json::json!({}),
                );
                self.next_start = std::time::Instant::now() + std::time::Duration::from_secs(5);
            }
        }
    }

    /// Waits (at most `timeout`, and while not stopped) until the coordinators checked their
    /// shards' placements; false when they did not say so in time.
    fn wait_checked(&mut self, timeout: std::time::Duration) -> bool {
        if self.argv.is_empty() {
            return true;
        }
        let deadline = std::time::Instant::now() + timeout;
        while std::time::Instant::now() < deadline && !STOP.load(Ordering::SeqCst) {
            if self.checked.load(Ordering::SeqCst) {
                return true;
            }
            self.keep_up();
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        self.log.warning(
            "the shards' coordinator did not check their placements in time: ready anyway",
            serde_json::json!({}),
        );
        false
    }

    /// SIGTERM, up to 5 s, then SIGKILL.
    fn stop(&mut self) {
        let Some(mut child) = self.child.take() else { return };
        // SAFETY: kill with the child's own pid.
        unsafe {
            libc::kill(child.id() as libc::pid_t, libc::SIGTERM);
        }
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while std::time::Instant::now() < deadline {
            if let Ok(Some(_)) = child.try_wait() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let _ = child.kill();
        let _ = child.wait();
    }
}

/// The zenoh session, or None when SIGTERM/SIGINT came first. A client waits for its router
/// as long as it takes (`connect/timeout_ms` -1), and zenoh's open does not return until then:
/// it runs on a thread of its own so that a host still waiting can be stopped.
fn open_session(config: zenoh::Config) -> anyhow::Result<Option<zenoh::Session>> {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::Builder::new()
        .name("open".into())
        .spawn(move || {
            let _ = tx.send(zenoh::open(config).wait());
        })
        .context("a thread to open the session")?;
    loop {
        match rx.recv_timeout(std::time::Duration::from_millis(100)) {
            Ok(opened) => return opened.map(Some).map_err(|e| anyhow::anyhow!("zenoh session: {e}")),
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) if STOP.load(Ordering::SeqCst) => return Ok(None),
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => bail!("zenoh session: its thread ended"),
        }
    }
}

extern "C" fn on_signal(_: libc::c_int) {
    STOP.store(true, Ordering::SeqCst);
}

struct Hosted {
    kind: String,
    robot: u32,
    swarm: String,
    wire_kind: i32,
    service: Arc<dyn Service>,
    metrics: Arc<ServiceMetrics>,
    log: Log,
    url: String,
}

fn host(spec: HostSpec) -> anyhow::Result<()> {
    if spec.services.is_empty() {
        bail!("a host runs at least one service");
    }
    zenoh_log(Log::new("zenoh", spec.services[0].robot, "WARNING"));
    for s in &spec.services {
        if !KINDS.contains(&s.kind.as_str()) {
            bail!(
                "{} has no compiled implementation (compiled: {})",
                s.kind,
                KINDS.join(", ")
            );
        }
    }
    if spec.die_with_parent {
        die_with_parent();
    }
    // SAFETY: the handler only stores to an atomic.
    unsafe {
        libc::signal(libc::SIGTERM, on_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGINT, on_signal as *const () as libc::sighandler_t);
    }
    let single = spec.services.len() == 1;
    let host_log = Log::new(
        if single { &spec.services[0].kind } else { "host" },
        spec.services[0].robot,
        &spec.log_level,
    );
    let mut hosted: Vec<Hosted> = Vec::new();
    let mut routers: Vec<Arc<router::Router>> = Vec::new();
    let local = Arc::new(LocalEndpoints::default());
    for s in &spec.services {
        let metrics = Arc::new(ServiceMetrics::new(&s.kind, s.robot, &s.swarm));
        let log = Log::new(&s.kind, s.robot, &spec.log_level);
        let service: Arc<dyn Service> = match s.kind.as_str() {
            "verifier" => Arc::new(verifier::Verifier::new(s, metrics.clone(), log.clone())?),
            "index-shard" => shard::IndexShard::new(s, metrics.clone(), log.clone())?,
            "descriptor" => descriptor::Descriptor::new(s, metrics.clone(), log.clone(), local.clone())?,
            "detector" => detector::Detector::new(s, metrics.clone(), log.clone(), local.clone())?,
            "router" => {
                let r = Arc::new(router::Router::new(metrics.clone(), log.clone()));
                routers.push(r.clone());
                r
            }
            other => bail!("{other} has no compiled implementation"),
        };
        let path = if single {
            "/metrics".to_string()
        } else {
            format!("/metrics/{}/{}", s.kind, s.robot)
        };
        hosted.push(Hosted {
            kind: s.kind.clone(),
            robot: s.robot,
            swarm: s.swarm.clone(),
            wire_kind: s.wire_kind,
            service,
            metrics,
            log,
            url: path,
        });
    }
    // Metrics: one endpoint for the process; with several services, /metrics is the host's readiness.
    let host_metrics = Arc::new(metrics::Registry::new());
    let host_ready = host_metrics.gauge(
        "swarmrec_service_ready",
        "1 while every service of this process serves",
        &[],
    );
    host_metrics.set(host_ready, &[], 0.0);
    let server = if spec.metrics_port >= 0 {
        let mut pages: Vec<(String, metrics::Page)> = Vec::new();
        for h in &hosted {
            let (m, service) = (h.metrics.clone(), h.service.clone());
            pages.push((
                h.url.clone(),
                Arc::new(move || {
                    service.refresh_metrics();
                    m.registry.render()
                }),
            ));
        }
        if !single {
            let m = host_metrics.clone();
            pages.push(("/metrics".to_string(), Arc::new(move || m.render())));
        }
        // A router's links and link state alone, cheap to read often (a mesh's deployment
        // polls it while the routers follow a new radio graph): `<its metrics path>/mesh`.
        // Its bytes by message type (zenoh's per-key counts): `<its metrics path>/keys`, read
        // while the links do not change (before and after a replay).
        for (h, r) in hosted.iter().filter(|h| h.kind == "router").zip(&routers) {
            let (r, k) = (r.clone(), r.clone());
            pages.push((
                format!("{}/mesh", h.url.trim_end_matches('/')),
                Arc::new(move || r.mesh_page()),
            ));
            pages.push((
                format!("{}/keys", h.url.trim_end_matches('/')),
                Arc::new(move || k.keys_page()),
            ));
        }
        let port = u16::try_from(spec.metrics_port).context("metrics_port")?;
        let server = MetricsServer::start(&spec.metrics_host, port, pages).context("metrics endpoint")?;
        for h in &mut hosted {
            h.url = server.url(&h.url);
        }
        Some(server)
    } else {
        for h in &mut hosted {
            h.url.clear();
        }
        None
    };
    let config =
        zenoh::Config::from_json5(&spec.zenoh.to_string()).map_err(|e| anyhow::anyhow!("zenoh config: {e}"))?;
    // Said before the wait for the router, which may be long: where it waits (and, to a
    // supervisor, that SIGTERM is handled from here on).
    host_log.info(
        "connecting to the swarm",
        serde_json::json!({"connect": spec.zenoh["connect"]["endpoints"]}),
    );
    let session = match open_session(config)? {
        Some(session) => session,
        None => {
            // Stopped while the router was out of reach: nothing was declared yet.
            host_log.info("stopped before reaching the swarm", serde_json::json!({}));
            return Ok(());
        }
    };
    for h in &hosted {
        h.service.attach(&session)?;
    }
    for r in &routers {
        r.follow_denials(std::time::Duration::from_secs(1));
    }
    // The coordinators start now: their interpreter's start overlaps the declarations, and a
    // shard restarted from its disk answers only once its coordinator has confirmed it.
    let mut coordinator = Sidecar::new(spec.coordinator.clone(), host_log.clone());
    let mut queryables = Vec::new();
    let mut tokens = Vec::new();
    for (h, s) in hosted.iter().zip(&spec.services) {
        // One queryable for the service's endpoints (routes.rs: zenoh matches a query
        // against every queryable of the session, one per endpoint was 700 of them).
        let mut routes: Routes<zenoh::query::Query> = Routes::new(&h.swarm, &h.kind, h.robot);
        for endpoint in h.service.clone().endpoints() {
            let key = runtime::endpoint_key(&h.swarm, &h.kind, h.robot, endpoint.name);
            let (name, blocking) = (endpoint.name, endpoint.blocking);
            let d = Arc::new(Dispatcher {
                endpoint,
                reply_key: runtime::declared(&session, &key),
                key: key.clone(),
                robot: h.robot,
                max_message_bytes: s.max_message_bytes,
                metrics: h.metrics.clone(),
                log: h.log.clone(),
                bound: runtime::caller_bound(&h.kind, name),
                session: session.clone(),
            });
            local.add(&key, h.robot, d.clone());
            if blocking {
                // Served on a thread of its own, in the order the queries came: zenoh's
                // one thread stays free to deliver the replies the handler waits for.
                let (tx, rx) = std::sync::mpsc::sync_channel::<zenoh::query::Query>(BLOCKING_QUEUE);
                let worker = d.clone();
                std::thread::Builder::new()
                    .name(format!("{}-{}", h.kind, worker.endpoint.name))
                    .spawn(move || {
                        while let Ok(query) = rx.recv() {
                            worker.serve(query);
                        }
                    })
                    .context("a thread for a blocking endpoint")?;
                routes.add(
                    name,
                    Box::new(move |query| {
                        if let Err(std::sync::mpsc::TrySendError::Full(query)) = tx.try_send(query) {
                            d.refuse_busy(query, BLOCKING_QUEUE);
                        }
                    }),
                )?;
            } else {
                routes.add(name, Box::new(move |query| d.serve(query)))?;
            }
        }
        // `info`: what the service says of itself (asked once per member: no counting).
        let key = runtime::endpoint_key(&h.swarm, &h.kind, h.robot, "info");
        let (service, reply_key) = (h.service.clone(), key.clone());
        let (wire_kind, robot, swarm, url, version) = (
            h.wire_kind,
            h.robot,
            h.swarm.clone(),
            h.url.clone(),
            spec.version.clone(),
        );
        routes.add(
            "info",
            Box::new(move |query| {
                let mut info = service.member_info();
                info.kind = wire_kind;
                info.robot_id = robot;
                info.version = version.clone();
                info.metrics_url = url.clone();
                info.swarm = swarm.clone();
                let _ = query
                    .reply(&reply_key, prost::Message::encode_to_vec(&info))
                    .encoding(runtime::encoding("MemberInfo"))
                    .wait();
            }),
        )?;
        let key = routes.key();
        let q = session
            .declare_queryable(&key)
            .callback(move |query| routes.serve(query))
            .wait()
            .map_err(|e| anyhow::anyhow!("queryable {key}: {e}"))?;
        queryables.push(q);
    }
    // A shard restarted from its disk answers once its coordinator confirmed its placement:
    // it is declared ready after that check, as the Python shard is (within a moment).
    coordinator.wait_checked(std::time::Duration::from_secs(30));
    // Last: once the tokens are up, peers may route to these services.
    for h in &hosted {
        let key = runtime::alive_key(&h.swarm, &h.kind, h.robot);
        tokens.push(
            session
                .liveliness()
                .declare_token(&key)
                .wait()
                .map_err(|e| anyhow::anyhow!("token {key}: {e}"))?,
        );
        h.metrics.registry.set(h.metrics.ready, &[], 1.0);
    }
    for h in &hosted {
        h.service.clone().serving();
    }
    host_metrics.set(host_ready, &[], 1.0);
    if let Some(s) = &server {
        s.set_ready(true);
    }
    let entries: Vec<serde_json::Value> = hosted
        .iter()
        .map(|h| serde_json::json!({"service": h.kind, "robot": h.robot, "metrics_url": h.url}))
        .collect();
    let mut ready = if single {
        let mut e = entries[0].clone();
        e["event"] = "ready".into();
        e
    } else {
        serde_json::json!({"event": "ready", "services": entries})
    };
    ready["dispatch"] = "compiled".into();
    // A router says where it listens, as zenoh bound it (the Python runner's readiness line too).
    let listen: Vec<String> = routers.iter().flat_map(|r| r.locators()).collect();
    if !listen.is_empty() {
        ready["listen"] = listen.clone().into();
    }
    host_log.info("ready", serde_json::json!({"services": entries, "listen": listen}));
    println!("{ready}");
    while !STOP.load(Ordering::SeqCst) {
        coordinator.keep_up();
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    host_log.info("stopping", serde_json::json!({}));
    // Still serving: an index shard hands its groups on first (a scale-down loses nothing).
    std::thread::scope(|scope| {
        for h in &hosted {
            scope.spawn(|| h.service.drain());
        }
    });
    // Drained (the coordinators moved the groups): now the coordinators may go.
    coordinator.stop();
    if let Some(s) = &server {
        s.set_ready(false); // first: a probe must not route to a stopping process
    }
    host_metrics.set(host_ready, &[], 0.0);
    for h in &hosted {
        h.metrics.registry.set(h.metrics.ready, &[], 0.0);
    }
    for t in tokens {
        let _ = t.undeclare().wait();
    }
    for q in queryables {
        let _ = q.undeclare().wait();
    }
    local.clear();
    for h in &hosted {
        h.service.close();
    }
    let _ = session.close().wait();
    if let Some(s) = &server {
        s.close();
    }
    host_log.info("stopped", serde_json::json!({}));
    Ok(())
}
