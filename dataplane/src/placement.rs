//! The elastic index's placement: which shards hold each label group. The compiled twin
//! of `swarmrec/core/placement.py`'s `Placement` and of the checks
//! `swarmrec/wire/placement.py` makes on one that arrives (the reference): a placement
//! from the wire is checked whole before anyone follows it, with the reference's
//! messages, and is never half-followed.
//!
//! Computing placements (the ring, rebalancing, handoffs) stays with the coordinator in
//! Python; a shard only follows them. `tests/integration/test_dataplane_index.py`
//! compares the checks and the questions below with the reference on random placements,
//! valid and broken.
use crate::pb;

/// Most groups a placement may have.
pub const MAX_GROUPS: usize = 4096;
/// Largest shard id (the robot ids' bound).
pub const MAX_SHARD_ID: u32 = 999_999;
/// A group's owners, learners or leaving owners: no more than this many shards.
const MAX_PER_GROUP: usize = 64;

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Placement {
    pub version: u64,
    pub groups: Vec<(u32, u32)>,
    pub owners: Vec<Vec<u32>>,
    pub members: Vec<u32>,
    pub replicas: u32,
    pub learners: Vec<Vec<u32>>,
    pub leaving: Vec<Vec<u32>>,
}

impl Placement {
    /// The placement in `msg` for a label list of `n_labels`; the first problem (the wire's
    /// bounds) or every problem (the placement's own rules), worded as the reference words them.
    pub fn from_proto(msg: &pb::Placement, n_labels: u32) -> Result<Placement, String> {
        let bounds = &msg.group_bounds;
        if !(2..=MAX_GROUPS + 1).contains(&bounds.len()) {
            return Err(format!(
                "a placement needs 1 to {MAX_GROUPS} groups, got {}",
                bounds.len() as i64 - 1
            ));
        }
        let (first, last) = (bounds[0], bounds[bounds.len() - 1]);
        if first != 0 || last != n_labels {
            return Err(format!(
                "a placement's groups must cover labels [0, {n_labels}), got [{first}, {last})"
            ));
        }
        if msg.groups.len() != bounds.len() - 1 {
            return Err(format!(
                "{} groups but {} owner lists",
                bounds.len() - 1,
                msg.groups.len()
            ));
        }
        if msg.members.len() > MAX_GROUPS || msg.members.iter().any(|&m| m > MAX_SHARD_ID) {
            return Err(format!(
                "a placement lists at most {MAX_GROUPS} shards, ids <= {MAX_SHARD_ID}"
            ));
        }
        if !(1..=MAX_PER_GROUP as u32).contains(&msg.replicas) {
            return Err(format!("replicas must be 1 to {MAX_PER_GROUP}, got {}", msg.replicas));
        }
        for g in &msg.groups {
            if g.owners.len().max(g.learners.len()).max(g.leaving.len()) > MAX_PER_GROUP {
                return Err(format!("a group lists at most {MAX_PER_GROUP} shards"));
            }
        }
        let placement = Placement {
            version: msg.version,
            groups: bounds.windows(2).map(|w| (w[0], w[1])).collect(),
            owners: msg.groups.iter().map(|g| g.owners.clone()).collect(),
            members: msg.members.clone(),
            replicas: msg.replicas,
            learners: msg.groups.iter().map(|g| g.learners.clone()).collect(),
            leaving: msg.groups.iter().map(|g| g.leaving.clone()).collect(),
        };
        let problems = placement.problems();
        if problems.is_empty() {
            Ok(placement)
        } else {
            Err(format!("invalid placement: {}", problems.join("; ")))
        }
    }

    pub fn to_proto(&self) -> pb::Placement {
        let mut bounds: Vec<u32> = self.groups.iter().map(|g| g.0).collect();
        bounds.extend(self.groups.last().map(|g| g.1));
        pb::Placement {
            version: self.version,
            group_bounds: bounds,
            groups: (0..self.groups.len())
                .map(|g| pb::GroupOwners {
                    owners: self.owners[g].clone(),
                    learners: self.learners[g].clone(),
                    leaving: self.leaving[g].clone(),
                })
                .collect(),
            members: self.members.clone(),
            replicas: self.replicas,
        }
    }

    /// The reference's rules (`Placement.__post_init__`), every broken one.
    fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        let mut prev = 0;
        for (g, &(lo, hi)) in self.groups.iter().enumerate() {
            if lo != prev || hi <= lo {
                problems.push(format!(
                    "group {g} is [{lo}, {hi}); groups must tile the labels in order"
                ));
            }
            prev = hi;
        }
        if distinct(&self.members) != self.members.len() {
            problems.push("a member is listed twice".to_string());
        }
        let member = |s: &u32| self.members.contains(s);
        for (g, own) in self.owners.iter().enumerate() {
            if own.is_empty() {
                problems.push(format!("group {g} has no owner"));
            }
            if distinct(own) != own.len() {
                problems.push(format!("group {g} lists an owner twice"));
            }
            let mut outside: Vec<u32> = own.iter().copied().filter(|s| !member(s)).collect();
            if !outside.is_empty() {
                outside.sort_unstable();
                outside.dedup();
                problems.push(format!("group {g} is owned by non-members {outside:?}"));
            }
        }
        for g in 0..self.groups.len() {
            let (own, learn, leave) = (&self.owners[g], &self.learners[g], &self.leaving[g]);
            if learn.iter().any(|s| own.contains(s)) || !learn.iter().all(member) || distinct(learn) != learn.len() {
                problems.push(format!("group {g}'s learners must be members that do not own it yet"));
            }
            let all_owners_leave = !own.is_empty() && own.iter().all(|s| leave.contains(s));
            if !leave.iter().all(|s| own.contains(s)) || (all_owners_leave && learn.is_empty()) {
                problems.push(format!(
                    "group {g}'s leaving owners must be owners, and not all of them"
                ));
            }
        }
        problems
    }

    /// The groups `shard` owns (answers queries for).
    pub fn groups_of(&self, shard: u32) -> Vec<usize> {
        (0..self.owners.len())
            .filter(|&g| self.owners[g].contains(&shard))
            .collect()
    }

    /// The groups `shard` is copying (stores them, answers no query for them).
    pub fn learning(&self, shard: u32) -> Vec<usize> {
        (0..self.learners.len())
            .filter(|&g| self.learners[g].contains(&shard))
            .collect()
    }

    /// Every shard that must store a descriptor of `group`: owners, then learners.
    pub fn store_targets(&self, group: usize) -> Vec<u32> {
        self.owners[group]
            .iter()
            .chain(&self.learners[group])
            .copied()
            .collect()
    }

    /// No handoff in progress (no learner, no leaving owner).
    pub fn settled(&self) -> bool {
        self.learners.iter().all(Vec::is_empty) && self.leaving.iter().all(Vec::is_empty)
    }

    /// The group whose label range is exactly `[lo, hi)`.
    pub fn group_of_range(&self, lo: u32, hi: u32) -> Option<usize> {
        self.groups.iter().position(|&g| g == (lo, hi))
    }
}

fn distinct(ids: &[u32]) -> usize {
    let mut v = ids.to_vec();
    v.sort_unstable();
    v.dedup();
    v.len()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn msg(bounds: &[u32], owners: &[&[u32]], members: &[u32]) -> pb::Placement {
        pb::Placement {
            version: 3,
            group_bounds: bounds.to_vec(),
            groups: owners
                .iter()
                .map(|o| pb::GroupOwners {
                    owners: o.to_vec(),
                    learners: vec![],
                    leaving: vec![],
                })
                .collect(),
            members: members.to_vec(),
            replicas: 2,
        }
    }

    #[test]
    fn a_valid_placement_round_trips_and_answers() {
        let m = msg(&[0, 40, 80], &[&[0, 1], &[1, 2]], &[0, 1, 2]);
        let p = Placement::from_proto(&m, 80).unwrap();
        assert_eq!(p.to_proto(), m);
        assert_eq!(p.groups_of(1), vec![0, 1]);
        assert_eq!(p.group_of_range(40, 80), Some(1));
        assert_eq!(p.group_of_range(40, 79), None);
        assert!(p.settled());
        assert_eq!(p.store_targets(1), vec![1, 2]);
    }

    #[test]
    fn broken_placements_are_refused_whole() {
        assert!(Placement::from_proto(&msg(&[0, 40, 80], &[&[0], &[]], &[0]), 80)
            .unwrap_err()
            .contains("group 1 has no owner"));
        assert!(Placement::from_proto(&msg(&[0, 40, 80], &[&[0], &[5]], &[0]), 80)
            .unwrap_err()
            .contains("non-members [5]"));
        assert!(Placement::from_proto(&msg(&[0, 40], &[&[0]], &[0]), 80)
            .unwrap_err()
            .contains("must cover labels [0, 80)"));
    }
}
