//! The detector's replay mode, compiled: plays its robot's recorded frames into the
//! robot's descriptor. The contract of `swarmrec/services/detector` (the reference)
//! in replay mode, endpoint for endpoint:
//!
//! * `step` (lock-step replay): frame `step` into the outbox, then the outbox sent to
//!   the descriptor oldest first; the reply carries the frame's report, or `queued`
//!   when it must wait, the reports of earlier queued frames delivered since
//!   (`late_reports`) and what still waits (`pending`); a step past the end flushes the
//!   outbox (`finished`). A frame the descriptor refuses for what it is (not for being
//!   unreachable) is answered with that refusal's code.
//! * `replay` (free replay): the whole block at `rate_hz` (0: as fast as the swarm
//!   answers) on a thread of its own; the descriptor publishes the reports.
//! * `classify`: FAILED_PRECONDITION (the classifier mode stays Python).
//!
//! The frames come ready: the Python reader and codec read the dataset and put each
//! frame on the wire once, before this process starts (`spec.rs`, `DetectorSpec`), so
//! the two implementations send the same bytes. The outbox is the reference's record
//! log (`<data_dir>/outbox.log`: `+`/`-` and the frame index, little-endian), so a data
//! folder moves between them both ways.
//!
//! Why it is compiled: hosted with its robot's descriptor, a frame goes from the one to
//! the other on the step's thread, with no message (`LocalEndpoints`); from a Python
//! detector it was a request through the router and back (docs/dataplane.md).

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use prost::Message;

use crate::caller::{CallError, Caller};
use crate::metrics::ServiceMetrics;
use crate::pb;
use crate::recordlog::RecordLog;
use crate::runtime::{decode, endpoint_key, lock, missing, Endpoint, LocalEndpoints, Log, RequestError, Service};
use crate::spec::ServiceSpec;

/// Late reports kept for the next step's reply (the reference's `LATE_REPORTS`).
const LATE_REPORTS: usize = 10_000;

/// The refusals a sender retries (`swarmrec.errors.TRANSIENT_CODES`; a code this version
/// does not know reads as UNSPECIFIED there, so it is retried too).
fn transient(code: i32) -> bool {
    use pb::ErrorCode as C;
    match C::try_from(code) {
        Ok(c) => matches!(
            c,
            C::Unavailable | C::Timeout | C::FailedPrecondition | C::Internal | C::Unspecified
        ),
        Err(_) => true,
    }
}

/// A frame of the block: its wire bytes, or why it cannot be put on the wire.
enum Frame {
    Wire(Vec<u8>),
    Unsendable(String),
}

fn unhex(text: &str) -> anyhow::Result<Vec<u8>> {
    let bytes = text.as_bytes();
    if bytes.len() % 2 != 0 {
        anyhow::bail!("odd number of hex digits");
    }
    bytes
        .chunks(2)
        .map(|pair| {
            let s = std::str::from_utf8(pair)?;
            Ok(u8::from_str_radix(s, 16)?)
        })
        .collect()
}

/// Frame indices the descriptor has not taken yet, oldest first, on disk
/// (`swarmrec/services/detector/outbox.py`, record for record).
struct Outbox {
    log: RecordLog,
    capacity: usize,
    /// Insertion order -> frame, and frame -> its place in that order.
    order: BTreeMap<u64, u32>,
    place: HashMap<u32, u64>,
    next: u64,
    done: usize,
}

const ADD: u8 = b'+';
const DONE: u8 = b'-';

fn record(tag: u8, frame: u32) -> Vec<u8> {
    let mut r = vec![tag];
    r.extend_from_slice(&frame.to_le_bytes());
    r
}

impl Outbox {
    fn new(log: RecordLog, records: &[Vec<u8>], capacity: usize) -> Outbox {
        let mut o = Outbox {
            log,
            capacity,
            order: BTreeMap::new(),
            place: HashMap::new(),
            next: 0,
            done: 0,
        };
        for r in records {
            if r.len() != 5 {
                continue;
            }
            let frame = u32::from_le_bytes([r[1], r[2], r[3], r[4]]);
            match r[0] {
                ADD => o.insert(frame),
                DONE => {
                    o.remove(frame);
                    o.done += 1;
                }
                _ => {}
            }
        }
        o
    }

    /// Keeps the place of a frame already there (a Python dict's order).
    fn insert(&mut self, frame: u32) {
        if self.place.contains_key(&frame) {
            return;
        }
        self.place.insert(frame, self.next);
        self.order.insert(self.next, frame);
        self.next += 1;
    }

    fn remove(&mut self, frame: u32) -> bool {
        match self.place.remove(&frame) {
            Some(at) => {
                self.order.remove(&at);
                true
            }
            None => false,
        }
    }

    fn len(&self) -> usize {
        self.place.len()
    }

    /// Keeps `frame` until `done` (on disk when this returns); UNAVAILABLE when full.
    fn add(&mut self, frame: u32) -> Result<(), RequestError> {
        if self.place.contains_key(&frame) {
            return Ok(());
        }
        if self.len() >= self.capacity {
            return Err(RequestError::new(
                pb::ErrorCode::Unavailable,
                format!(
                    "{} frames wait for the descriptor (outbox_capacity {}): refusing new ones until it takes them",
                    self.len(),
                    self.capacity
                ),
            ));
        }
        self.log.append(&record(ADD, frame)).map_err(io_error)?;
        self.insert(frame);
        Ok(())
    }

    fn waiting(&self) -> Vec<u32> {
        self.order.values().copied().collect()
    }

    fn done(&mut self, frame: u32) -> Result<(), RequestError> {
        if !self.remove(frame) {
            return Ok(());
        }
        self.log.append(&record(DONE, frame)).map_err(io_error)?;
        self.done += 1;
        if self.done > 1000.max(2 * self.len()) {
            let kept: Vec<Vec<u8>> = self.order.values().map(|&f| record(ADD, f)).collect();
            self.log.rewrite(&kept).map_err(io_error)?;
            self.done = 0;
        }
        Ok(())
    }
}

fn io_error(e: std::io::Error) -> RequestError {
    RequestError::new(pb::ErrorCode::Internal, format!("outbox: {e}"))
}

/// Why the descriptor did not take a frame for good: the step's refusal.
struct Refusal {
    code: pb::ErrorCode,
    text: String,
}

/// What one step or flush holds: the outbox and what came back for later replies.
struct Player {
    outbox: Outbox,
    /// Reports of queued frames the retrier delivered, for the next step's reply.
    late: Vec<pb::QueryReport>,
    /// Frames the descriptor refused for what they are (answered with the step's error).
    refused: HashMap<u32, Refusal>,
}

/// A stop signal threads wait on (`threading.Event` of the reference).
#[derive(Default)]
struct StopSignal {
    stopped: Mutex<bool>,
    cv: Condvar,
}

impl StopSignal {
    /// Waits `d` or until stopped; true when stopped.
    fn wait(&self, d: Duration) -> bool {
        let guard = lock(&self.stopped);
        let (guard, _) = self
            .cv
            .wait_timeout_while(guard, d, |stopped| !*stopped)
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        *guard
    }
    fn is_set(&self) -> bool {
        *lock(&self.stopped)
    }
    fn set(&self) {
        *lock(&self.stopped) = true;
        self.cv.notify_all();
    }
}

pub struct Detector {
    robot: u32,
    n_robots: u32,
    n_labels: u32,
    frames: Vec<Frame>,
    /// The robot's descriptor's `process`.
    key: String,
    caller: Caller,
    timeout: Duration,
    retry: Duration,
    player: Mutex<Player>,
    /// The outbox's length, read by `info` on zenoh's thread without the player's lock
    /// (a step holds that lock while it waits for replies arriving on that thread).
    pending: AtomicUsize,
    replaying: Mutex<Option<std::thread::JoinHandle<()>>>,
    retrier: Mutex<Option<std::thread::JoinHandle<()>>>,
    stop: StopSignal,
    started: AtomicBool,
    metrics: Arc<ServiceMetrics>,
    log: Log,
}

impl Detector {
    pub fn new(
        spec: &ServiceSpec,
        metrics: Arc<ServiceMetrics>,
        log: Log,
        local: Arc<LocalEndpoints>,
    ) -> anyhow::Result<Arc<Detector>> {
        let d = spec
            .detector
            .clone()
            .ok_or_else(|| anyhow::anyhow!("a detector needs its detector settings"))?;
        let frames = d
            .frames
            .iter()
            .enumerate()
            .map(|(t, f)| match (&f.wire, &f.unsendable) {
                (Some(hex), None) => unhex(hex)
                    .map(Frame::Wire)
                    .map_err(|e| anyhow::anyhow!("frame {t}: {e}")),
                (None, Some(why)) => Ok(Frame::Unsendable(why.clone())),
                _ => Err(anyhow::anyhow!(
                    "frame {t}: give either its wire bytes or why it has none"
                )),
            })
            .collect::<anyhow::Result<Vec<Frame>>>()?;
        let dir = spec.data_dir.as_deref();
        let (olog, records) = RecordLog::open(dir.map(|p| p.join("outbox.log")).as_deref(), spec.fsync)?;
        let outbox = Outbox::new(olog, &records, d.outbox_capacity);
        // The reference's families, though replay mode counts nothing in them (they are
        // the RGB-D mode's): a scrape finds the same names whichever implementation runs.
        let r = &metrics.registry;
        r.counter(
            "swarmrec_detector_frames",
            "RGB-D frames the detector handled, by outcome (detected, no_objects, or why it skipped)",
            &["outcome"],
        );
        r.counter(
            "swarmrec_detector_boxes_dropped",
            "Detected boxes left out of the constellation, by reason (no_depth: no valid depth pixel)",
            &["reason"],
        );
        r.counter(
            "swarmrec_detector_objects",
            "Objects in the constellations the detector made",
            &[],
        );
        r.histogram(
            "swarmrec_detector_stage_seconds",
            "Time of one frame in each detector stage (decode, detect, points; describe: the full-image \
             descriptor, place_method dvpr)",
            &["stage"],
        );
        let timeout = Duration::from_secs_f64(d.process_timeout_s.max(0.001));
        let caller = Caller::new(spec.robot, timeout, spec.max_message_bytes, metrics.clone(), local);
        let pending = AtomicUsize::new(outbox.len());
        log.info(
            "dataset loaded",
            serde_json::json!({"dataset": d.dataset, "frames": frames.len()}),
        );
        Ok(Arc::new(Detector {
            robot: spec.robot,
            n_robots: spec.n_robots.max(1),
            n_labels: spec.places.n_labels,
            frames,
            key: endpoint_key(&spec.swarm, "descriptor", spec.robot, "process"),
            caller,
            timeout,
            retry: Duration::from_secs_f64(d.outbox_retry_s.max(0.01)),
            player: Mutex::new(Player {
                outbox,
                late: Vec::new(),
                refused: HashMap::new(),
            }),
            pending,
            replaying: Mutex::new(None),
            retrier: Mutex::new(None),
            stop: StopSignal::default(),
            started: AtomicBool::new(false),
            metrics,
            log,
        }))
    }

    /// Sends frame `t` to the descriptor and waits for its report.
    fn send(&self, t: u32) -> Result<pb::QueryReport, Sent> {
        match &self.frames[t as usize] {
            Frame::Unsendable(why) => {
                let m = &self.metrics;
                m.registry
                    .inc(m.rejected, &["frame", "ERROR_CODE_INVALID_ARGUMENT"], 1.0);
                self.log
                    .warning("frame not sent", serde_json::json!({"frame": t, "reason": why}));
                Err(Sent::Unsendable(format!("frame {t}: {why}")))
            }
            Frame::Wire(bytes) => self
                .caller
                .start_bytes(
                    &self.key,
                    "Constellation",
                    bytes.clone(),
                    Some(self.robot),
                    "process",
                    false,
                )
                .result::<pb::QueryReport>("QueryReport")
                .map_err(Sent::Call),
        }
    }

    /// Sends the waiting frames, oldest first, until one must wait again or `deadline`. A
    /// frame the descriptor refuses for what it is (not for being unreachable) leaves the
    /// outbox: sending it again would be refused again.
    fn flush(&self, p: &mut Player, deadline: Instant) -> Result<Vec<(u32, pb::QueryReport)>, RequestError> {
        let mut delivered = Vec::new();
        let result = (|| {
            for frame in p.outbox.waiting() {
                if Instant::now() > deadline {
                    break;
                }
                match self.send(frame) {
                    Ok(report) => {
                        p.outbox.done(frame)?;
                        delivered.push((frame, report));
                    }
                    Err(Sent::Call(CallError::Remote { code, message })) => {
                        if transient(code) {
                            break;
                        }
                        p.outbox.done(frame)?;
                        let name = pb::ErrorCode::try_from(code).map_or("ERROR_CODE_UNSPECIFIED", |c| c.as_str_name());
                        let text = format!("{}: {name}: {message}", self.key);
                        self.log
                            .warning("frame refused", serde_json::json!({"frame": frame, "reason": text}));
                        let code = pb::ErrorCode::try_from(code).unwrap_or(pb::ErrorCode::Unspecified);
                        p.refused.insert(frame, Refusal { code, text });
                    }
                    Err(Sent::Call(_)) => break, // nobody answered, or not in time
                    Err(Sent::Unsendable(text)) => {
                        p.outbox.done(frame)?;
                        p.refused.insert(
                            frame,
                            Refusal {
                                code: pb::ErrorCode::InvalidArgument,
                                text,
                            },
                        );
                    }
                }
            }
            Ok(())
        })();
        self.pending.store(p.outbox.len(), Ordering::SeqCst);
        result.map(|()| delivered)
    }

    fn step(&self, data: &[u8]) -> Result<pb::StepReply, RequestError> {
        let req: pb::StepRequest = decode(data, "swarmrec.v1.StepRequest")?;
        let step = req.step.ok_or_else(|| missing("swarmrec.v1.StepRequest", "step"))?;
        let deadline = Instant::now() + self.timeout;
        let mut p = lock(&self.player); // steps of one robot run in order
        if step as usize >= self.frames.len() {
            let delivered = self.flush(&mut p, deadline)?;
            let mut late: Vec<pb::QueryReport> = delivered.into_iter().map(|(_, r)| r).collect();
            late.append(&mut p.late);
            return Ok(pb::StepReply {
                robot_id: self.robot,
                step,
                finished: true,
                late_reports: late,
                pending: p.outbox.len() as u32,
                ..Default::default()
            });
        }
        p.outbox.add(step)?;
        self.pending.store(p.outbox.len(), Ordering::SeqCst);
        p.refused.remove(&step);
        let delivered = self.flush(&mut p, deadline)?;
        if let Some(r) = p.refused.remove(&step) {
            return Err(RequestError::new(
                r.code,
                format!("descriptor refused frame {step}: {}", r.text),
            ));
        }
        let (mut own, mut late) = (None, Vec::new());
        for (frame, report) in delivered {
            if frame == step && own.is_none() {
                own = Some(report);
            } else {
                late.push(report);
            }
        }
        late.append(&mut p.late);
        Ok(pb::StepReply {
            robot_id: self.robot,
            step,
            queued: own.is_none(),
            report: own,
            late_reports: late,
            pending: p.outbox.len() as u32,
            ..Default::default()
        })
    }

    fn replay(self: &Arc<Self>, data: &[u8]) -> Result<pb::ReplayReply, RequestError> {
        let req: pb::ReplayRequest = decode(data, "swarmrec.v1.ReplayRequest")?;
        let rate = req
            .rate_hz
            .ok_or_else(|| missing("swarmrec.v1.ReplayRequest", "rate_hz"))?;
        if !(rate.is_finite() && rate >= 0.0) {
            return Err(RequestError::invalid(format!(
                "rate_hz must be >= 0, got {}",
                py_float(f64::from(rate))
            )));
        }
        // Not the player's lock: this runs on zenoh's thread, which a step holding that
        // lock may be waiting on.
        let mut replaying = lock(&self.replaying);
        if replaying.as_ref().is_some_and(|h| !h.is_finished()) {
            return Err(RequestError::new(
                pb::ErrorCode::Unavailable,
                "a replay is already running",
            ));
        }
        let me = self.clone();
        let handle = std::thread::Builder::new()
            .name(format!("replay-{}", self.robot))
            .spawn(move || me.play(f64::from(rate)))
            .map_err(|e| RequestError::new(pb::ErrorCode::Internal, format!("no thread to replay: {e}")))?;
        *replaying = Some(handle);
        Ok(pb::ReplayReply {
            robot_id: self.robot,
            n_frames: self.frames.len() as u32,
        })
    }

    /// The free replay: every frame of the block at `rate_hz` (0: as fast as answered).
    fn play(&self, rate_hz: f64) {
        let period = if rate_hz > 0.0 { 1.0 / rate_hz } else { 0.0 };
        // Robots are not synchronised: each starts at its own phase of the period, or all
        // ten would query at the same instant, every time.
        let start = Instant::now() + Duration::from_secs_f64(period * f64::from(self.robot) / f64::from(self.n_robots));
        let n = self.frames.len();
        for t in 0..n as u32 {
            if self.stop.is_set() {
                return;
            }
            if period > 0.0 {
                let at = start + Duration::from_secs_f64(period * f64::from(t));
                let now = Instant::now();
                if at > now && self.stop.wait(at - now) {
                    return;
                }
            }
            let mut p = lock(&self.player);
            if let Err(e) = p.outbox.add(t) {
                self.log
                    .warning("frame failed", serde_json::json!({"frame": t, "reason": e.message}));
                continue;
            }
            if let Err(e) = self.flush(&mut p, Instant::now() + self.timeout) {
                self.log
                    .emit(40, "sending frames failed", serde_json::json!({"reason": e.message}));
            }
        }
        let waiting = self.pending.load(Ordering::SeqCst);
        self.log
            .info("replay finished", serde_json::json!({"frames": n, "waiting": waiting}));
    }

    /// Sends queued frames again in the background (a free replay, or between steps).
    fn retry_loop(&self) {
        while !self.stop.wait(self.retry) {
            if self.pending.load(Ordering::SeqCst) == 0 {
                continue;
            }
            let Ok(mut p) = self.player.try_lock() else { continue };
            match self.flush(&mut p, Instant::now() + self.timeout) {
                Ok(delivered) => {
                    p.late.extend(delivered.into_iter().map(|(_, r)| r));
                    // A free replay reads them from the events instead.
                    let extra = p.late.len().saturating_sub(LATE_REPORTS);
                    p.late.drain(..extra);
                }
                Err(e) => self.log.emit(
                    40,
                    "sending queued frames failed",
                    serde_json::json!({"reason": e.message}),
                ),
            }
        }
    }

    fn classify(&self, data: &[u8]) -> Result<pb::ClassifyReply, RequestError> {
        let req: pb::ClassifyRequest = decode(data, "swarmrec.v1.ClassifyRequest")?;
        req.round_id
            .ok_or_else(|| missing("swarmrec.v1.ClassifyRequest", "round_id"))?;
        Err(RequestError::new(
            pb::ErrorCode::FailedPrecondition,
            "classify: this detector runs in replay mode (it plays frames)",
        ))
    }
}

/// Why a frame was not delivered.
enum Sent {
    Unsendable(String),
    Call(CallError),
}

/// A double as Python's `repr` writes it (the reference's messages format floats so).
fn py_float(v: f64) -> String {
    if v.is_nan() {
        return "nan".into();
    }
    if v.is_infinite() {
        return if v > 0.0 { "inf".into() } else { "-inf".into() };
    }
    if v == 0.0 {
        return if v.is_sign_negative() {
            "-0.0".into()
        } else {
            "0.0".into()
        };
    }
    // The shortest digits that read back as `v`, then Python's layout: positional for
    // exponents -4 <= e < 16, else d.ddde+XX.
    let sci = format!("{v:e}"); // e.g. "-1.5e-7"
    let (mantissa, exp) = sci.split_once('e').unwrap_or((&sci, "0"));
    let exp: i32 = exp.parse().unwrap_or(0);
    if (-4..16).contains(&exp) {
        let s = format!("{v}");
        if s.contains('.') {
            s
        } else {
            s + ".0"
        }
    } else {
        let sign = if exp < 0 { '-' } else { '+' };
        format!("{mantissa}e{sign}{:02}", exp.abs())
    }
}

impl Service for Detector {
    fn endpoints(self: Arc<Self>) -> Vec<Endpoint> {
        let (a, b, c) = (self.clone(), self.clone(), self);
        vec![
            Endpoint {
                name: "step",
                request: "StepRequest",
                handler: Box::new(move |data, _| a.step(data).map(|r| ("StepReply", r.encode_to_vec()))),
                // It waits for the descriptor's answer (which waits for its peers').
                blocking: true,
            },
            Endpoint {
                name: "replay",
                request: "ReplayRequest",
                handler: Box::new(move |data, _| b.replay(data).map(|r| ("ReplayReply", r.encode_to_vec()))),
                blocking: false,
            },
            Endpoint {
                name: "classify",
                request: "ClassifyRequest",
                handler: Box::new(move |data, _| c.classify(data).map(|r| ("ClassifyReply", r.encode_to_vec()))),
                blocking: false,
            },
        ]
    }

    fn member_info(&self) -> pb::MemberInfo {
        pb::MemberInfo {
            n_labels: self.n_labels,
            pending_items: self.pending.load(Ordering::SeqCst) as u64,
            ..Default::default()
        }
    }

    fn attach(&self, session: &zenoh::Session) -> anyhow::Result<()> {
        self.caller.attach(session);
        Ok(())
    }

    fn serving(self: Arc<Self>) {
        if self.started.swap(true, Ordering::SeqCst) {
            return;
        }
        let me = self.clone();
        match std::thread::Builder::new()
            .name(format!("outbox-{}", self.robot))
            .spawn(move || me.retry_loop())
        {
            Ok(h) => *lock(&self.retrier) = Some(h),
            Err(e) => self.log.warning(
                &format!("no thread to resend queued frames: {e}"),
                serde_json::json!({}),
            ),
        }
    }

    fn close(&self) {
        self.stop.set();
        // A replay or a resend in the middle of a frame finishes it (at most the process
        // timeout); waited for 5 s, as the reference does, then left to end with the process.
        let deadline = Instant::now() + Duration::from_secs(5);
        for slot in [&self.replaying, &self.retrier] {
            let handle = lock(slot).take();
            if let Some(h) = handle {
                while !h.is_finished() && Instant::now() < deadline {
                    std::thread::sleep(Duration::from_millis(10));
                }
                if h.is_finished() {
                    let _ = h.join();
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn outbox(dir: &std::path::Path, capacity: usize) -> Outbox {
        let (log, records) = RecordLog::open(Some(&dir.join("outbox.log")), false).unwrap();
        Outbox::new(log, &records, capacity)
    }

    #[test]
    fn the_outbox_keeps_its_order_and_its_frames_across_a_restart() {
        let dir = std::env::temp_dir().join(format!("swarmrec-outbox-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut o = outbox(&dir, 3);
        for f in [7, 2, 9] {
            o.add(f).unwrap();
        }
        o.add(2).unwrap(); // again: kept where it was, not counted twice
        assert_eq!(o.add(4).unwrap_err().code, pb::ErrorCode::Unavailable);
        o.done(2).unwrap();
        o.done(5).unwrap(); // never there: nothing written
        assert_eq!(o.waiting(), vec![7, 9]);
        let again = outbox(&dir, 3);
        assert_eq!(again.waiting(), vec![7, 9]);
        let raw = std::fs::read(dir.join("outbox.log")).unwrap();
        // 4 records of 5 bytes, each behind its 4-byte length: + 7, + 2, + 9, - 2.
        assert_eq!(raw.len(), 4 * 9);
        assert_eq!(&raw[4..9], &[b'+', 7, 0, 0, 0]);
        assert_eq!(&raw[31..36], &[b'-', 2, 0, 0, 0]);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_outbox_rewrites_its_log_once_mostly_done() {
        let dir = std::env::temp_dir().join(format!("swarmrec-outbox-rw-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut o = outbox(&dir, 10_000);
        for f in 0..1002 {
            o.add(f).unwrap();
        }
        for f in 0..1001 {
            o.done(f).unwrap();
        }
        // 1001 done > max(1000, 2 * 1 left): rewritten to the one frame left.
        assert_eq!(std::fs::read(dir.join("outbox.log")).unwrap().len(), 9);
        assert_eq!(outbox(&dir, 10).waiting(), vec![1001]);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn floats_read_as_python_writes_them() {
        for (v, text) in [
            (-1.0, "-1.0"),
            (-0.5, "-0.5"),
            (f64::from(-0.1f32), "-0.10000000149011612"),
            (-1e-5, "-1e-05"),
            (-2.5e20, "-2.5e+20"),
            (-123456.0, "-123456.0"),
            (f64::NAN, "nan"),
            (f64::NEG_INFINITY, "-inf"),
            (-0.0, "-0.0"),
            (-1e16, "-1e+16"),
            (-0.0001, "-0.0001"),
        ] {
            assert_eq!(py_float(v), text);
        }
    }

    #[test]
    fn transient_refusals_are_the_references() {
        use pb::ErrorCode as C;
        for c in [
            C::Unavailable,
            C::Timeout,
            C::FailedPrecondition,
            C::Internal,
            C::Unspecified,
        ] {
            assert!(transient(c as i32));
        }
        for c in [C::InvalidArgument, C::Malformed, C::TooLarge, C::AlreadyExists] {
            assert!(!transient(c as i32));
        }
        assert!(transient(9999));
    }
}
