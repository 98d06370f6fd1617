//! What `swarmrec serve`/`host` hand the compiled host: every setting already
//! resolved by the Python configuration (flags, environment, files, defaults), so
//! the two implementations of a kind can never read their settings differently.
//! The zenoh configuration travels whole, as the Python binding printed it (the
//! same zenoh version parses it), with its TLS files and access-control choices.

use std::path::PathBuf;

use serde::Deserialize;

#[derive(Debug, Deserialize)]
pub struct HostSpec {
    /// The zenoh configuration (JSON), as `str(zenoh.Config)` printed it.
    pub zenoh: serde_json::Value,
    /// Where the process serves Prometheus (port 0: a free one, -1: none).
    pub metrics_host: String,
    pub metrics_port: i32,
    pub log_level: String,
    /// swarmrec's version, reported in MemberInfo.
    pub version: String,
    pub services: Vec<ServiceSpec>,
    /// The command of the Python process that runs the index shards' coordinators beside
    /// this host (empty: none). Started once the session is open (the shards are declared
    /// ready when it has checked their placements), stopped after the shards drained, and it
    /// dies with the host (`PR_SET_PDEATHSIG`).
    #[serde(default)]
    pub coordinator: Vec<String>,
    /// The host is the child of a Python host (a host mixing both kinds): it dies with it.
    #[serde(default)]
    pub die_with_parent: bool,
}

#[derive(Debug, Deserialize)]
pub struct ServiceSpec {
    pub kind: String,
    /// The `swarmrec.v1.ServiceKind` value.
    pub wire_kind: i32,
    pub swarm: String,
    pub robot: u32,
    pub n_robots: u32,
    pub max_message_bytes: usize,
    pub data_dir: Option<PathBuf>,
    #[serde(default)]
    pub fsync: bool,
    /// The place-recognition settings (absent for a router, which has none).
    #[serde(default)]
    pub places: PlaceSpec,
    /// An index shard's settings (absent for other kinds).
    #[serde(default)]
    pub index: Option<IndexSpec>,
    /// A descriptor's settings (absent for other kinds).
    #[serde(default)]
    pub descriptor: Option<DescriptorSpec>,
    /// A replaying detector's frames and settings (absent for other kinds).
    #[serde(default)]
    pub detector: Option<DetectorSpec>,
}

/// A replaying detector: its robot's block of the dataset, read and put on the wire by
/// the Python reader and codec (`swarmrec.services.detector.replay.wire_frames`), and the
/// outbox's settings (DetectorSettings).
#[derive(Clone, Debug, Deserialize)]
pub struct DetectorSpec {
    /// Where the frames were read (for the log).
    pub dataset: String,
    /// Each frame of the block, in order.
    pub frames: Vec<FrameSpec>,
    pub outbox_capacity: usize,
    pub outbox_retry_s: f64,
    /// How long the descriptor may take over one frame (a query of nested requests).
    pub process_timeout_s: f64,
}

/// One frame: its `swarmrec.v1.Constellation` bytes (hex), or why it cannot be sent.
#[derive(Clone, Debug, Deserialize)]
pub struct FrameSpec {
    #[serde(default)]
    pub wire: Option<String>,
    #[serde(default)]
    pub unsendable: Option<String>,
}

/// What a descriptor reads beyond the place settings (its preset, PlaceSettings,
/// IndexSettings, ExplainSettings and the bus's request timeout), resolved by Python.
#[derive(Clone, Debug, Deserialize)]
pub struct DescriptorSpec {
    pub n_ret: u32,
    pub n_fq: u32,
    pub min_objects: u32,
    pub exclusion: u32,
    pub loop_closure_min_score: f64,
    pub suspect_s: f64,
    pub pending_capacity: usize,
    pub retry_interval_s: f64,
    pub explain_reports: u32,
    pub request_timeout_s: f64,
    /// The placement a querier routes with until it learns better (version 0, `ring`), as
    /// serialized `swarmrec.v1.Placement` bytes, computed by the Python core.
    pub initial_placement: Vec<u8>,
}

/// What an index shard reads beyond the place settings (IndexSettings, the label groups
/// and the swarm's first placement), resolved by Python.
#[derive(Clone, Debug, Deserialize)]
pub struct IndexSpec {
    /// The label groups `[lo, hi)` (PlaceSettings.bounds).
    pub groups: Vec<(u32, u32)>,
    /// Candidates a partial query returns when it asks for 0 (the preset's n_ret).
    pub n_ret: u32,
    /// Shards answer from the frames stored before a query's step (PlaceSettings.lockstep).
    pub lockstep: bool,
    pub transfer_page: u32,
    pub drain_timeout_s: f64,
    /// The placement a shard with nothing on disk starts from (version 0, `ring`), as
    /// serialized `swarmrec.v1.Placement` bytes: computed by the one implementation of
    /// the placement rules, the Python core.
    pub initial_placement: Vec<u8>,
}

/// The place-recognition settings a verifier reads (PlaceSettings and its preset).
#[derive(Clone, Debug, Default, Deserialize)]
pub struct PlaceSpec {
    pub n_labels: u32,
    pub d: f64,
    pub min_common: u32,
    pub same_label_only: bool,
    pub max_objects_per_frame: u32,
    pub max_objects_per_label: u32,
    pub verify_max_frames: u32,
    pub verify_max_object_pairs: u64,
}
