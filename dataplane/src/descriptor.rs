//! The descriptor, compiled: turns its robot's constellations into queries. The
//! contract of `swarmrec/services/descriptor.py` and `swarmrec/services/protocol.py`
//! (the reference), endpoint for endpoint:
//!
//! * `process`: a Constellation of this robot -> QueryReport. Stored in the robot's own
//!   verifier first (it is the authority on what frame `t` is: ALREADY_EXISTS refuses
//!   the frame before any shard stores a slice of it); then, with at least
//!   `min_objects` objects, the two-step query: each non-empty slice to an owner of its
//!   label group (the placement, `routing.rs`), the `n_fq` robots with the most
//!   candidates plus this one verify theirs, every slice stored by every owner and
//!   learner of its group. A slice some shard did not acknowledge is kept on disk
//!   (`pending.rs`) and retried in the background. The best verified match the
//!   loop-closure rule accepts is kept (`loop-closures.log`) and published; every
//!   report, with where each candidate stopped in the funnel, is published and counted.
//! * `loop_closures`: the loop closures found so far (at least `min_score` good).
//! * `explain`: the report of one of the last `explain_reports` frames.
//!
//! `process` waits on peers, so it is served on a thread of its own
//! (`Endpoint::blocking`); the requests of one query are all in flight together, and
//! those to this robot's own verifier and shard in this process are served on that
//! thread with no message (`LocalEndpoints`).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use prost::Message;
use zenoh::qos::CongestionControl;
use zenoh::Wait;

use crate::caller::{CallError, Caller, Pending};
use crate::metrics::{Metric, ServiceMetrics};
use crate::pb;
use crate::pending::PendingStores;
use crate::placement::Placement;
use crate::recordlog::RecordLog;
use crate::routing::Routing;
use crate::runtime::{
    declared, decode, encoding, endpoint_key, lock, missing, Endpoint, LocalEndpoints, Log, RequestError, Service,
};
use crate::selection::select_robots;
use crate::spec::{DescriptorSpec, PlaceSpec, ServiceSpec};
use crate::verifier::{objects, MAX_FRAME_INDEX};

/// Rounds of asking a group's owners (`protocol.ROUTE_ATTEMPTS`).
const ROUTE_ATTEMPTS: usize = 3;
/// Pending stores sent again per retry round.
const RETRY_BATCH: usize = 256;

/// `swarmrec.core.funnel.Reason`: the wire's enum, whose numbers the Python one has.
use crate::pb::FunnelReason as Reason;

/// (stage label, reason label) of a wire reason, as `Reason.stage.label`/`Reason.label`
/// name them: the schema's name without its prefix, lowercase; a number this version does
/// not know reads as unspecified.
fn funnel_labels(reason: i32) -> (&'static str, String) {
    let reason = Reason::try_from(reason).unwrap_or(Reason::Unspecified);
    let stage = match reason {
        Reason::Unspecified => "unspecified",
        Reason::BelowShardCut => "shard",
        Reason::RobotNotChosen => "selection",
        Reason::VerifierUnreachable
        | Reason::VerifierTimeout
        | Reason::VerifierError
        | Reason::TooFewMatches
        | Reason::Matched => "verification",
        Reason::BelowScoreThreshold
        | Reason::OwnRecentFrame
        | Reason::Outranked
        | Reason::AlreadyClosed
        | Reason::Accepted => "closure",
    };
    let name = reason.as_str_name();
    (
        stage,
        name.strip_prefix("FUNNEL_REASON_").unwrap_or(name).to_lowercase(),
    )
}

/// The reason for the candidates of a verifier that did not answer as asked.
fn verifier_failure(e: &CallError) -> Reason {
    match e {
        CallError::Timeout(_) => Reason::VerifierTimeout,
        CallError::NoReply => Reason::VerifierUnreachable,
        CallError::Remote { .. } => Reason::VerifierError,
    }
}

/// `ClosureRule.verdicts`: one closure-stage reason per (robot, frame, score), best first.
fn closure_verdicts(
    min_score: f64,
    exclusion: u32,
    query: (u32, u32),
    matches: &[(u32, u32, f64)],
    already_closed: bool,
) -> Vec<Reason> {
    let mut taken = false;
    matches
        .iter()
        .map(|&(robot, frame, score)| {
            #[allow(clippy::neg_cmp_op_on_partial_ord)] // NaN too: never a closure
            if !(score >= min_score) {
                Reason::BelowScoreThreshold
            } else if robot == query.0 && (i64::from(frame) - i64::from(query.1)).abs() <= i64::from(exclusion) {
                Reason::OwnRecentFrame
            } else if taken {
                Reason::Outranked
            } else {
                taken = true;
                if already_closed {
                    Reason::AlreadyClosed
                } else {
                    Reason::Accepted
                }
            }
        })
        .collect()
}

/// `classify`: each distinct candidate frame up to the verification stage, in (robot, frame) order.
fn classify(
    candidates: &[(u32, u32)],
    asked: &[u32],
    failures: &HashMap<u32, Reason>,
    matches: &[(u32, u32, f64)],
) -> Vec<pb::CandidateOutcome> {
    let scores: HashMap<(u32, u32), f64> = matches.iter().map(|&(r, f, s)| ((r, f), s)).collect();
    let keys: BTreeSet<(u32, u32)> = candidates.iter().copied().chain(scores.keys().copied()).collect();
    keys.into_iter()
        .map(|(r, f)| {
            let reason = if !asked.contains(&r) {
                Reason::RobotNotChosen
            } else if let Some(why) = failures.get(&r) {
                *why
            } else if scores.contains_key(&(r, f)) {
                Reason::Matched
            } else {
                Reason::TooFewMatches
            };
            pb::CandidateOutcome {
                robot_id: r,
                frame_index: f,
                reason: reason as i32,
            }
        })
        .collect()
}

/// `match_scores`: (score, semantic score) of a verified match, the doubles the verifier computed.
fn match_scores(m: &pb::VerifyMatch) -> Option<(f64, f64)> {
    if !(0 < m.n_common && m.n_common <= m.n_union) || m.n_matched > m.n_common {
        return None;
    }
    let semantic = f64::from(m.n_common) / f64::from(m.n_union);
    Some((semantic * (f64::from(m.n_matched) / f64::from(m.n_common)), semantic))
}

/// `candidates_from_proto`'s checks: (robot, frame) of each candidate, or None for an
/// inconsistent reply.
fn candidates_of(reply: &pb::CandidatesReply, n_labels: u32) -> Option<Vec<(u32, u32)>> {
    let n = reply.robot_ids.len();
    let names_range = reply.label_lo != 0 || reply.label_hi != 0;
    if (names_range && !(reply.label_lo < reply.label_hi && reply.label_hi <= n_labels))
        || reply.frame_indices.len() != n
        || !(reply.scores.is_empty() || reply.scores.len() == n)
        || reply.scores.iter().any(|s| !s.is_finite())
    {
        return None;
    }
    Some(
        reply
            .robot_ids
            .iter()
            .copied()
            .zip(reply.frame_indices.iter().copied())
            .collect(),
    )
}

/// `partial_descriptor_to_proto`: the slice `[lo, hi)` of a dense count vector.
fn partial(desc: &[u32], lo: u32, hi: u32, robot: u32, frame: u32) -> pb::PartialDescriptor {
    let slice = &desc[lo as usize..hi as usize];
    let offsets: Vec<u32> = (0..slice.len() as u32).filter(|&i| slice[i as usize] != 0).collect();
    pb::PartialDescriptor {
        robot_id: robot,
        frame_index: frame,
        query_step: 0,
        label_lo: lo,
        label_hi: hi,
        counts: offsets.iter().map(|&i| slice[i as usize]).collect(),
        label_offsets: offsets,
    }
}

fn any_in(desc: &[u32], lo: u32, hi: u32) -> bool {
    desc[lo as usize..hi as usize].iter().any(|&c| c != 0)
}

struct Ids {
    loop_closures: Metric,
    query_seconds: Metric,
    pending_stores: Metric,
    store_retries: Metric,
    placement_refreshes: Metric,
    frames: Metric,
    funnel: Metric,
}

/// What `process`, `loop_closures` and `explain` share.
struct Memory {
    closure_log: RecordLog,
    closures: Vec<pb::LoopClosure>,
    /// Query frames that have their loop closure: a frame processed again adds none.
    closed: BTreeSet<u32>,
    /// The last reports, serialized, oldest first (by the order they were kept in).
    reports: BTreeMap<u64, u32>,
    report_of: HashMap<u32, (u64, Vec<u8>)>,
    next: u64,
    /// One bit per frame index processed since the start.
    seen: Vec<u8>,
}

pub struct Descriptor {
    swarm: String,
    robot: u32,
    n_robots: u32,
    places: PlaceSpec,
    spec: DescriptorSpec,
    caller: Caller,
    routing: Routing,
    pending: Mutex<PendingStores>,
    /// Passes over the pending stores finished (`PendingStores::next_batch`), said in
    /// `MemberInfo.pending_passes`.
    pending_passes: AtomicU64,
    memory: Mutex<Memory>,
    metrics: Arc<ServiceMetrics>,
    ids: Ids,
    log: Log,
    session: OnceLock<zenoh::Session>,
    stopping: Arc<AtomicBool>,
    retrier: Mutex<Option<std::thread::JoinHandle<()>>>,
}

/// One group's partial query in flight.
struct GroupAsk<'a> {
    group: usize,
    request: pb::PartialQuery,
    owners: Vec<u32>,
    shard: u32,
    pending: Option<Pending<'a>>,
    tried: Vec<u32>,
}

struct Store<'a> {
    group: usize,
    shard: u32,
    /// The placement version the store was routed with.
    version: u64,
    pending: Pending<'a>,
}

impl Descriptor {
    pub fn new(
        spec: &ServiceSpec,
        metrics: Arc<ServiceMetrics>,
        log: Log,
        local: Arc<LocalEndpoints>,
    ) -> anyhow::Result<Arc<Descriptor>> {
        let d = spec
            .descriptor
            .clone()
            .ok_or_else(|| anyhow::anyhow!("a descriptor needs its descriptor settings"))?;
        let first = pb::Placement::decode(d.initial_placement.as_slice())
            .map_err(|e| anyhow::anyhow!("initial placement: {e}"))
            .and_then(|p| Placement::from_proto(&p, spec.places.n_labels).map_err(|e| anyhow::anyhow!(e)))?;
        let dir = spec.data_dir.as_deref();
        let (plog, precords) = RecordLog::open(dir.map(|p| p.join("pending-stores.log")).as_deref(), spec.fsync)?;
        let (clog, crecords) = RecordLog::open(dir.map(|p| p.join("loop-closures.log")).as_deref(), spec.fsync)?;
        let closures: Vec<pb::LoopClosure> = crecords
            .iter()
            .filter_map(|r| pb::LoopClosure::decode(r.as_slice()).ok())
            .collect();
        let closed = closures.iter().map(|c| c.query_frame_index).collect();
        let r = &metrics.registry;
        let ids = Ids {
            pending_stores: r.gauge(
                "swarmrec_descriptor_pending_stores",
                "Descriptor slices not yet acknowledged by every shard that must hold them (kept on disk)",
                &[],
            ),
            store_retries: r.counter(
                "swarmrec_descriptor_store_retries",
                "Stores sent again to a shard that had not acknowledged them",
                &[],
            ),
            placement_refreshes: r.counter(
                "swarmrec_descriptor_placement_refreshes",
                "Times this descriptor fetched the index placement again (a shard said it was stale)",
                &[],
            ),
            loop_closures: r.counter("swarmrec_loop_closures", "Loop closures found by this robot", &[]),
            query_seconds: r.histogram(
                "swarmrec_query_duration_seconds",
                "Time of one two-step query, frame in to last verifier reply",
                &[],
            ),
            frames: r.counter(
                "swarmrec_descriptor_frames",
                "Frames this robot's descriptor processed, by outcome (queried, too_few_objects, not_stored)",
                &["outcome"],
            ),
            funnel: r.counter(
                "swarmrec_funnel_candidates",
                "Candidates of this robot's queries, by the loop-closure funnel stage and reason they \
                 stopped at (accepted: the loop closures)",
                &["stage", "reason"],
            ),
        };
        // Every label value exists from the start (at 0), as the reference creates them.
        for outcome in ["queried", "too_few_objects", "not_stored"] {
            r.inc(ids.frames, &[outcome], 0.0);
        }
        for reason in 2..=12 {
            if reason != Reason::Matched as i32 {
                let (stage, label) = funnel_labels(reason);
                r.inc(ids.funnel, &[stage, &label], 0.0);
            }
        }
        r.inc(ids.loop_closures, &[], 0.0);
        r.inc(ids.store_retries, &[], 0.0);
        r.inc(ids.placement_refreshes, &[], 0.0);
        let pending = PendingStores::new(plog, precords, d.pending_capacity);
        r.set(ids.pending_stores, &[], pending.len() as f64);
        let caller = Caller::new(
            spec.robot,
            Duration::from_secs_f64(d.request_timeout_s),
            spec.max_message_bytes,
            metrics.clone(),
            local,
        );
        Ok(Arc::new(Descriptor {
            swarm: spec.swarm.clone(),
            robot: spec.robot,
            n_robots: spec.n_robots,
            places: spec.places.clone(),
            routing: Routing::new(&spec.swarm, first, d.suspect_s),
            spec: d,
            caller,
            pending: Mutex::new(pending),
            pending_passes: AtomicU64::new(0),
            memory: Mutex::new(Memory {
                closure_log: clog,
                closures,
                closed,
                reports: BTreeMap::new(),
                report_of: HashMap::new(),
                next: 0,
                seen: vec![0; (MAX_FRAME_INDEX / 8) as usize],
            }),
            metrics,
            ids,
            log,
            session: OnceLock::new(),
            stopping: Arc::new(AtomicBool::new(false)),
            retrier: Mutex::new(None),
        }))
    }

    fn refreshed(&self) {
        self.metrics.registry.inc(self.ids.placement_refreshes, &[], 1.0);
    }

    /// The placement to route with after a request routed with version `routed` was refused
    /// by `from` (see `Routing::refresh`).
    fn refresh(&self, from: &BTreeSet<u32>, routed: u64) -> Placement {
        self.routing.refresh(&self.caller, from, routed, &|| self.refreshed())
    }

    fn publish<M: Message>(&self, name: &str, schema: &'static str, msg: &M) {
        let Some(session) = self.session.get() else { return };
        let payload = msg.encode_to_vec();
        self.metrics.count_sent(schema, "client", payload.len());
        let key = format!("swarmrec/v1/{}/events/{name}/{}", self.swarm, self.robot);
        let Some(key) = declared(session, &key) else { return };
        let _ = session
            .put(key, payload)
            .encoding(encoding(schema))
            .congestion_control(CongestionControl::Block)
            .wait();
    }

    // --- process -------------------------------------------------------------------

    fn process(&self, data: &[u8]) -> Result<pb::QueryReport, RequestError> {
        let msg: pb::Constellation = decode(data, "swarmrec.v1.Constellation")?;
        let robot_id = msg
            .robot_id
            .ok_or_else(|| missing("swarmrec.v1.Constellation", "robot_id"))?;
        let frame = msg
            .frame_index
            .ok_or_else(|| missing("swarmrec.v1.Constellation", "frame_index"))?;
        let robot = self.robot;
        if robot_id != robot {
            return Err(RequestError::invalid(format!(
                "descriptor {robot} queries only its own robot's frames, got robot {robot_id}"
            )));
        }
        if frame >= MAX_FRAME_INDEX {
            return Err(RequestError::invalid(format!(
                "frame index must be below {MAX_FRAME_INDEX}, got {frame}"
            )));
        }
        let (labels, _) = objects(&msg, &self.places)?;
        {
            let pending = lock(&self.pending);
            if pending.room() < self.routing.groups().len() {
                return Err(RequestError::new(
                    pb::ErrorCode::Unavailable,
                    format!(
                        "{} stores are waiting for index shards to acknowledge them: refusing new frames \
                         until they are (the shards are gone or unreachable)",
                        pending.len()
                    ),
                ));
            }
        }
        let t0 = Instant::now();
        let key = endpoint_key(&self.swarm, "verifier", robot, "store");
        let stored = self
            .caller
            .start(&key, "Constellation", &msg, Some(robot), "store", false)
            .result::<pb::StoreReply>("StoreReply");
        if let Err(e) = stored {
            self.metrics.registry.inc(self.ids.frames, &["not_stored"], 1.0);
            return Err(match e {
                CallError::Remote { code, message } if code == pb::ErrorCode::AlreadyExists as i32 => {
                    RequestError::new(pb::ErrorCode::AlreadyExists, format!("frame {frame}: {message}"))
                }
                e => RequestError::new(
                    pb::ErrorCode::Unavailable,
                    format!("own verifier did not store the frame: {key}: {e}"),
                ),
            });
        }
        let mut report = if labels.len() as u32 >= self.spec.min_objects {
            self.two_step_query(&msg, &labels, frame)?
        } else {
            pb::QueryReport {
                robot_id: robot,
                frame_index: frame,
                queried: false,
                ..Default::default()
            }
        };
        let waiting = lock(&self.pending).len();
        self.metrics.registry.set(self.ids.pending_stores, &[], waiting as f64);
        report.n_objects = labels.len() as u32;
        report.duration_us = u32::try_from(t0.elapsed().as_micros()).unwrap_or(u32::MAX);
        let reg = &self.metrics.registry;
        reg.observe(self.ids.query_seconds, &[], f64::from(report.duration_us) / 1e6);
        let outcome = if report.queried { "queried" } else { "too_few_objects" };
        reg.inc(self.ids.frames, &[outcome], 1.0);
        if report.queried {
            self.loop_closure(&mut report);
        }
        for o in &report.candidates {
            let (stage, label) = funnel_labels(o.reason);
            reg.inc(self.ids.funnel, &[stage, &label], 1.0);
        }
        self.remember(&report);
        // Every frame's report, queried or not, so a listener can count frames.
        self.publish("query", "QueryReport", &report);
        Ok(report)
    }

    fn two_step_query(
        &self,
        wire: &pb::Constellation,
        labels: &[u32],
        frame: u32,
    ) -> Result<pb::QueryReport, RequestError> {
        let robot = self.robot;
        let mut report = pb::QueryReport {
            robot_id: robot,
            frame_index: frame,
            queried: true,
            ..Default::default()
        };
        let mut desc = vec![0u32; self.places.n_labels as usize];
        for &l in labels {
            desc[l as usize] += 1;
        }
        let mut stores = Vec::new();
        let (replies, answered) = self.ask_shards(&desc, frame, &mut report, &mut stores);
        let (mut cand_robot, mut cand_frame) = (Vec::new(), Vec::new());
        for (g, reply) in &replies {
            let served_by = answered.iter().find(|(ag, _)| ag == g).map_or(0, |(_, s)| *s);
            let Some(found) = candidates_of(reply, self.places.n_labels) else {
                report.failed_shard_robot_ids.push(served_by);
                continue;
            };
            let before = cand_robot.len();
            for (r, f) in found {
                if r < self.n_robots {
                    cand_robot.push(r);
                    cand_frame.push(f);
                }
            }
            report.shard_candidates.push(pb::ShardCandidates {
                robot_id: served_by,
                n_candidates: (cand_robot.len() - before) as u32,
                group: *g as u32,
            });
        }
        report.n_candidates = cand_robot.len() as u32;
        // Step 2: the full constellation to the chosen robots that have candidates.
        let robots: Vec<usize> = cand_robot.iter().map(|&r| r as usize).collect();
        let chosen = select_robots(&robots, self.spec.n_fq as usize, Some(robot as usize));
        // The verifiers need the objects, not the frame's name; a robot or frame of 0 is left
        // absent. Another robot's verifier gets the objects alone (it takes the query's robot
        // from the caller's id, and with the robots differing the frame cannot matter).
        let objects_only = pb::Constellation {
            labels: wire.labels.clone(),
            positions_mm: wire.positions_mm.clone(),
            positions_m: wire.positions_m.clone(),
            ..Default::default()
        };
        let query = pb::Constellation {
            robot_id: Some(robot).filter(|&r| r != 0),
            frame_index: Some(frame).filter(|&f| f != 0),
            labels: wire.labels.clone(),
            positions_mm: wire.positions_mm.clone(),
            positions_m: wire.positions_m.clone(),
            ..Default::default()
        };
        let mut verifying = Vec::new();
        for r in chosen {
            let r = r as u32;
            let frames: BTreeSet<u32> = cand_robot
                .iter()
                .zip(&cand_frame)
                .filter(|(cr, _)| **cr == r)
                .map(|(_, f)| *f)
                .collect();
            if frames.is_empty() {
                continue; // a robot chosen to fill the list has nothing to verify
            }
            report.verified_robot_ids.push(r);
            let request = pb::VerifyRequest {
                query_id: 0,
                query: Some(if r == robot {
                    query.clone()
                } else {
                    objects_only.clone()
                }),
                candidate_frame_indices: frames.into_iter().collect(),
                ..Default::default()
            };
            let key = endpoint_key(&self.swarm, "verifier", r, "verify");
            verifying.push((
                r,
                self.caller
                    .start(&key, "VerifyRequest", &request, Some(r), "verify", false),
            ));
        }
        // The replicas' stores left with step 1; those it could not know of leave now.
        self.start_replica_stores(&desc, frame, &answered, &mut stores);
        let mut pairs: Vec<pb::VerifiedPair> = Vec::new();
        let mut failures: HashMap<u32, Reason> = HashMap::new();
        for (r, pending) in verifying {
            let vreply = match pending.result::<pb::VerifyReply>("VerifyReply") {
                Ok(v) => v,
                Err(e) => {
                    report.failed_verifier_robot_ids.push(r);
                    failures.insert(r, verifier_failure(&e));
                    continue;
                }
            };
            let scored: Option<Vec<_>> = if vreply.robot_id == r {
                vreply.matches.iter().map(|m| match_scores(m).map(|s| (m, s))).collect()
            } else {
                None
            };
            let Some(scored) = scored else {
                self.caller.count_failure("verify", "error");
                report.failed_verifier_robot_ids.push(r);
                failures.insert(r, Reason::VerifierError);
                continue;
            };
            for (m, (score, semantic)) in scored {
                pairs.push(pb::VerifiedPair {
                    match_robot_id: r,
                    match_frame_index: m.frame_index,
                    score,
                    semantic_score: semantic,
                    n_matched: m.n_matched,
                });
            }
        }
        pairs.sort_by(|a, b| {
            b.score
                .partial_cmp(&a.score)
                .unwrap_or(std::cmp::Ordering::Equal)
                .then(a.match_robot_id.cmp(&b.match_robot_id))
                .then(a.match_frame_index.cmp(&b.match_frame_index))
        });
        let matched: Vec<(u32, u32, f64)> = pairs
            .iter()
            .map(|p| (p.match_robot_id, p.match_frame_index, p.score))
            .collect();
        report.matches = pairs;
        let candidates: Vec<(u32, u32)> = cand_robot.into_iter().zip(cand_frame).collect();
        report.candidates = classify(&candidates, &report.verified_robot_ids, &failures, &matched);
        self.finish_replica_stores(stores, &desc, frame, &answered)?;
        report.duration_us = 0;
        Ok(report)
    }

    fn send<'a>(&'a self, ask: &mut GroupAsk<'a>, shard: u32, version: u64) {
        ask.shard = shard;
        ask.tried.push(shard);
        ask.request.placement_version = version;
        let key = endpoint_key(&self.swarm, "index-shard", shard, "query");
        ask.pending = Some(
            self.caller
                .start(&key, "PartialQuery", &ask.request, Some(shard), "shard_query", false),
        );
    }

    /// Step 1 (`ask_shards`): every non-empty slice to an owner of its group, all in flight
    /// together, and its store to the group's other owners and learners right behind them
    /// (into `stores`: acknowledged while the shards search, not after the verifiers);
    /// (group, reply) in the order answered and, per group answered, the shard that
    /// answered (it stored the slice with its search).
    #[allow(clippy::type_complexity)]
    fn ask_shards<'a>(
        &'a self,
        desc: &[u32],
        frame: u32,
        report: &mut pb::QueryReport,
        stores: &mut Vec<Store<'a>>,
    ) -> (Vec<(usize, pb::CandidatesReply)>, Vec<(usize, u32)>) {
        let robot = self.robot;
        let mut placement = self.routing.placement();
        let mut asks: Vec<GroupAsk<'_>> = Vec::new();
        for (g, &(lo, hi)) in placement.groups.iter().enumerate() {
            if !any_in(desc, lo, hi) {
                continue;
            }
            let request = pb::PartialQuery {
                query_id: 0,
                // n_ret 0: the shards' own, which the swarm shares (costs no byte).
                n_ret: 0,
                descriptor: Some(partial(desc, lo, hi, robot, frame)),
                read_only: false,
                include_scores: false,
                placement_version: 0,
            };
            let owners = self.routing.owners_in_order(&placement, g, robot, frame);
            let mut ask = GroupAsk {
                group: g,
                request,
                owners,
                shard: 0,
                pending: None,
                tried: Vec::new(),
            };
            if let Some(&first) = ask.owners.first() {
                self.send(&mut ask, first, placement.version);
            }
            asks.push(ask);
        }
        for ask in &asks {
            if let Some(&asked) = ask.tried.first() {
                self.store_group(stores, &placement, ask.group, desc, frame, Some(asked));
            }
        }
        let mut replies = Vec::new();
        let mut answered: Vec<(usize, u32)> = Vec::new();
        for attempt in 0..ROUTE_ATTEMPTS {
            let mut retry: Vec<usize> = Vec::new();
            let mut stale: BTreeSet<u32> = BTreeSet::new();
            for (i, ask) in asks.iter_mut().enumerate() {
                let Some(pending) = ask.pending.take() else { continue };
                match pending.result::<pb::CandidatesReply>("CandidatesReply") {
                    Ok(reply) => {
                        replies.push((ask.group, reply));
                        answered.push((ask.group, ask.shard));
                    }
                    Err(CallError::Remote { code, .. }) => {
                        if code != pb::ErrorCode::FailedPrecondition as i32 {
                            continue; // a refusal of the request itself: another owner would refuse it too
                        }
                        stale.insert(ask.shard);
                        retry.push(i);
                    }
                    Err(_) => {
                        self.routing.suspect(ask.shard);
                        retry.push(i);
                    }
                }
            }
            if retry.is_empty() || attempt == ROUTE_ATTEMPTS - 1 {
                break;
            }
            let mut moved = false;
            if !stale.is_empty() {
                let before = placement.version;
                placement = self.refresh(&stale, before);
                moved = placement.version != before;
            }
            for i in retry {
                let ask = &mut asks[i];
                let owners = self.routing.owners_in_order(&placement, ask.group, robot, frame);
                // The placement moved on: its first owner. Otherwise the next owner not asked yet.
                let fresh: Vec<u32> = if moved {
                    owners
                } else {
                    owners.into_iter().filter(|o| !ask.tried.contains(o)).collect()
                };
                if let Some(&first) = fresh.first() {
                    self.send(ask, first, placement.version);
                }
            }
        }
        for ask in &asks {
            if answered.iter().any(|(g, _)| *g == ask.group) {
                continue;
            }
            let shards = if ask.tried.is_empty() {
                ask.owners.iter().take(1).copied().collect()
            } else {
                ask.tried.clone()
            };
            for shard in shards {
                if !report.failed_shard_robot_ids.contains(&shard) {
                    report.failed_shard_robot_ids.push(shard);
                }
            }
        }
        (replies, answered)
    }

    fn store_to<'a>(&'a self, group: usize, shard: u32, msg: &pb::ShardStore) -> Store<'a> {
        let key = endpoint_key(&self.swarm, "index-shard", shard, "store");
        Store {
            group,
            shard,
            version: msg.placement_version,
            pending: self
                .caller
                .start(&key, "ShardStore", msg, Some(shard), "shard_store", false),
        }
    }

    /// A ShardStore of each answered group's slice to its other owners and learners that
    /// the stores started with step 1 missed: where another owner than the one first
    /// asked answered, or the placement moved meanwhile (`stores` has the others).
    fn start_replica_stores<'a>(
        &'a self,
        desc: &[u32],
        frame: u32,
        answered: &[(usize, u32)],
        stores: &mut Vec<Store<'a>>,
    ) {
        let placement = self.routing.placement();
        for &(g, served_by) in answered {
            self.store_group(stores, &placement, g, desc, frame, Some(served_by));
        }
    }

    /// A ShardStore of `group`'s slice, under `placement`, to each of the group's owners and
    /// learners but `skip` (the shard that stored it with its search) and those `stores`
    /// holds already.
    fn store_group<'a>(
        &'a self,
        stores: &mut Vec<Store<'a>>,
        placement: &Placement,
        group: usize,
        desc: &[u32],
        frame: u32,
        skip: Option<u32>,
    ) {
        let (lo, hi) = placement.groups[group];
        let msg = pb::ShardStore {
            descriptor: Some(partial(desc, lo, hi, self.robot, frame)),
            placement_version: placement.version,
        };
        for shard in placement.store_targets(group) {
            let sent = stores.iter().any(|st| st.group == group && st.shard == shard);
            if Some(shard) != skip && !sent {
                stores.push(self.store_to(group, shard, &msg));
            }
        }
    }

    /// The replicas' acknowledgements (`finish_replica_stores`): a group a shard refused as
    /// routed with another placement is stored again at once with the refreshed one; each
    /// slice some shard still did not acknowledge (and each no owner answered for) is queued.
    fn finish_replica_stores<'a>(
        &'a self,
        mut stores: Vec<Store<'a>>,
        desc: &[u32],
        frame: u32,
        answered: &[(usize, u32)],
    ) -> Result<(), RequestError> {
        let groups = self.routing.placement().groups;
        let mut missed: BTreeSet<usize> = groups
            .iter()
            .enumerate()
            .filter(|(g, &(lo, hi))| any_in(desc, lo, hi) && !answered.iter().any(|(ag, _)| ag == g))
            .map(|(g, _)| g)
            .collect();
        for attempt in 0..ROUTE_ATTEMPTS {
            let mut stale: BTreeSet<usize> = BTreeSet::new();
            let mut refused_by: BTreeSet<u32> = BTreeSet::new();
            let mut routed = u64::MAX;
            for st in stores.drain(..) {
                match st.pending.result::<pb::StoreReply>("StoreReply") {
                    Ok(_) => {}
                    Err(CallError::Remote { code, .. }) if code == pb::ErrorCode::FailedPrecondition as i32 => {
                        stale.insert(st.group);
                        refused_by.insert(st.shard);
                        routed = routed.min(st.version);
                    }
                    // Stored there with other content: not ours to fix.
                    Err(CallError::Remote { code, .. }) if code == pb::ErrorCode::AlreadyExists as i32 => {}
                    Err(_) => {
                        missed.insert(st.group);
                    }
                }
            }
            stale.retain(|g| !missed.contains(g));
            if stale.is_empty() {
                break;
            }
            if attempt == ROUTE_ATTEMPTS - 1 {
                missed.extend(stale);
                break;
            }
            let placement = self.refresh(&refused_by, routed);
            for g in stale {
                self.store_group(&mut stores, &placement, g, desc, frame, None);
            }
        }
        let mut pending = lock(&self.pending);
        for g in missed {
            let (lo, hi) = groups[g];
            pending
                .add(&partial(desc, lo, hi, self.robot, frame))
                .map_err(|m| RequestError::new(pb::ErrorCode::Unavailable, m))?;
        }
        Ok(())
    }

    /// Keeps and publishes the loop closure the rule takes from the report's matches (if
    /// any), and puts the rule's verdict on each matched candidate of the report's funnel.
    fn loop_closure(&self, report: &mut pb::QueryReport) {
        let robot = self.robot;
        let matches: Vec<(u32, u32, f64)> = report
            .matches
            .iter()
            .map(|m| (m.match_robot_id, m.match_frame_index, m.score))
            .collect();
        let mut closure = None;
        let verdicts = {
            let mut mem = lock(&self.memory);
            let already = mem.closed.contains(&report.frame_index);
            let verdicts = closure_verdicts(
                self.spec.loop_closure_min_score,
                self.spec.exclusion,
                (robot, report.frame_index),
                &matches,
                already,
            );
            for (m, v) in report.matches.iter().zip(&verdicts) {
                if *v == Reason::Accepted {
                    let c = pb::LoopClosure {
                        query_robot_id: robot,
                        query_frame_index: report.frame_index,
                        match_robot_id: m.match_robot_id,
                        match_frame_index: m.match_frame_index,
                        score: m.score,
                        semantic_score: m.semantic_score,
                        n_matched: m.n_matched,
                        unix_time_ns: SystemTime::now()
                            .duration_since(UNIX_EPOCH)
                            .map_or(0, |d| d.as_nanos() as u64),
                    };
                    if let Err(e) = mem.closure_log.append(&c.encode_to_vec()) {
                        self.log
                            .warning(&format!("loop closure not logged: {e}"), serde_json::json!({}));
                    }
                    mem.closures.push(c);
                    mem.closed.insert(report.frame_index);
                    closure = Some(c);
                }
            }
            verdicts
        };
        let by_pair: HashMap<(u32, u32), Reason> = matches
            .iter()
            .zip(&verdicts)
            .map(|(&(r, f, _), &v)| ((r, f), v))
            .collect();
        for o in &mut report.candidates {
            if o.reason == Reason::Matched as i32 {
                if let Some(v) = by_pair.get(&(o.robot_id, o.frame_index)) {
                    o.reason = *v as i32;
                }
            }
        }
        if let Some(c) = closure {
            self.metrics.registry.inc(self.ids.loop_closures, &[], 1.0);
            self.publish("loop_closure", "LoopClosure", &c);
        }
    }

    fn remember(&self, report: &pb::QueryReport) {
        let f = report.frame_index;
        let kept = self.spec.explain_reports as usize;
        let data = if kept > 0 { report.encode_to_vec() } else { Vec::new() };
        let mut mem = lock(&self.memory);
        mem.seen[(f >> 3) as usize] |= 1 << (f & 7);
        if kept == 0 {
            return;
        }
        let seq = mem.next;
        mem.next += 1;
        if let Some((old, _)) = mem.report_of.insert(f, (seq, data)) {
            mem.reports.remove(&old);
        }
        mem.reports.insert(seq, f);
        while mem.reports.len() > kept {
            if let Some((_, oldest)) = mem.reports.pop_first() {
                mem.report_of.remove(&oldest);
            }
        }
    }

    // --- explain, loop_closures ------------------------------------------------------

    fn explain(&self, data: &[u8]) -> Result<pb::ExplainReply, RequestError> {
        let req: pb::ExplainRequest = decode(data, "swarmrec.v1.ExplainRequest")?;
        let f = req
            .frame_index
            .ok_or_else(|| missing("swarmrec.v1.ExplainRequest", "frame_index"))?;
        if f >= MAX_FRAME_INDEX {
            return Err(RequestError::invalid(format!(
                "frame index must be below {MAX_FRAME_INDEX}, got {f}"
            )));
        }
        let mut reply = pb::ExplainReply {
            robot_id: self.robot,
            reports_kept: self.spec.explain_reports,
            loop_closure_min_score: self.spec.loop_closure_min_score,
            exclusion: self.spec.exclusion,
            min_objects: self.spec.min_objects,
            n_ret: self.spec.n_ret,
            n_fq: self.spec.n_fq,
            ..Default::default()
        };
        let mem = lock(&self.memory);
        let held = mem.report_of.get(&f).map(|(_, d)| d.clone());
        let seen = mem.seen[(f >> 3) as usize] & (1 << (f & 7)) != 0;
        reply.reports_held = mem.reports.len() as u32;
        if let (Some((_, &oldest)), Some((_, &newest))) = (mem.reports.first_key_value(), mem.reports.last_key_value())
        {
            reply.oldest_frame_index = oldest;
            reply.newest_frame_index = newest;
        }
        drop(mem);
        if let Some(data) = held {
            reply.status = pb::ReportStatus::Held as i32;
            reply.report = pb::QueryReport::decode(data.as_slice()).ok();
        } else if seen {
            reply.status = pb::ReportStatus::AgedOut as i32;
        } else {
            reply.status = pb::ReportStatus::NotSeen as i32;
        }
        Ok(reply)
    }

    fn loop_closures(&self, data: &[u8]) -> Result<pb::LoopClosureList, RequestError> {
        let req: pb::LoopClosuresRequest = decode(data, "swarmrec.v1.LoopClosuresRequest")?;
        if !req.min_score.is_finite() {
            // NaN compares false with everything and no score reaches inf: the answer would be
            // an empty list, indistinguishable from "none found".
            let shown = if req.min_score.is_nan() {
                "nan".to_string()
            } else if req.min_score > 0.0 {
                "inf".to_string()
            } else {
                "-inf".to_string()
            };
            return Err(RequestError::invalid(format!(
                "min_score must be a finite number, got {shown}"
            )));
        }
        let min = f64::from(req.min_score);
        let mem = lock(&self.memory);
        Ok(pb::LoopClosureList {
            robot_id: self.robot,
            loop_closures: mem.closures.iter().filter(|c| c.score >= min).cloned().collect(),
        })
    }

    // --- pending stores ---------------------------------------------------------------

    /// Sends every waiting slice to every shard that must hold it under the current
    /// placement; done with those all of them acknowledged.
    fn retry_once(&self) {
        let (waiting, ends_pass) = lock(&self.pending).next_batch(RETRY_BATCH);
        if waiting.is_empty() {
            if ends_pass {
                self.pending_passes.fetch_add(1, Ordering::SeqCst);
            }
            return;
        }
        let placement = self.routing.placement();
        let mut sent = Vec::new();
        for d in waiting {
            let Some(g) = placement.group_of_range(d.label_lo, d.label_hi) else {
                // Of groups the swarm no longer has: nowhere to store it.
                let _ = lock(&self.pending).done(&d);
                continue;
            };
            let msg = pb::ShardStore {
                descriptor: Some(d.clone()),
                placement_version: placement.version,
            };
            let asked: Vec<Store<'_>> = placement
                .store_targets(g)
                .into_iter()
                .map(|shard| self.store_to(g, shard, &msg))
                .collect();
            sent.push((d, asked));
        }
        let mut stale = BTreeSet::new();
        let routed = placement.version;
        for (d, asked) in sent {
            let mut acked = true;
            for st in asked {
                self.metrics.registry.inc(self.ids.store_retries, &[], 1.0);
                match st.pending.result::<pb::StoreReply>("StoreReply") {
                    Ok(_) => {}
                    Err(CallError::Remote { code, .. }) => {
                        if code == pb::ErrorCode::FailedPrecondition as i32 {
                            stale.insert(st.shard);
                        }
                        acked = acked && code == pb::ErrorCode::AlreadyExists as i32;
                    }
                    Err(_) => acked = false,
                }
            }
            if acked {
                if let Err(e) = lock(&self.pending).done(&d) {
                    self.log.warning(&format!("pending stores: {e}"), serde_json::json!({}));
                }
            }
        }
        if !stale.is_empty() {
            self.refresh(&stale, routed);
        }
        if ends_pass {
            self.pending_passes.fetch_add(1, Ordering::SeqCst);
        }
        let n = lock(&self.pending).len();
        self.metrics.registry.set(self.ids.pending_stores, &[], n as f64);
    }
}

impl Service for Descriptor {
    fn endpoints(self: Arc<Self>) -> Vec<Endpoint> {
        let (a, b, c) = (self.clone(), self.clone(), self);
        vec![
            Endpoint {
                name: "process",
                request: "Constellation",
                handler: Box::new(move |data, _| a.process(data).map(|r| ("QueryReport", r.encode_to_vec()))),
                blocking: true,
            },
            Endpoint {
                name: "loop_closures",
                request: "LoopClosuresRequest",
                handler: Box::new(move |data, _| b.loop_closures(data).map(|r| ("LoopClosureList", r.encode_to_vec()))),
                blocking: false,
            },
            Endpoint {
                name: "explain",
                request: "ExplainRequest",
                handler: Box::new(move |data, _| c.explain(data).map(|r| ("ExplainReply", r.encode_to_vec()))),
                blocking: false,
            },
        ]
    }

    fn member_info(&self) -> pb::MemberInfo {
        pb::MemberInfo {
            n_labels: self.places.n_labels,
            pending_items: lock(&self.pending).len() as u64,
            pending_passes: self.pending_passes.load(Ordering::SeqCst),
            ..Default::default()
        }
    }

    fn attach(&self, session: &zenoh::Session) -> anyhow::Result<()> {
        let _ = self.session.set(session.clone());
        self.caller.attach(session);
        self.routing.watch(session)?;
        Ok(())
    }

    fn serving(self: Arc<Self>) {
        // Learn the swarm's placement (a descriptor joining a running swarm starts at 0),
        // then retry the pending stores until stopped.
        self.refresh(&BTreeSet::new(), self.routing.placement().version);
        let me = self.clone();
        let interval = Duration::from_secs_f64(self.spec.retry_interval_s.max(0.01));
        let handle = std::thread::Builder::new()
            .name("pending-stores".into())
            .spawn(move || {
                let mut next = Instant::now() + interval;
                while !me.stopping.load(Ordering::SeqCst) {
                    std::thread::sleep(Duration::from_millis(20));
                    if Instant::now() >= next {
                        me.retry_once();
                        next = Instant::now() + interval;
                    }
                }
            });
        match handle {
            Ok(h) => *lock(&self.retrier) = Some(h),
            Err(e) => self.log.warning(
                &format!("no thread to retry pending stores: {e}"),
                serde_json::json!({}),
            ),
        }
    }

    fn close(&self) {
        self.stopping.store(true, Ordering::SeqCst);
        if let Some(h) = lock(&self.retrier).take() {
            let _ = h.join();
        }
        self.routing.close();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_closure_rule_takes_the_best_match_not_of_the_recent_own_trajectory() {
        let m = [(0, 98, 0.9), (1, 5, 0.8), (2, 7, 0.7), (3, 1, 0.1), (1, 6, f64::NAN)];
        let v = closure_verdicts(0.5, 5, (0, 100), &m, false);
        assert_eq!(
            v,
            vec![
                Reason::OwnRecentFrame,
                Reason::Accepted,
                Reason::Outranked,
                Reason::BelowScoreThreshold,
                Reason::BelowScoreThreshold
            ]
        );
        assert_eq!(closure_verdicts(0.5, 5, (0, 100), &m, true)[1], Reason::AlreadyClosed);
    }

    #[test]
    fn classify_orders_by_robot_and_frame_and_counts_a_frame_once() {
        let mut failures = HashMap::new();
        failures.insert(2, Reason::VerifierTimeout);
        let got = classify(
            &[(1, 4), (3, 1), (1, 4), (2, 9), (1, 2)],
            &[1, 2],
            &failures,
            &[(1, 4, 0.5)],
        );
        let reasons: Vec<(u32, u32, i32)> = got.iter().map(|o| (o.robot_id, o.frame_index, o.reason)).collect();
        assert_eq!(reasons, vec![(1, 2, 6), (1, 4, 7), (2, 9, 4), (3, 1, 2)]);
    }

    #[test]
    fn a_partial_descriptor_lists_the_non_zero_counts_of_its_range() {
        let d = partial(&[0, 2, 0, 1, 5, 0], 1, 4, 3, 9);
        assert_eq!((d.label_lo, d.label_hi, d.robot_id, d.frame_index), (1, 4, 3, 9));
        assert_eq!(d.label_offsets, vec![0, 2]);
        assert_eq!(d.counts, vec![2, 1]);
    }

    #[test]
    fn match_scores_refuse_inconsistent_counts() {
        let m = |n_matched, n_common, n_union| pb::VerifyMatch {
            n_matched,
            n_common,
            n_union,
            ..Default::default()
        };
        assert_eq!(match_scores(&m(2, 4, 8)), Some((0.25, 0.5)));
        assert_eq!(match_scores(&m(5, 4, 8)), None);
        assert_eq!(match_scores(&m(0, 0, 8)), None);
    }
}
