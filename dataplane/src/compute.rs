//! `swarmrec-dataplane compute`: the compiled computations one JSON line at a time,
//! so the exactness tests can hand the compiled code and the Python reference the
//! same inputs (`tests/integration/test_argsort.py`, `test_dataplane_index.py`).
//! Not a service: no zenoh, no settings; one answer line per request line.
use std::io::{BufRead, Write};

use anyhow::Context;
use serde::Deserialize;
use serde_json::{json, Value};

use crate::argsort::{argsort_at, Level};
use crate::index::RangeIndex;
use crate::pb;
use crate::placement::Placement;
use crate::selection::{select_candidates, select_robots};

#[derive(Deserialize)]
#[serde(tag = "op", rename_all = "snake_case", deny_unknown_fields)]
enum Request {
    /// The level numpy's 64-bit argsort runs at in this process.
    Level,
    /// `numpy.argsort(values)`; `level` forces a program (default: numpy's choice).
    Argsort {
        values: Value,
        dtype: String,
        level: Option<String>,
    },
    SelectCandidates {
        scores: Vec<f64>,
        n_ret: usize,
    },
    SelectRobots {
        robots: Vec<usize>,
        n_fq: usize,
        self_robot: Option<usize>,
    },
    /// A range index fed `stores` (robot, frame, slice) in order, then asked `queries`
    /// and read back: its rows in arrival order, each robot's frame count, and `gets`.
    RangeIndex {
        lo: u32,
        hi: u32,
        n_robots: u32,
        stores: Vec<(u32, u64, Vec<f64>)>,
        queries: Vec<IndexQuery>,
        gets: Vec<(u32, u64)>,
    },
    /// A placement from the wire: refused (the reference's message), or what it says of
    /// `shards` and label `ranges`.
    Placement {
        placement: PlacementJson,
        n_labels: u32,
        shards: Vec<u32>,
        ranges: Vec<(u32, u32)>,
    },
}

/// A `Placement` message as JSON (prost's types are not serde's).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PlacementJson {
    version: u64,
    group_bounds: Vec<u32>,
    groups: Vec<GroupJson>,
    members: Vec<u32>,
    replicas: u32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct GroupJson {
    owners: Vec<u32>,
    learners: Vec<u32>,
    leaving: Vec<u32>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct IndexQuery {
    counts: Vec<f64>,
    n_ret: usize,
    before: Option<u64>,
}

pub fn serve_lines(input: impl BufRead, mut output: impl Write) -> anyhow::Result<()> {
    for line in input.lines() {
        let line = line.context("stdin")?;
        if line.trim().is_empty() {
            continue;
        }
        let answer = match serde_json::from_str::<Request>(&line) {
            Ok(request) => answer(request).unwrap_or_else(|e| json!({"error": format!("{e:#}")})),
            Err(e) => json!({"error": format!("bad request: {e}")}),
        };
        writeln!(output, "{answer}")?;
        output.flush()?;
    }
    Ok(())
}

fn answer(request: Request) -> anyhow::Result<Value> {
    Ok(match request {
        Request::Level => json!({"result": Level::numpy().name()}),
        Request::Argsort { values, dtype, level } => {
            let level = match level {
                None => Level::numpy(),
                Some(name) => Level::parse(&name).with_context(|| format!("unknown level {name:?}"))?,
            };
            let order = match dtype.as_str() {
                "f64" => argsort_at(&serde_json::from_value::<Vec<f64>>(values)?, level),
                "i64" => argsort_at(&serde_json::from_value::<Vec<i64>>(values)?, level),
                other => anyhow::bail!("dtype {other:?}: f64 or i64"),
            };
            json!({"result": order})
        }
        Request::SelectCandidates { scores, n_ret } => json!({"result": select_candidates(&scores, n_ret)}),
        Request::SelectRobots {
            robots,
            n_fq,
            self_robot,
        } => {
            json!({"result": select_robots(&robots, n_fq, self_robot)})
        }
        Request::RangeIndex {
            lo,
            hi,
            n_robots,
            stores,
            queries,
            gets,
        } => {
            let mut index = RangeIndex::new(lo, hi, n_robots)?;
            for (robot, frame, counts) in &stores {
                index.add(*robot, *frame, counts)?;
            }
            let answers: Vec<Vec<(u32, u64, f64)>> = queries
                .iter()
                .map(|q| {
                    let found = index.candidates(&q.counts, q.n_ret, q.before);
                    found.iter().map(|c| (c.robot, c.frame, c.score)).collect()
                })
                .collect();
            let rows: Vec<(u32, u64, &[f64])> = index.rows(0, index.size());
            let frames: Vec<u64> = (0..n_robots).map(|r| index.frames_of(r)).collect();
            let got: Vec<Option<&[f64]>> = gets.iter().map(|&(r, f)| index.get(r, f)).collect();
            json!({"result": {"candidates": answers, "rows": rows, "frames_of": frames, "get": got}})
        }
        Request::Placement {
            placement,
            n_labels,
            shards,
            ranges,
        } => {
            let msg = pb::Placement {
                version: placement.version,
                group_bounds: placement.group_bounds,
                groups: placement
                    .groups
                    .into_iter()
                    .map(|g| pb::GroupOwners {
                        owners: g.owners,
                        learners: g.learners,
                        leaving: g.leaving,
                    })
                    .collect(),
                members: placement.members,
                replicas: placement.replicas,
            };
            match Placement::from_proto(&msg, n_labels) {
                Err(refused) => json!({"result": {"refused": refused}}),
                Ok(p) => {
                    let groups_of: Vec<Vec<usize>> = shards.iter().map(|&s| p.groups_of(s)).collect();
                    let learning: Vec<Vec<usize>> = shards.iter().map(|&s| p.learning(s)).collect();
                    let targets: Vec<Vec<u32>> = (0..p.groups.len()).map(|g| p.store_targets(g)).collect();
                    let of_range: Vec<Option<usize>> =
                        ranges.iter().map(|&(lo, hi)| p.group_of_range(lo, hi)).collect();
                    let same = p.to_proto() == msg;
                    json!({"result": {
                        "groups_of": groups_of, "learning": learning, "store_targets": targets,
                        "settled": p.settled(), "group_of_range": of_range, "round_trip": same,
                    }})
                }
            }
        }
    })
}
