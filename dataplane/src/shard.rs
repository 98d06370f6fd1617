//! The index shard, compiled: label groups of the swarm's descriptor index. The contract
//! of `swarmrec/services/index_shard.py` (the reference), endpoint for endpoint:
//!
//! * `query` / `lookup`: a PartialQuery for a group this shard owns -> its best stored
//!   frames (CandidatesReply); a query that is not read-only is then stored;
//! * `store`: a ShardStore, stored without a search;
//! * `placement`: the placement followed and what is held (ShardState);
//! * `adopt`: a newer placement, from the coordinator (the lowest live shard) or from
//!   this shard's own coordinator, which runs beside it in Python
//!   (`swarmrec.services.shard_coordinator`);
//! * `transfer`: a page of a group's descriptors, for a shard copying the group.
//!
//! Every request that reads or writes a group carries the placement version its sender
//! routed with, and a shard following another one refuses it (FAILED_PRECONDITION). The
//! reference waits up to a second for an adoption on its way when a request is a few
//! versions ahead; served on zenoh's one thread, this shard cannot wait (the adoption
//! arrives on that thread), so it refuses at once and the sender routes again after
//! refreshing, as it does for any stale version.
//!
//! Stored slices go to the record log (`<data_dir>/index-shard.log`, the Python format)
//! before the answer, and are replayed on start; the placement followed and the groups
//! copied completely are kept beside it (`placement.state`, a ShardState), so a log and
//! its state move between the two implementations in either direction.
//!
//! A learner copies a group on a thread of its own (never zenoh's), paging through an
//! owner's `transfer`. On SIGTERM the shard drains: it declares its draining token and
//! waits (at most `drain_timeout_s`) until the coordinator has moved its groups, unless
//! no other shard stays.

use std::collections::{BTreeSet, HashMap};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use prost::Message;
use zenoh::Wait;

use crate::index::RangeIndex;
use crate::metrics::{Metric, ServiceMetrics};
use crate::pb;
use crate::placement::Placement;
use crate::recordlog::RecordLog;
use crate::runtime::{
    decode, encoding, endpoint_key, lock, missing, watch_tokens, Endpoint, Log, RequestError, Service,
};
use crate::spec::{IndexSpec, PlaceSpec, ServiceSpec};

/// `swarmrec.services.limits`: candidates a query may ask for, frame indices, and how far
/// past what is stored a frame index may be.
pub const MAX_N_RET: u32 = 256;
pub const MAX_FRAME_INDEX: u32 = 1 << 20;
pub const MAX_FRAME_GAP: u64 = 4096;
/// Largest row a transfer may start at.
const MAX_ROW: u64 = 1 << 40;
/// How long a learner waits for an owner's page.
const TRANSFER_TIMEOUT: Duration = Duration::from_secs(10);

fn failed(message: impl Into<String>) -> RequestError {
    RequestError::new(pb::ErrorCode::FailedPrecondition, message)
}

/// A dense slice `[lo, hi)` from a PartialDescriptor, checked as
/// `swarmrec.wire.codec.partial_descriptor_from_proto` checks it (same order, codes and
/// messages), against the frame bounds.
pub fn slice_of(desc: &pb::PartialDescriptor, places: &PlaceSpec) -> Result<Vec<f64>, RequestError> {
    let (lo, hi) = (desc.label_lo, desc.label_hi);
    if lo >= hi {
        return Err(RequestError::invalid(format!("label range [{lo}, {hi}) is empty")));
    }
    if hi > places.n_labels {
        return Err(RequestError::new(
            pb::ErrorCode::UnknownLabel,
            format!(
                "label range [{lo}, {hi}) ends past the label list of {} labels",
                places.n_labels
            ),
        ));
    }
    let (idx, cnt) = (&desc.label_offsets, &desc.counts);
    if idx.len() != cnt.len() {
        return Err(RequestError::invalid(format!(
            "descriptor lists {} labels but {} counts",
            idx.len(),
            cnt.len()
        )));
    }
    let width = hi - lo;
    if let Some(i) = idx.iter().position(|&o| o >= width) {
        return Err(RequestError::invalid(format!(
            "descriptor bin {i}: label {} is outside [{lo}, {hi})",
            u64::from(lo) + u64::from(idx[i])
        )));
    }
    if let Some(i) = cnt.iter().position(|&c| c == 0) {
        return Err(RequestError::invalid(format!(
            "descriptor bin {i}: label {} has count 0; only non-zero bins are sent",
            lo + idx[i]
        )));
    }
    let mut dense = vec![0.0f64; width as usize];
    let mut seen = vec![false; width as usize];
    let mut twice: Option<u32> = None;
    for (&o, &c) in idx.iter().zip(cnt) {
        if seen[o as usize] {
            twice = Some(twice.map_or(o, |t| t.min(o)));
        }
        seen[o as usize] = true;
        dense[o as usize] = f64::from(c);
    }
    if let Some(o) = twice {
        return Err(RequestError::invalid(format!(
            "descriptor lists label {} more than once",
            lo + o
        )));
    }
    // The first label holding the most objects, as numpy's argmax names it.
    let mut best: Option<(usize, f64)> = None;
    for (i, &c) in dense.iter().enumerate() {
        if best.is_none_or(|(_, b)| c > b) {
            best = Some((i, c));
        }
    }
    if let Some((i, c)) = best {
        if c > f64::from(places.max_objects_per_label) {
            return Err(RequestError::too_large(
                &format!("objects of label {} in the frame", lo as usize + i),
                c as u64,
                places.max_objects_per_label.into(),
                "max_objects_per_label",
            ));
        }
    }
    let total: f64 = dense.iter().sum();
    if total > f64::from(places.max_objects_per_frame) {
        return Err(RequestError::too_large(
            "objects in the frame",
            total as u64,
            places.max_objects_per_frame.into(),
            "max_objects_per_frame",
        ));
    }
    Ok(dense)
}

/// The slice's wire form (`partial_descriptor_to_proto` of the dense vector).
fn to_proto(counts: &[f64], lo: u32, hi: u32, robot: u32, frame: u64) -> pb::PartialDescriptor {
    let (mut offsets, mut values) = (Vec::new(), Vec::new());
    for (i, &c) in counts.iter().enumerate() {
        if c != 0.0 {
            offsets.push(i as u32);
            values.push(c as u32);
        }
    }
    pb::PartialDescriptor {
        robot_id: robot,
        frame_index: frame as u32,
        query_step: 0,
        label_lo: lo,
        label_hi: hi,
        label_offsets: offsets,
        counts: values,
    }
}

struct State {
    placement: Placement,
    indexes: HashMap<usize, RangeIndex>,
    /// Groups held completely (owned, or copied to the end).
    ready: BTreeSet<usize>,
    /// Partial queries served per group since start (the coordinator's load).
    served: Vec<u64>,
    /// Groups a copy thread is working on.
    syncing: BTreeSet<usize>,
    confirmed: bool,
    draining: bool,
    log: RecordLog,
}

impl State {
    fn stored(&self) -> usize {
        self.indexes.values().map(RangeIndex::size).sum()
    }
}

/// The shards this one sees alive and those that declared they are draining.
#[derive(Default)]
struct Live {
    alive: BTreeSet<u32>,
    draining: BTreeSet<u32>,
}

struct ShardMetricIds {
    partial_queries: Metric,
    stored_descriptors: Metric,
    group_queries: Metric,
    placement_version: Metric,
    groups: Metric,
    refused: Metric,
    handoff_records: Metric,
    placements_published: Metric,
}

pub struct IndexShard {
    shard: u32,
    swarm: String,
    n_robots: u32,
    places: PlaceSpec,
    index: IndexSpec,
    state_path: Option<PathBuf>,
    state: Mutex<State>,
    live: Arc<Mutex<Live>>,
    session: OnceLock<zenoh::Session>,
    /// The liveliness subscribers (kept: dropping one ends it) and the draining token.
    watchers: Mutex<Vec<Box<dyn std::any::Any + Send>>>,
    metrics: Arc<ServiceMetrics>,
    ids: ShardMetricIds,
    log: Log,
    /// Set when the host stops: copies end.
    stopping: Arc<std::sync::atomic::AtomicBool>,
}

fn register(metrics: &ServiceMetrics) -> ShardMetricIds {
    let r = &metrics.registry;
    ShardMetricIds {
        partial_queries: r.counter(
            "swarmrec_shard_partial_queries",
            "Partial queries served by this index shard",
            &[],
        ),
        stored_descriptors: r.gauge(
            "swarmrec_shard_stored_descriptors",
            "Partial descriptors held by this index shard (every group it owns or copies)",
            &[],
        ),
        group_queries: r.counter(
            "swarmrec_shard_group_queries",
            "Robots' partial queries served by this index shard, by label group (the rebalancing \
             load; a client's lookups are not in it)",
            &["group"],
        ),
        placement_version: r.gauge(
            "swarmrec_shard_placement_version",
            "Version of the placement this shard follows",
            &[],
        ),
        groups: r.gauge(
            "swarmrec_shard_groups",
            "Label groups this shard owns or is copying",
            &["role"],
        ),
        refused: r.counter(
            "swarmrec_shard_refused",
            "Requests refused because the sender routed with another placement (stale) or before \
             the shard's placement was confirmed (unconfirmed), or for a group it does not hold",
            &["reason"],
        ),
        handoff_records: r.counter(
            "swarmrec_shard_handoff_records",
            "Partial descriptors copied into this shard from another one (handoffs)",
            &[],
        ),
        placements_published: r.counter(
            "swarmrec_shard_placements_published",
            "Placements this shard published as the coordinator, by why (members: a shard came, \
             went or drains; rebalance: the observed load; handoff_done: the learners own)",
            &["reason"],
        ),
    }
}

impl IndexShard {
    pub fn new(spec: &ServiceSpec, metrics: Arc<ServiceMetrics>, log: Log) -> anyhow::Result<Arc<IndexShard>> {
        let index = spec
            .index
            .clone()
            .ok_or_else(|| anyhow::anyhow!("an index shard's spec has no index settings"))?;
        let ids = register(&metrics);
        let initial = pb::Placement::decode(index.initial_placement.as_slice())
            .map_err(|e| anyhow::anyhow!("initial placement: {e}"))?;
        let initial = Placement::from_proto(&initial, spec.places.n_labels)
            .map_err(|e| anyhow::anyhow!("initial placement: {e}"))?;
        anyhow::ensure!(
            initial.groups == index.groups,
            "the initial placement's label groups are not the swarm's"
        );
        let state_path = spec.data_dir.as_ref().map(|d| d.join("placement.state"));
        let path = spec.data_dir.as_ref().map(|d| d.join("index-shard.log"));
        let (record_log, records) = RecordLog::open(path.as_deref(), spec.fsync)?;
        if record_log.truncated_bytes > 0 {
            log.warning(
                "record log: a cut last record was dropped",
                serde_json::json!({"bytes": record_log.truncated_bytes}),
            );
        }
        let shard = spec.robot;
        let saved = load_state(state_path.as_deref(), &index.groups, spec.places.n_labels, &log);
        let (placement, ready, held) = match saved {
            None => {
                let held: BTreeSet<usize> = initial.groups_of(shard).into_iter().collect();
                (initial, held.clone(), held)
            }
            Some((p, ready)) => {
                let held: BTreeSet<usize> = p.groups_of(shard).into_iter().chain(p.learning(shard)).collect();
                (p, ready, held)
            }
        };
        let mut indexes = HashMap::new();
        for &g in &held {
            let (lo, hi) = index.groups[g];
            indexes.insert(g, RangeIndex::new(lo, hi, spec.n_robots)?);
        }
        let n_groups = index.groups.len();
        let this = IndexShard {
            shard,
            swarm: spec.swarm.clone(),
            n_robots: spec.n_robots,
            places: spec.places.clone(),
            index,
            state_path,
            state: Mutex::new(State {
                placement,
                indexes,
                ready,
                served: vec![0; n_groups],
                syncing: BTreeSet::new(),
                confirmed: false,
                draining: false,
                log: record_log,
            }),
            live: Arc::new(Mutex::new(Live::default())),
            session: OnceLock::new(),
            watchers: Mutex::new(Vec::new()),
            metrics,
            ids,
            log,
            stopping: Arc::new(std::sync::atomic::AtomicBool::new(false)),
        };
        let (restored, skipped) = {
            let mut st = lock(&this.state);
            let out = this.replay(&mut st, &held, &records);
            this.update_gauges(&st);
            out
        };
        {
            let st = lock(&this.state);
            this.log.info(
                "index loaded",
                serde_json::json!({"fields": {
                    "groups": st.placement.groups_of(shard),
                    "learning": st.placement.learning(shard),
                    "version": st.placement.version,
                    "records": restored,
                    "skipped": skipped,
                    "stored": st.stored(),
                }}),
            );
        }
        Ok(Arc::new(this))
    }

    /// Loads the logged slices of `groups` into their indexes: (loaded, skipped).
    fn replay(&self, st: &mut State, groups: &BTreeSet<usize>, records: &[Vec<u8>]) -> (usize, usize) {
        let (mut restored, mut skipped) = (0, 0);
        for record in records {
            let Ok(msg) = pb::PartialDescriptor::decode(record.as_slice()) else {
                skipped += 1;
                continue;
            };
            let Some(g) = st.placement.group_of_range(msg.label_lo, msg.label_hi) else {
                continue;
            };
            if !groups.contains(&g) {
                continue;
            }
            let counts = match slice_of(&msg, &self.places) {
                Ok(c) => c,
                Err(e) => {
                    // Stored before the bounds existed (or were lowered): skipped, not deleted.
                    skipped += 1;
                    self.log.warning(
                        "stored slice over the bounds skipped",
                        serde_json::json!({"fields": {"robot": msg.robot_id, "frame": msg.frame_index, "reason": e.message}}),
                    );
                    continue;
                }
            };
            if msg.robot_id >= self.n_robots {
                skipped += 1;
                continue;
            }
            // A log written before stores were idempotent may hold a frame twice: the last wins.
            if let Some(ix) = st.indexes.get_mut(&g) {
                if ix.add(msg.robot_id, u64::from(msg.frame_index), &counts).is_ok() {
                    restored += 1;
                }
            }
        }
        (restored, skipped)
    }

    fn update_gauges(&self, st: &State) {
        let r = &self.metrics.registry;
        r.set(self.ids.stored_descriptors, &[], st.stored() as f64);
        r.set(self.ids.placement_version, &[], st.placement.version as f64);
        r.set(
            self.ids.groups,
            &["owner"],
            st.placement.groups_of(self.shard).len() as f64,
        );
        r.set(
            self.ids.groups,
            &["learner"],
            st.placement.learning(self.shard).len() as f64,
        );
    }

    /// The placement followed and the groups held completely, atomically (a crash leaves
    /// the old file or the new one).
    fn save_state(&self, st: &State) {
        let Some(path) = &self.state_path else { return };
        let msg = pb::ShardState {
            placement: Some(st.placement.to_proto()),
            ready_groups: st.ready.iter().map(|&g| g as u32).collect(),
            ..Default::default()
        };
        let tmp = path.with_file_name("placement.state.tmp");
        let written = std::fs::write(&tmp, msg.encode_to_vec()).and_then(|()| std::fs::rename(&tmp, path));
        if let Err(e) = written {
            self.log
                .emit(40, &format!("placement state not saved: {e}"), serde_json::json!({}));
        }
    }

    fn state_msg(&self, known_version: Option<u64>) -> pb::ShardState {
        let (query_calls, query_cpu_s) = self.metrics.cost("query");
        let (store_calls, store_cpu_s) = self.metrics.cost("store");
        let st = lock(&self.state);
        // Left out when the asker has it or a newer one (only a newer placement is news to
        // it), confirmed or not (no one follows an unconfirmed shard's placement): as a swarm
        // starts every shard asks every other, and after a placement change every querier asks.
        let known = known_version.is_some_and(|k| st.placement.version <= k);
        pb::ShardState {
            placement: if known { None } else { Some(st.placement.to_proto()) },
            placement_version: st.placement.version,
            query_calls,
            query_cpu_s: query_cpu_s as f32,
            store_calls,
            store_cpu_s: store_cpu_s as f32,
            shard_id: self.shard,
            ready_groups: st.ready.iter().map(|&g| g as u32).collect(),
            served_groups: (0..st.served.len())
                .filter(|&g| st.served[g] > 0)
                .map(|g| g as u32)
                .collect(),
            served_queries: st.served.iter().copied().filter(|&n| n > 0).collect(),
            confirmed: st.confirmed,
            draining: st.draining,
        }
    }

    /// Follows `placement` (newer, or the same to confirm it): groups gained get an index
    /// (filled from this shard's own log, then copied when learning), groups let go are
    /// dropped from memory (their records stay in the log). False when it is older.
    fn follow(self: &Arc<Self>, placement: Placement) -> Result<bool, RequestError> {
        if placement.groups != self.index.groups {
            return Err(RequestError::invalid(
                "the placement's label groups are not this swarm's",
            ));
        }
        let copy: Vec<usize> = {
            let mut st = lock(&self.state);
            if placement.version < st.placement.version {
                return Ok(false);
            }
            let old: BTreeSet<usize> = st.indexes.keys().copied().collect();
            let owned: BTreeSet<usize> = placement.groups_of(self.shard).into_iter().collect();
            let learning: BTreeSet<usize> = placement.learning(self.shard).into_iter().collect();
            let held: BTreeSet<usize> = owned.union(&learning).copied().collect();
            for g in old.difference(&held) {
                st.indexes.remove(g);
                st.ready.remove(g);
            }
            let gained: BTreeSet<usize> = held.difference(&old).copied().collect();
            for &g in &gained {
                let (lo, hi) = self.index.groups[g];
                let ix = RangeIndex::new(lo, hi, self.n_robots).map_err(|e| RequestError::invalid(e.to_string()))?;
                st.indexes.insert(g, ix);
            }
            st.placement = placement;
            if !gained.is_empty() {
                match st.log.records() {
                    Ok(records) => {
                        self.replay(&mut st, &gained, &records);
                    }
                    Err(e) => self
                        .log
                        .emit(40, &format!("record log unreadable: {e}"), serde_json::json!({})),
                }
            }
            // A group owned without having been learned is one this shard held when it went
            // away: its own records are all there is.
            for g in owned.difference(&learning) {
                st.ready.insert(*g);
            }
            st.confirmed = true;
            self.save_state(&st);
            self.update_gauges(&st);
            let copy: Vec<usize> = learning
                .iter()
                .copied()
                .filter(|g| !st.ready.contains(g) && !st.syncing.contains(g))
                .collect();
            st.syncing.extend(copy.iter().copied());
            copy
        };
        for g in copy {
            let me = self.clone();
            let spawned = std::thread::Builder::new()
                .name(format!("copy-group-{g}"))
                .spawn(move || me.copy_group(g));
            if let Err(e) = spawned {
                lock(&self.state).syncing.remove(&g);
                self.log
                    .emit(40, &format!("no thread to copy group {g}: {e}"), serde_json::json!({}));
            }
        }
        Ok(true)
    }

    // --- copying a group (a learner) -------------------------------------------------

    /// Pages through an owner's descriptors of `group` until it has sent everything it held
    /// when asked; then the group is ready. Another owner is tried when one fails; the
    /// placement moving on ends the copy.
    fn copy_group(self: Arc<Self>, group: usize) {
        let stopping = self.stopping.clone();
        while !stopping.load(std::sync::atomic::Ordering::SeqCst) {
            let (version, sources) = {
                let st = lock(&self.state);
                if !st.placement.learning(self.shard).contains(&group) {
                    break;
                }
                let sources: Vec<u32> = st.placement.owners[group]
                    .iter()
                    .copied()
                    .filter(|&o| o != self.shard)
                    .collect();
                (st.placement.version, sources)
            };
            if sources.iter().any(|&s| self.copy_from(group, s, version)) {
                let mut st = lock(&self.state);
                if st.placement.learning(self.shard).contains(&group) {
                    st.ready.insert(group);
                    self.save_state(&st);
                }
                drop(st);
                self.log
                    .info("group copied", serde_json::json!({"fields": {"group": group}}));
                break;
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        lock(&self.state).syncing.remove(&group);
    }

    /// Copies `group` from `source` to the end; false when it failed (logged).
    fn copy_from(&self, group: usize, source: u32, version: u64) -> bool {
        let Some(session) = self.session.get() else {
            return false;
        };
        let key = endpoint_key(&self.swarm, "index-shard", source, "transfer");
        let mut row = 0u64;
        while !self.stopping.load(std::sync::atomic::Ordering::SeqCst) {
            let req = pb::TransferRequest {
                group: group as u32,
                placement_version: version,
                start_row: row,
                max_records: self.index.transfer_page,
            }
            .encode_to_vec();
            let reply = match self.call(session, &key, req, "TransferRequest") {
                Ok(data) => pb::TransferReply::decode(data.as_slice()).map_err(|e| e.to_string()),
                Err(e) => Err(e),
            };
            let taken = reply.and_then(|r| self.take(group, &r.records).map(|()| r));
            match taken {
                Ok(r) => {
                    row = r.next_row;
                    if r.done {
                        return true;
                    }
                }
                Err(e) => {
                    self.log.info(
                        &format!("copy of group {group} from shard {source}: {e}"),
                        serde_json::json!({}),
                    );
                    return false;
                }
            }
        }
        false
    }

    /// One request to a peer, counted as the Python caller counts it; the reply's bytes or
    /// why there is none.
    fn call(&self, session: &zenoh::Session, key: &str, req: Vec<u8>, schema: &str) -> Result<Vec<u8>, String> {
        let size = req.len();
        let replies = session
            .get(key)
            .payload(req)
            .encoding(encoding(schema))
            .attachment(self.shard.to_string())
            .timeout(TRANSFER_TIMEOUT)
            .wait()
            .map_err(|e| e.to_string())?;
        self.metrics.count_sent(schema, "swarm", size);
        let fail = |reason: &str, why: String| {
            self.metrics
                .registry
                .inc(self.metrics.peer_failures, &["transfer", reason], 1.0);
            Err(why)
        };
        match replies.recv() {
            Ok(reply) => match reply.result() {
                Ok(sample) => {
                    let data = sample.payload().to_bytes().into_owned();
                    self.metrics.count_received("TransferReply", "swarm", data.len());
                    Ok(data)
                }
                Err(err) => {
                    let data = err.payload().to_bytes();
                    match pb::ErrorReply::decode(data.as_ref()) {
                        Ok(e) => fail("error", format!("{}: {}", e.code().as_str_name(), e.message)),
                        Err(_) => fail("error", "an error reply that does not decode".into()),
                    }
                }
            },
            Err(_) => fail("timeout", "no reply".into()),
        }
    }

    /// Copied slices into `group`'s index and this shard's log (a restart keeps them).
    fn take(&self, group: usize, records: &[pb::PartialDescriptor]) -> Result<(), String> {
        let mut st = lock(&self.state);
        if !st.indexes.contains_key(&group) {
            return Ok(());
        }
        for msg in records {
            if (msg.label_lo, msg.label_hi) != self.index.groups[group] {
                return Err("a copied slice is not of the group asked for".into());
            }
            let counts = slice_of(msg, &self.places).map_err(|e| e.message)?;
            let frame = u64::from(msg.frame_index);
            let present = st.indexes[&group].get(msg.robot_id, frame).is_some();
            if present || msg.robot_id >= self.n_robots {
                continue; // stored already (a new store got here first: same content)
            }
            st.log.append(&msg.encode_to_vec()).map_err(|e| e.to_string())?;
            if let Some(ix) = st.indexes.get_mut(&group) {
                ix.add(msg.robot_id, frame, &counts).map_err(|e| e.to_string())?;
            }
            self.metrics.registry.inc(self.ids.handoff_records, &[], 1.0);
        }
        self.metrics
            .registry
            .set(self.ids.stored_descriptors, &[], st.stored() as f64);
        Ok(())
    }

    // --- requests ----------------------------------------------------------------------

    fn refuse(&self, reason: &str) {
        self.metrics.registry.inc(self.ids.refused, &[reason], 1.0);
    }

    /// The group `desc` belongs to and its dense slice, checked against the placement
    /// followed (`st` is held).
    fn group_for(
        &self,
        st: &State,
        desc: &pb::PartialDescriptor,
        version: u64,
        storing: bool,
    ) -> Result<(usize, Vec<f64>), RequestError> {
        if !st.confirmed {
            self.refuse("unconfirmed");
            return Err(failed(format!(
                "shard {} restarted and waits for the coordinator to confirm its placement: retry",
                self.shard
            )));
        }
        if version != st.placement.version {
            self.refuse("stale");
            return Err(failed(format!(
                "routed with placement version {version}, shard {} follows {}: refresh the placement and route again",
                self.shard, st.placement.version
            )));
        }
        let counts = slice_of(desc, &self.places)?;
        let Some(g) = st.placement.group_of_range(desc.label_lo, desc.label_hi) else {
            return Err(RequestError::invalid(format!(
                "labels [{}, {}) are not a label group of this swarm",
                desc.label_lo, desc.label_hi
            )));
        };
        let holds =
            st.placement.owners[g].contains(&self.shard) || (storing && st.placement.learners[g].contains(&self.shard));
        if !holds {
            self.refuse("not_held");
            return Err(failed(format!(
                "shard {} does not {} label group {g} at placement version {version}",
                self.shard,
                if storing { "hold" } else { "answer for" }
            )));
        }
        Ok((g, counts))
    }

    fn check_ids(&self, desc: &pb::PartialDescriptor) -> Result<(), RequestError> {
        if desc.robot_id >= self.n_robots {
            return Err(RequestError::invalid(format!(
                "robot {} is not in this swarm of {} robots",
                desc.robot_id, self.n_robots
            )));
        }
        if desc.frame_index >= MAX_FRAME_INDEX || desc.query_step >= MAX_FRAME_INDEX {
            return Err(RequestError::invalid(format!(
                "frame index and query step must be below {MAX_FRAME_INDEX}"
            )));
        }
        Ok(())
    }

    fn already(desc: &pb::PartialDescriptor) -> RequestError {
        RequestError::new(
            pb::ErrorCode::AlreadyExists,
            format!(
                "frame {} of robot {} is already stored here with another slice; stores are idempotent \
                 (the same slice again is accepted)",
                desc.frame_index, desc.robot_id
            ),
        )
    }

    /// Stores a slice unless stored already with the same content.
    fn store_slice(
        &self,
        st: &mut State,
        g: usize,
        desc: &pb::PartialDescriptor,
        counts: &[f64],
    ) -> Result<(), RequestError> {
        let frame = u64::from(desc.frame_index);
        let ix = &st.indexes[&g];
        if let Some(stored) = ix.get(desc.robot_id, frame) {
            if stored != counts {
                return Err(Self::already(desc));
            }
            return Ok(());
        }
        if frame > ix.frames_of(desc.robot_id) + MAX_FRAME_GAP {
            return Err(RequestError::invalid(format!(
                "frame index more than {MAX_FRAME_GAP} frames past what is stored"
            )));
        }
        // Stored before the answer leaves: an acknowledged frame survives a crash.
        st.log
            .append(&desc.encode_to_vec())
            .map_err(|e| RequestError::new(pb::ErrorCode::Internal, format!("record log: {e}")))?;
        if let Some(ix) = st.indexes.get_mut(&g) {
            ix.add(desc.robot_id, frame, counts)
                .map_err(|e| RequestError::invalid(e.to_string()))?;
        }
        let stored = st.stored();
        self.metrics
            .registry
            .set(self.ids.stored_descriptors, &[], stored as f64);
        Ok(())
    }

    fn query(&self, data: &[u8], lookup: bool, caller: Option<u32>) -> Result<pb::CandidatesReply, RequestError> {
        let req: pb::PartialQuery = decode(data, "swarmrec.v1.PartialQuery")?;
        let Some(desc) = req.descriptor.as_ref() else {
            return Err(missing("swarmrec.v1.PartialQuery", "descriptor"));
        };
        if lookup && !req.read_only {
            return Err(RequestError::invalid(
                "lookup never stores: send read_only = true (descriptors use query)",
            ));
        }
        if !req.read_only {
            own_slice(desc, caller)?;
        }
        if req.n_ret > MAX_N_RET {
            return Err(RequestError::invalid(format!(
                "n_ret must be at most {MAX_N_RET}, got {}",
                req.n_ret
            )));
        }
        let n_ret = if req.n_ret == 0 { self.index.n_ret } else { req.n_ret };
        self.check_ids(desc)?;
        // A read-only lookup (a client's) searches everything even in a lock-step swarm.
        let lockstep = self.index.lockstep && !req.read_only;
        let step = if desc.query_step != 0 {
            desc.query_step
        } else {
            desc.frame_index
        };
        let before = lockstep.then_some(u64::from(step));
        let mut st = lock(&self.state);
        let (g, counts) = self.group_for(&st, desc, req.placement_version, false)?;
        if counts.iter().all(|&c| c == 0.0) {
            return Err(RequestError::invalid(
                "partial descriptor has no labels; send only non-empty slices",
            ));
        }
        let ix = &st.indexes[&g];
        let frame = u64::from(desc.frame_index);
        if frame > ix.frames_of(desc.robot_id) + MAX_FRAME_GAP
            || before.is_some_and(|b| b > ix.frames() + MAX_FRAME_GAP)
        {
            return Err(RequestError::invalid(format!(
                "frame index or step more than {MAX_FRAME_GAP} frames past what is stored"
            )));
        }
        // A slice already here (a replica's store can come before its query's retry) is
        // accepted when the same, and its frame is never its own candidate.
        let mut own = None;
        if !req.read_only {
            if let Some(stored) = ix.get(desc.robot_id, frame) {
                if stored != counts.as_slice() {
                    return Err(Self::already(desc));
                }
                own = Some((desc.robot_id, frame));
            }
        }
        let found = ix.candidates_except(&counts, n_ret as usize, before, own);
        if !req.read_only {
            self.store_slice(&mut st, g, desc, &counts)?;
        }
        // The load the placement moves groups for is the robots': a client's lookups
        // (read-only, anyone may send them) must not move the index.
        if !req.read_only {
            st.served[g] += 1;
        }
        drop(st);
        let r = &self.metrics.registry;
        r.inc(self.ids.partial_queries, &[], 1.0);
        if !req.read_only {
            r.inc(self.ids.group_queries, &[&g.to_string()], 1.0);
        }
        // The label range is not echoed: zenoh pairs the reply with its request, which names it.
        Ok(pb::CandidatesReply {
            query_id: req.query_id,
            label_lo: 0,
            label_hi: 0,
            robot_ids: found.iter().map(|c| c.robot).collect(),
            frame_indices: found.iter().map(|c| c.frame as u32).collect(),
            scores: if req.include_scores {
                found.iter().map(|c| c.score as f32).collect()
            } else {
                Vec::new()
            },
        })
    }

    fn store(&self, data: &[u8], caller: Option<u32>) -> Result<pb::StoreReply, RequestError> {
        let req: pb::ShardStore = decode(data, "swarmrec.v1.ShardStore")?;
        let Some(desc) = req.descriptor.as_ref() else {
            return Err(missing("swarmrec.v1.ShardStore", "descriptor"));
        };
        own_slice(desc, caller)?;
        self.check_ids(desc)?;
        let mut st = lock(&self.state);
        let (g, counts) = self.group_for(&st, desc, req.placement_version, true)?;
        if counts.iter().all(|&c| c == 0.0) {
            return Err(RequestError::invalid(
                "partial descriptor has no labels; send only non-empty slices",
            ));
        }
        self.store_slice(&mut st, g, desc, &counts)?;
        Ok(pb::StoreReply {
            stored_frames: st.stored() as u32,
        })
    }

    fn placement_state(&self, data: &[u8]) -> Result<pb::ShardState, RequestError> {
        let req: pb::PlacementRequest = decode(data, "swarmrec.v1.PlacementRequest")?;
        Ok(self.state_msg(req.known_version))
    }

    fn adopt(self: &Arc<Self>, data: &[u8], caller: Option<u32>) -> Result<pb::ShardState, RequestError> {
        let req: pb::AdoptRequest = decode(data, "swarmrec.v1.AdoptRequest")?;
        let Some(msg) = req.placement.as_ref() else {
            return Err(missing("swarmrec.v1.AdoptRequest", "placement"));
        };
        // Only the lowest live shard coordinates (a placement from a shard that knows less is
        // refused, so two tables never compete); this shard's own coordinator, which runs
        // beside it under the same identity, confirms and publishes through here too.
        let lowest = self.lowest_live();
        let allowed = caller.is_some_and(|c| c <= lowest || c == self.shard);
        if !allowed {
            let who = caller.map_or("None".to_string(), |c| c.to_string());
            return Err(failed(format!(
                "placements come from the coordinator, the lowest live shard ({lowest}), not from {who}"
            )));
        }
        let placement = Placement::from_proto(msg, self.places.n_labels).map_err(RequestError::invalid)?;
        let version = placement.version;
        if !self.follow(placement)? {
            let followed = lock(&self.state).placement.version;
            return Err(failed(format!(
                "placement version {version} is older than the {followed} followed"
            )));
        }
        if req.publish && caller == Some(self.shard) {
            let reason = reason_name(req.reason);
            self.metrics.registry.inc(self.ids.placements_published, &[reason], 1.0);
        }
        Ok(self.state_msg(Some(version))) // the coordinator sent it: not back
    }

    fn transfer(&self, data: &[u8]) -> Result<pb::TransferReply, RequestError> {
        let req: pb::TransferRequest = decode(data, "swarmrec.v1.TransferRequest")?;
        let n_groups = self.index.groups.len();
        if req.group as usize >= n_groups {
            return Err(RequestError::invalid(format!(
                "group {} is not one of the {n_groups} label groups",
                req.group
            )));
        }
        if req.start_row >= MAX_ROW {
            return Err(RequestError::invalid(format!("start_row must be below {MAX_ROW}")));
        }
        let page = self.index.transfer_page;
        let page = u64::from(if req.max_records == 0 {
            page
        } else {
            req.max_records.min(page)
        });
        let g = req.group as usize;
        let st = lock(&self.state);
        if st.placement.version < req.placement_version || !st.confirmed {
            return Err(failed(format!(
                "shard {} follows placement version {}, not yet {}: ask again",
                self.shard, st.placement.version, req.placement_version
            )));
        }
        if !st.placement.owners[g].contains(&self.shard) || !st.ready.contains(&g) {
            return Err(failed(format!(
                "shard {} does not own label group {}",
                self.shard, req.group
            )));
        }
        let ix = &st.indexes[&g];
        let (start, stop) = (req.start_row as usize, (req.start_row + page) as usize);
        let (lo, hi) = self.index.groups[g];
        let records = ix
            .rows(start, stop)
            .into_iter()
            .map(|(r, f, counts)| to_proto(counts, lo, hi, r, f))
            .collect();
        let next_row = (req.start_row + page).min(ix.size() as u64);
        Ok(pb::TransferReply {
            group: req.group,
            records,
            next_row,
            done: next_row >= ix.size() as u64,
        })
    }

    /// The lowest shard id this shard sees alive (itself included).
    fn lowest_live(&self) -> u32 {
        let live = lock(&self.live);
        live.alive.iter().next().map_or(self.shard, |&l| l.min(self.shard))
    }

    /// Whether another live shard has not declared it is stopping.
    fn anyone_stays(&self) -> bool {
        let live = lock(&self.live);
        live.alive
            .iter()
            .any(|m| *m != self.shard && !live.draining.contains(m))
    }

    fn watch(&self, session: &zenoh::Session, what: &str) -> anyhow::Result<()> {
        let live = self.live.clone();
        let draining = what == "draining";
        let sub = watch_tokens(session, &self.swarm, what, "index-shard", move |id, declared| {
            let mut live = lock(&live);
            let set = if draining { &mut live.draining } else { &mut live.alive };
            if declared {
                set.insert(id);
            } else {
                set.remove(&id);
            }
        })?;
        lock(&self.watchers).push(sub);
        Ok(())
    }
}

/// The placement and ready groups saved in `placement.state`, when readable and for these groups.
fn load_state(
    path: Option<&std::path::Path>,
    groups: &[(u32, u32)],
    n_labels: u32,
    log: &Log,
) -> Option<(Placement, BTreeSet<usize>)> {
    let path = path?;
    let data = std::fs::read(path).ok()?;
    let parsed = pb::ShardState::decode(data.as_slice())
        .map_err(|e| e.to_string())
        .and_then(|s| {
            let p = s.placement.as_ref().ok_or("no placement")?;
            Placement::from_proto(p, n_labels).map(|p| (p, s.ready_groups))
        });
    match parsed {
        Err(e) => {
            log.warning(
                &format!("placement state unreadable, starting from version 0: {e}"),
                serde_json::json!({}),
            );
            None
        }
        Ok((p, _)) if p.groups != groups => {
            log.warning(
                "placement state is for other label groups: starting from version 0",
                serde_json::json!({}),
            );
            None
        }
        Ok((p, ready)) => {
            let ready = ready
                .into_iter()
                .map(|g| g as usize)
                .filter(|&g| g < groups.len())
                .collect();
            Some((p, ready))
        }
    }
}

/// The handlers of an index shard, each with its own handle on it.
/// Refuses a slice that is not the caller's own robot's (PERMISSION_DENIED): a robot stores
/// and queries with its own frames only, and the caller is the robot the request's key
/// names, which the router checks against its certificate (`runtime::CALLER_BOUND`).
fn own_slice(desc: &pb::PartialDescriptor, caller: Option<u32>) -> Result<(), RequestError> {
    if caller == Some(desc.robot_id) {
        return Ok(());
    }
    let who = caller.map_or_else(|| "outside the swarm".to_owned(), |c| format!("robot {c}"));
    Err(RequestError::new(
        pb::ErrorCode::PermissionDenied,
        format!(
            "a request from {who} carries robot {}'s frame {}: a robot stores and queries with its own frames only",
            desc.robot_id, desc.frame_index
        ),
    ))
}

fn handler<R: Message + 'static>(
    shard: &Arc<IndexShard>,
    reply: &'static str,
    f: impl Fn(&Arc<IndexShard>, &[u8], Option<u32>) -> Result<R, RequestError> + Send + Sync + 'static,
) -> crate::runtime::Handler {
    let s = shard.clone();
    Box::new(move |data, caller| f(&s, data, caller).map(|r| (reply, r.encode_to_vec())))
}

impl Service for IndexShard {
    fn endpoints(self: Arc<Self>) -> Vec<Endpoint> {
        vec![
            Endpoint {
                name: "query",
                request: "PartialQuery",
                handler: handler(&self, "CandidatesReply", |s, d, c| s.query(d, false, c)),
                blocking: false,
            },
            Endpoint {
                name: "lookup",
                request: "PartialQuery",
                handler: handler(&self, "CandidatesReply", |s, d, c| s.query(d, true, c)),
                blocking: false,
            },
            Endpoint {
                name: "store",
                request: "ShardStore",
                handler: handler(&self, "StoreReply", |s, d, c| s.store(d, c)),
                blocking: false,
            },
            Endpoint {
                name: "placement",
                request: "PlacementRequest",
                handler: handler(&self, "ShardState", |s, d, _| s.placement_state(d)),
                blocking: false,
            },
            Endpoint {
                name: "adopt",
                request: "AdoptRequest",
                handler: handler(&self, "ShardState", |s, d, c| s.adopt(d, c)),
                blocking: false,
            },
            Endpoint {
                name: "transfer",
                request: "TransferRequest",
                handler: handler(&self, "TransferReply", |s, d, _| s.transfer(d)),
                blocking: false,
            },
        ]
    }

    fn member_info(&self) -> pb::MemberInfo {
        let st = lock(&self.state);
        let owned = st.placement.groups_of(self.shard);
        let (lo, hi) = owned.first().map_or((0, 0), |&g| self.index.groups[g]);
        pb::MemberInfo {
            label_lo: lo,
            label_hi: hi,
            stored_items: st.stored() as u64,
            n_labels: self.places.n_labels,
            label_ranges: owned
                .iter()
                .flat_map(|&g| [self.index.groups[g].0, self.index.groups[g].1])
                .collect(),
            ..Default::default()
        }
    }

    fn attach(&self, session: &zenoh::Session) -> anyhow::Result<()> {
        let _ = self.session.set(session.clone());
        self.watch(session, "alive")?;
        self.watch(session, "draining")
    }

    fn drain(&self) {
        lock(&self.state).draining = true;
        if let Some(session) = self.session.get() {
            let key = format!("swarmrec/v1/{}/draining/index-shard/{}", self.swarm, self.shard);
            if let Ok(token) = session.liveliness().declare_token(&key).wait() {
                lock(&self.watchers).push(Box::new(token));
            }
        }
        let deadline = Instant::now() + Duration::from_secs_f64(self.index.drain_timeout_s.max(0.0));
        let mut waited = false;
        while Instant::now() < deadline {
            let holds = {
                let st = lock(&self.state);
                !st.placement.groups_of(self.shard).is_empty() || !st.placement.learning(self.shard).is_empty()
            };
            if !holds || !self.anyone_stays() {
                break;
            }
            waited = true;
            std::thread::sleep(Duration::from_millis(200));
        }
        if waited {
            let st = lock(&self.state);
            self.log.info(
                "drained",
                serde_json::json!({"fields": {"version": st.placement.version, "groups": st.placement.groups_of(self.shard)}}),
            );
        }
    }

    fn close(&self) {
        self.stopping.store(true, std::sync::atomic::Ordering::SeqCst);
        lock(&self.watchers).clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn places() -> PlaceSpec {
        PlaceSpec {
            n_labels: 80,
            d: 0.5,
            min_common: 2,
            same_label_only: true,
            max_objects_per_frame: 10,
            max_objects_per_label: 4,
            verify_max_frames: 10,
            verify_max_object_pairs: 100,
        }
    }

    fn desc(lo: u32, hi: u32, offsets: &[u32], counts: &[u32]) -> pb::PartialDescriptor {
        pb::PartialDescriptor {
            label_lo: lo,
            label_hi: hi,
            label_offsets: offsets.to_vec(),
            counts: counts.to_vec(),
            ..Default::default()
        }
    }

    #[test]
    fn slices_are_checked_in_the_references_order() {
        let p = places();
        assert_eq!(
            slice_of(&desc(40, 44, &[1, 3], &[2, 1]), &p).unwrap(),
            vec![0.0, 2.0, 0.0, 1.0]
        );
        let e = slice_of(&desc(40, 40, &[], &[]), &p).unwrap_err();
        assert!(e.message.contains("is empty"));
        let e = slice_of(&desc(40, 81, &[], &[]), &p).unwrap_err();
        assert_eq!(e.code, pb::ErrorCode::UnknownLabel);
        let e = slice_of(&desc(40, 44, &[3, 1, 3, 1], &[1, 1, 1, 1]), &p).unwrap_err();
        assert_eq!(e.message, "descriptor lists label 41 more than once");
        let e = slice_of(&desc(40, 44, &[0, 2], &[3, 5]), &p).unwrap_err();
        assert_eq!(e.code, pb::ErrorCode::TooLarge);
        assert!(e.message.starts_with("objects of label 42 in the frame: 5"));
        let e = slice_of(&desc(40, 44, &[0, 1, 2], &[4, 4, 4]), &p).unwrap_err();
        assert!(e.message.starts_with("objects in the frame: 12"));
    }

    #[test]
    fn a_slice_round_trips_through_its_wire_form() {
        let d = to_proto(&[0.0, 2.0, 0.0, 1.0], 40, 44, 3, 7);
        assert_eq!((d.label_offsets.clone(), d.counts.clone()), (vec![1, 3], vec![2, 1]));
        assert_eq!(slice_of(&d, &places()).unwrap(), vec![0.0, 2.0, 0.0, 1.0]);
    }
}

/// A `PlacementReason` as the metrics name it (as `reason_name` in swarmrec/services/coordinator.py).
fn reason_name(reason: i32) -> &'static str {
    match pb::PlacementReason::try_from(reason) {
        Ok(pb::PlacementReason::Members) => "members",
        Ok(pb::PlacementReason::Rebalance) => "rebalance",
        Ok(pb::PlacementReason::HandoffDone) => "handoff_done",
        _ => "unspecified",
    }
}
