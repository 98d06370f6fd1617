//! The verifier, compiled: holds its robot's constellations and verifies queries
//! against them geometrically. The contract of `swarmrec/services/verifier.py`
//! (the reference), endpoint for endpoint:
//!
//! * `store`: a Constellation of this robot -> StoreReply; appended to the record log
//!   (`<data_dir>/verifier.log`, the Python log format) before the answer, replayed
//!   on start. The same frame again is accepted as before; a stored frame index with
//!   other content is refused (ALREADY_EXISTS).
//! * `verify`: a VerifyRequest -> VerifyReply, every candidate with a score > 0, best
//!   first (ties by frame index).
//!
//! The same bounds are checked before any work: objects a frame and a label
//! (TOO_LARGE), frames to verify and object pairs to compare (TOO_LARGE).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use prost::Message;

use crate::association::{verify, Frame, Knobs};
use crate::metrics::{Metric, ServiceMetrics};
use crate::pb;
use crate::recordlog::RecordLog;
use crate::runtime::{decode, missing, Endpoint, Log, RequestError, Service};
use crate::spec::{PlaceSpec, ServiceSpec};

/// Frame indices are below this (`swarmrec.services.limits.MAX_FRAME_INDEX`).
pub const MAX_FRAME_INDEX: u32 = 1 << 20;

struct Stored {
    labels: Vec<u32>,
    positions: Vec<f64>,
    frame_id: String,
    table: Frame,
}

struct State {
    frames: HashMap<u32, Stored>,
    /// Frame indices in the order they were stored (a verify of "all frames" walks them so).
    order: Vec<u32>,
    log: RecordLog,
}

pub struct Verifier {
    robot: u32,
    n_robots: u32,
    places: PlaceSpec,
    knobs: Knobs,
    state: Mutex<State>,
    metrics: Arc<ServiceMetrics>,
    stored_frames: Metric,
    log: Log,
}

/// A constellation's objects checked against the label list and the bounds, in the
/// order `swarmrec.wire.codec.constellation_from_proto` checks them.
pub fn objects(msg: &pb::Constellation, places: &PlaceSpec) -> Result<(Vec<u32>, Vec<f64>), RequestError> {
    let n = msg.labels.len();
    if n as u64 > u64::from(places.max_objects_per_frame) {
        return Err(RequestError::too_large(
            "objects in the frame",
            n as u64,
            places.max_objects_per_frame.into(),
            "max_objects_per_frame",
        ));
    }
    let exact = !msg.positions_m.is_empty();
    if exact && !msg.positions_mm.is_empty() {
        return Err(RequestError::invalid(
            "constellation carries both positions_mm and positions_m; send one",
        ));
    }
    let count = if exact {
        msg.positions_m.len()
    } else {
        msg.positions_mm.len()
    };
    if count != 3 * n {
        let field = if exact { "positions_m" } else { "positions_mm" };
        return Err(RequestError::invalid(format!(
            "constellation has {n} labels but {count} coordinates in {field}; expected 3 per label ({})",
            3 * n
        )));
    }
    if let Some(k) = msg.labels.iter().position(|&l| l >= places.n_labels) {
        return Err(RequestError::new(
            pb::ErrorCode::UnknownLabel,
            format!(
                "object {k} has label {}, outside the label list of {} labels",
                msg.labels[k], places.n_labels
            ),
        ));
    }
    let mut counts: HashMap<u32, u32> = HashMap::new();
    for &l in &msg.labels {
        *counts.entry(l).or_insert(0) += 1;
    }
    // The first label (lowest index) holding the most objects, as numpy's argmax names it.
    if let Some((&label, &c)) = counts.iter().max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0))) {
        if c > places.max_objects_per_label {
            return Err(RequestError::too_large(
                &format!("objects of label {label} in the frame"),
                c.into(),
                places.max_objects_per_label.into(),
                "max_objects_per_label",
            ));
        }
    }
    let positions: Vec<f64> = if exact {
        if let Some(k) = msg.positions_m.chunks(3).position(|p| p.iter().any(|v| !v.is_finite())) {
            return Err(RequestError::invalid(format!(
                "object {k} has a non-finite position {:?}",
                &msg.positions_m[3 * k..3 * k + 3]
            )));
        }
        msg.positions_m.clone()
    } else {
        // Divided, not multiplied by 0.001: the double nearest the exact decimal, as the reference.
        msg.positions_mm.iter().map(|&mm| f64::from(mm) / 1000.0).collect()
    };
    Ok((msg.labels.clone(), positions))
}

/// The query's robot, which orders the association's arguments with the stored frame's
/// (robot, frame): the query's own when it names one, else the caller's when the caller is
/// another robot of the swarm (a descriptor leaves robot and frame out of a request to
/// another robot's verifier: the robots differ, so the frame cannot matter), else 0.
pub fn query_robot(query: &pb::Constellation, caller: Option<u32>, own: u32) -> u32 {
    match (query.robot_id, caller) {
        (Some(r), _) => r,
        (None, Some(c)) if c != own => c,
        _ => 0,
    }
}

impl Verifier {
    pub fn new(spec: &ServiceSpec, metrics: Arc<ServiceMetrics>, log: Log) -> anyhow::Result<Verifier> {
        let places = spec.places.clone();
        let knobs = Knobs {
            d: places.d,
            min_common: places.min_common,
            same_label_only: places.same_label_only,
        };
        let stored_frames = metrics.registry.gauge(
            "swarmrec_verifier_stored_frames",
            "Constellations held by this verifier",
            &[],
        );
        let path = spec.data_dir.as_ref().map(|d| d.join("verifier.log"));
        let (record_log, records) = RecordLog::open(path.as_deref(), spec.fsync)?;
        if record_log.truncated_bytes > 0 {
            log.warning(
                "cut a truncated record off the log",
                serde_json::json!({"path": path, "bytes": record_log.truncated_bytes}),
            );
        }
        let mut state = State {
            frames: HashMap::new(),
            order: Vec::new(),
            log: record_log,
        };
        let mut skipped = 0;
        for record in records {
            let msg = match pb::Constellation::decode(&record[..]) {
                Ok(m) => m,
                Err(_) => {
                    skipped += 1;
                    continue;
                }
            };
            match objects(&msg, &places) {
                Ok((labels, positions)) => {
                    // A log written before stores were idempotent may hold a frame twice: the last wins.
                    let f = msg.frame_index();
                    let table = Frame::new(&labels, &positions);
                    if state
                        .frames
                        .insert(
                            f,
                            Stored {
                                labels,
                                positions,
                                frame_id: msg.frame_id,
                                table,
                            },
                        )
                        .is_none()
                    {
                        state.order.push(f);
                    }
                }
                Err(e) => {
                    // Stored before the bounds existed (or were lowered): skipped, not deleted.
                    skipped += 1;
                    log.warning(
                        "stored frame over the bounds skipped",
                        serde_json::json!({"frame": msg.frame_index(), "reason": e.message}),
                    );
                }
            }
        }
        metrics.registry.set(stored_frames, &[], state.frames.len() as f64);
        log.info(
            "frames loaded",
            serde_json::json!({"stored": state.frames.len(), "skipped": skipped}),
        );
        Ok(Verifier {
            robot: spec.robot,
            n_robots: spec.n_robots,
            places,
            knobs,
            state: Mutex::new(state),
            metrics,
            stored_frames,
            log,
        })
    }

    /// The state, also after a handler panicked holding it (answered INTERNAL): what it
    /// holds is only ever changed by whole appends, so it stays consistent.
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn constellation(&self, msg: &pb::Constellation) -> Result<(Vec<u32>, Vec<f64>), RequestError> {
        if msg.robot_id() >= self.n_robots {
            return Err(RequestError::invalid(format!(
                "robot {} is not in this swarm of {} robots",
                msg.robot_id(),
                self.n_robots
            )));
        }
        if msg.frame_index() >= MAX_FRAME_INDEX {
            return Err(RequestError::invalid(format!(
                "frame index must be below {MAX_FRAME_INDEX}, got {}",
                msg.frame_index()
            )));
        }
        objects(msg, &self.places)
    }

    fn store(&self, data: &[u8]) -> Result<pb::StoreReply, RequestError> {
        let msg: pb::Constellation = decode(data, "swarmrec.v1.Constellation")?;
        if msg.robot_id.is_none() {
            return Err(missing("swarmrec.v1.Constellation", "robot_id"));
        }
        if msg.frame_index.is_none() {
            return Err(missing("swarmrec.v1.Constellation", "frame_index"));
        }
        if msg.robot_id() != self.robot {
            return Err(RequestError::invalid(format!(
                "verifier {} stores only its own robot's frames, got robot {}",
                self.robot,
                msg.robot_id()
            )));
        }
        let (labels, positions) = self.constellation(&msg)?;
        let f = msg.frame_index();
        let table = Frame::new(&labels, &positions);
        let mut state = self.lock();
        match state.frames.get(&f) {
            None => {
                state
                    .log
                    .append(&msg.encode_to_vec())
                    .map_err(|e| RequestError::new(pb::ErrorCode::Internal, format!("record log: {e}")))?;
                let frame_id = msg.frame_id;
                state.frames.insert(
                    f,
                    Stored {
                        labels,
                        positions,
                        frame_id,
                        table,
                    },
                );
                state.order.push(f);
            }
            // Peers may already have matched against the stored frame: replacing it would
            // change answers behind their back (and an empty payload would wipe it).
            Some(old) if !(old.labels == labels && old.positions == positions && old.frame_id == msg.frame_id) => {
                return Err(RequestError::new(
                    pb::ErrorCode::AlreadyExists,
                    format!(
                        "frame {f} of robot {} is already stored with other content; stores are idempotent (the \
                         same frame again is accepted), a changed frame needs a new index",
                        self.robot
                    ),
                ));
            }
            Some(_) => {}
        }
        let n = state.frames.len();
        drop(state);
        self.metrics.registry.set(self.stored_frames, &[], n as f64);
        Ok(pb::StoreReply {
            stored_frames: n as u32,
        })
    }

    fn verify_request(&self, data: &[u8], caller: Option<u32>) -> Result<pb::VerifyReply, RequestError> {
        let req: pb::VerifyRequest = decode(data, "swarmrec.v1.VerifyRequest")?;
        let Some(query_msg) = req.query.as_ref() else {
            return Err(missing("swarmrec.v1.VerifyRequest", "query"));
        };
        let (labels, positions) = self.constellation(query_msg)?;
        let mut knobs = self.knobs;
        if let Some(d) = req.distance_threshold_m {
            if !(d.is_finite() && d > 0.0) {
                return Err(RequestError::invalid(format!(
                    "distance_threshold_m must be a positive number, got {d}"
                )));
            }
            knobs.d = f64::from(d);
        }
        let n_query = labels.len() as u64;
        let max_frames = self.places.verify_max_frames;
        let state = self.lock();
        let frames: Vec<(u32, &Frame)> = if req.candidate_frame_indices.is_empty() {
            let all: Vec<(u32, &Frame)> = state
                .order
                .iter()
                .map(|f| (*f, &state.frames[f]))
                .filter(|(_, s)| s.labels.len() as u64 >= u64::from(self.knobs.min_common))
                .map(|(f, s)| (f, &s.table))
                .collect();
            if all.len() as u64 > u64::from(max_frames) {
                return Err(RequestError::too_large(
                    "stored frames to verify (no candidate list: all of them)",
                    all.len() as u64,
                    max_frames.into(),
                    "verify_max_frames",
                ));
            }
            all
        } else {
            let asked = req.candidate_frame_indices.len() as u64;
            if asked > u64::from(max_frames) {
                return Err(RequestError::too_large(
                    "candidate frames to verify",
                    asked,
                    max_frames.into(),
                    "verify_max_frames",
                ));
            }
            let mut wanted = req.candidate_frame_indices.clone();
            wanted.sort_unstable();
            wanted.dedup();
            let found: Vec<(u32, &Frame)> = wanted
                .iter()
                .filter_map(|f| state.frames.get(f).map(|s| (*f, &s.table)))
                .collect();
            if found.len() < wanted.len() {
                self.log.warning(
                    "asked to verify frames it does not hold",
                    serde_json::json!({"missing": wanted.len() - found.len()}),
                );
            }
            found
        };
        let pairs: u64 = n_query * frames.iter().map(|(_, t)| t.n_objects() as u64).sum::<u64>();
        if pairs > self.places.verify_max_object_pairs {
            return Err(RequestError::too_large(
                "object pairs to compare",
                pairs,
                self.places.verify_max_object_pairs,
                "verify_max_object_pairs",
            ));
        }
        // Packed only now: a request over the bounds is refused before any work.
        let query = Frame::new(&labels, &positions);
        let query_key = (query_robot(query_msg, caller, self.robot), query_msg.frame_index());
        let mut results: Vec<_> = verify(&query, query_key, self.robot, frames, knobs)
            .into_iter()
            .filter(|m| m.score > 0.0)
            .collect();
        drop(state);
        if req.max_matches > 0 {
            results.truncate(req.max_matches as usize);
        }
        let matches = results
            .into_iter()
            .map(|m| pb::VerifyMatch {
                frame_index: m.frame,
                n_matched: m.pairs.len() as u32,
                n_common: m.n_common,
                n_union: m.n_union,
                object_pairs: if req.include_pairs {
                    m.pairs.iter().flat_map(|&(q, s)| [q, s]).collect()
                } else {
                    Vec::new()
                },
            })
            .collect();
        Ok(pb::VerifyReply {
            query_id: req.query_id,
            robot_id: self.robot,
            matches,
        })
    }
}

impl Service for Verifier {
    fn endpoints(self: Arc<Self>) -> Vec<Endpoint> {
        let (a, b) = (self.clone(), self);
        vec![
            Endpoint {
                name: "store",
                request: "Constellation",
                handler: Box::new(move |data, _caller| a.store(data).map(|r| ("StoreReply", r.encode_to_vec()))),
                blocking: false,
            },
            Endpoint {
                name: "verify",
                request: "VerifyRequest",
                handler: Box::new(move |data, caller| {
                    b.verify_request(data, caller)
                        .map(|r| ("VerifyReply", r.encode_to_vec()))
                }),
                blocking: false,
            },
        ]
    }

    fn member_info(&self) -> pb::MemberInfo {
        let n = self.lock().frames.len();
        pb::MemberInfo {
            stored_items: n as u64,
            n_labels: self.places.n_labels,
            ..Default::default()
        }
    }
}
