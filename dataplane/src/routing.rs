//! Where a querier sends each slice of a frame's descriptor: the index placement, kept
//! fresh. The compiled twin of `swarmrec/services/routing.py` (the reference): version 0
//! (the swarm's first placement, computed by Python) until it learns better; refreshed
//! from the shards when one says the sender is stale, the refusing shards asked first;
//! a group's query goes to its serving owner (`serving_owner`), the other live owners
//! next, a shard that timed out last for `suspect_s` seconds.

use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::caller::Caller;
use crate::pb;
use crate::placement::Placement;
use crate::runtime::{endpoint_key, lock, watch_tokens};

/// `swarmrec.core.placement.stable_hash`: one splitmix64 step per value, the value mixed
/// into the state first; the same in every process and run.
pub fn stable_hash(values: &[u64]) -> u64 {
    let mut x: u64 = 0;
    for &v in values {
        let mut z = (x ^ v).wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        x = z ^ (z >> 31);
    }
    x
}

/// The owner of `group` that answers the query of `robot`'s `frame`: a stable choice
/// among the owners in `alive` (None when none is).
pub fn serving_owner(p: &Placement, group: usize, robot: u32, frame: u32, alive: &[u32]) -> Option<u32> {
    let live: Vec<u32> = p.owners[group].iter().copied().filter(|m| alive.contains(m)).collect();
    if live.is_empty() {
        return None;
    }
    let h = stable_hash(&[u64::from(robot), u64::from(frame), group as u64]);
    Some(live[(h % live.len() as u64) as usize])
}

/// The newest placement among confirmed shards' states, of these `groups`.
pub fn newest_placement(states: &[pb::ShardState], groups: &[(u32, u32)]) -> Option<Placement> {
    let mut best: Option<Placement> = None;
    for st in states {
        let Some(msg) = st.placement.as_ref() else { continue };
        if !st.confirmed || msg.group_bounds.len() < 2 {
            continue;
        }
        let n_labels = msg.group_bounds[msg.group_bounds.len() - 1];
        let Ok(p) = Placement::from_proto(msg, n_labels) else {
            continue;
        };
        if p.groups != groups {
            continue;
        }
        if best.as_ref().is_none_or(|b| p.version > b.version) {
            best = Some(p);
        }
    }
    best
}

pub struct Routing {
    swarm: String,
    groups: Vec<(u32, u32)>,
    suspect: Duration,
    placement: Mutex<Placement>,
    suspects: Mutex<HashMap<u32, Instant>>,
    /// The ids of the live index shards, kept by a liveliness subscriber.
    live: Arc<Mutex<BTreeSet<u32>>>,
    watcher: Mutex<Option<Box<dyn std::any::Any + Send>>>,
}

impl Routing {
    pub fn new(swarm: &str, first: Placement, suspect_s: f64) -> Routing {
        Routing {
            swarm: swarm.to_string(),
            groups: first.groups.clone(),
            suspect: Duration::from_secs_f64(suspect_s.max(0.0)),
            placement: Mutex::new(first),
            suspects: Mutex::new(HashMap::new()),
            live: Arc::new(Mutex::new(BTreeSet::new())),
            watcher: Mutex::new(None),
        }
    }

    /// Watches the swarm's index shards' liveliness tokens (those already declared too).
    pub fn watch(&self, session: &zenoh::Session) -> anyhow::Result<()> {
        let live = self.live.clone();
        let sub = watch_tokens(session, &self.swarm, "alive", "index-shard", move |id, declared| {
            if declared {
                lock(&live).insert(id);
            } else {
                lock(&live).remove(&id);
            }
        })?;
        *lock(&self.watcher) = Some(sub);
        Ok(())
    }

    pub fn close(&self) {
        lock(&self.watcher).take();
    }

    pub fn placement(&self) -> Placement {
        lock(&self.placement).clone()
    }

    pub fn groups(&self) -> &[(u32, u32)] {
        &self.groups
    }

    /// Routes with `p` if it is newer; whether it was.
    pub fn update(&self, p: Placement) -> bool {
        let mut current = lock(&self.placement);
        if p.groups != self.groups || p.version <= current.version {
            return false;
        }
        *current = p;
        true
    }

    /// Routes with the newest placement a confirmed shard follows, after a request routed
    /// with version `routed` was refused: nothing to ask when this querier has moved past
    /// `routed` already (another refresh did). Else one of `from_shards` (those that just
    /// refused as routed with another placement: each usually follows the newer one), then
    /// the lowest live shard, the coordinator, which follows the newest placement (it
    /// publishes them); every shard only when neither gives anything newer. Every refusing
    /// shard, or every shard, answering each querier of a hundred after each placement change
    /// was more bytes than the queries themselves. `on_refresh` is called once per refresh.
    pub fn refresh(
        &self,
        caller: &Caller,
        from_shards: &BTreeSet<u32>,
        routed: u64,
        on_refresh: &dyn Fn(),
    ) -> Placement {
        let before = self.placement().version;
        if before > routed {
            return self.placement();
        }
        let req = pb::PlacementRequest {
            known_version: Some(before),
        };
        let coordinator = lock(&self.live).iter().next().copied();
        let first = from_shards.iter().next().copied();
        let rounds: [Vec<u32>; 2] = [
            first.into_iter().collect(),
            coordinator.filter(|c| Some(*c) != first).into_iter().collect(),
        ];
        for asked in rounds.iter().filter(|r| !r.is_empty()) {
            let pendings: Vec<_> = asked
                .iter()
                .map(|&shard| {
                    let key = endpoint_key(&self.swarm, "index-shard", shard, "placement");
                    caller.start(&key, "PlacementRequest", &req, Some(shard), "placement", false)
                })
                .collect();
            let states = decode_states(pendings.into_iter().flat_map(|p| p.gather("ShardState")));
            if let Some(newest) = newest_placement(&states, &self.groups) {
                if newest.version > before {
                    on_refresh();
                    self.update(newest);
                    return self.placement();
                }
            }
        }
        let key = format!("swarmrec/v1/{}/index-shard/*/placement", self.swarm);
        let pending = caller.start(&key, "PlacementRequest", &req, None, "placement", true);
        let states = decode_states(pending.gather("ShardState").into_iter());
        on_refresh();
        if let Some(newest) = newest_placement(&states, &self.groups) {
            self.update(newest);
        }
        self.placement()
    }

    /// `shard` did not answer in time: ask it last for a while.
    pub fn suspect(&self, shard: u32) {
        lock(&self.suspects).insert(shard, Instant::now() + self.suspect);
    }

    /// `group`'s owners, the one that should answer this frame's query first: the stable
    /// choice among live, unsuspected owners, then the other live ones, then the
    /// suspected, then those not seen alive.
    pub fn owners_in_order(&self, p: &Placement, group: usize, robot: u32, frame: u32) -> Vec<u32> {
        let owners = &p.owners[group];
        let live = lock(&self.live).clone();
        let now = Instant::now();
        let suspected: BTreeSet<u32> = {
            let mut s = lock(&self.suspects);
            s.retain(|_, until| *until > now);
            s.keys().copied().collect()
        };
        let good: Vec<u32> = owners
            .iter()
            .copied()
            .filter(|o| live.contains(o) && !suspected.contains(o))
            .collect();
        let first = serving_owner(p, group, robot, frame, &good);
        let mut out: Vec<u32> = first.into_iter().collect();
        out.extend(good.iter().copied().filter(|&o| Some(o) != first));
        out.extend(
            owners
                .iter()
                .copied()
                .filter(|o| live.contains(o) && suspected.contains(o)),
        );
        out.extend(owners.iter().copied().filter(|o| !live.contains(o)));
        out
    }
}

fn decode_states(outcomes: impl Iterator<Item = crate::caller::Outcome>) -> Vec<pb::ShardState> {
    use prost::Message;
    outcomes
        .filter_map(Result::ok)
        .filter_map(|data| pb::ShardState::decode(data.as_slice()).ok())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stable_hash_is_splitmix64() {
        // splitmix64's first output from seed 0 (a single 0 value).
        assert_eq!(stable_hash(&[0]), 0xE220_A839_7B1D_CDAF);
    }

    #[test]
    fn the_serving_owner_is_among_the_live_owners() {
        let p = Placement {
            version: 0,
            groups: vec![(0, 10), (10, 20)],
            owners: vec![vec![0, 1, 2], vec![1, 2]],
            members: vec![0, 1, 2],
            replicas: 2,
            learners: vec![vec![], vec![]],
            leaving: vec![vec![], vec![]],
        };
        assert_eq!(serving_owner(&p, 0, 3, 7, &[]), None);
        assert_eq!(serving_owner(&p, 0, 3, 7, &[2]), Some(2));
        let got = serving_owner(&p, 0, 3, 7, &[0, 1, 2]).unwrap();
        assert!(p.owners[0].contains(&got));
    }
}
