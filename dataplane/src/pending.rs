//! A descriptor's stores that some shard has not acknowledged yet, kept on disk: the
//! compiled twin of `swarmrec/services/pending.py`, in its log format (a `+` record adds
//! a slice, a `-` record with the slice's (robot, frame, label_lo, label_hi) as four
//! little-endian u32 marks it done), so a data folder moves between the two
//! implementations. Bounded: when full, the descriptor refuses new frames.

use std::collections::{BTreeMap, HashMap};

use prost::Message;

use crate::pb;
use crate::recordlog::RecordLog;

pub type SliceKey = (u32, u32, u32, u32);

pub fn slice_key(d: &pb::PartialDescriptor) -> SliceKey {
    (d.robot_id, d.frame_index, d.label_lo, d.label_hi)
}

pub struct PendingStores {
    log: RecordLog,
    pub capacity: usize,
    /// Oldest first: the order slices were added in.
    items: BTreeMap<u64, pb::PartialDescriptor>,
    seq_of: HashMap<SliceKey, u64>,
    next: u64,
    done_since_compaction: usize,
    /// The pass under way (see `next_batch`): the next sequence number it reaches and its
    /// end (exclusive); None between passes.
    pass: Option<(u64, u64)>,
}

impl PendingStores {
    /// The queue of `log` (its records replayed).
    pub fn new(log: RecordLog, records: Vec<Vec<u8>>, capacity: usize) -> PendingStores {
        let mut q = PendingStores {
            log,
            capacity,
            items: BTreeMap::new(),
            seq_of: HashMap::new(),
            next: 0,
            done_since_compaction: 0,
            pass: None,
        };
        for r in records {
            match r.split_first() {
                Some((b'+', body)) => {
                    if let Ok(d) = pb::PartialDescriptor::decode(body) {
                        q.insert(d);
                    }
                }
                Some((b'-', body)) if body.len() == 16 => {
                    let u = |i: usize| u32::from_le_bytes(body[4 * i..4 * i + 4].try_into().expect("4 bytes"));
                    q.remove(&(u(0), u(1), u(2), u(3)));
                    q.done_since_compaction += 1;
                }
                _ => {}
            }
        }
        q
    }

    /// As a Python dict keeps it: a key set again keeps its place and takes the new value.
    fn insert(&mut self, d: pb::PartialDescriptor) {
        let key = slice_key(&d);
        if let Some(&seq) = self.seq_of.get(&key) {
            self.items.insert(seq, d);
            return;
        }
        self.items.insert(self.next, d);
        self.seq_of.insert(key, self.next);
        self.next += 1;
    }

    fn remove(&mut self, key: &SliceKey) -> bool {
        match self.seq_of.remove(key) {
            Some(seq) => self.items.remove(&seq).is_some(),
            None => false,
        }
    }

    pub fn len(&self) -> usize {
        self.items.len()
    }

    pub fn room(&self) -> usize {
        self.capacity.saturating_sub(self.items.len())
    }

    /// Keeps `d` until `done`; on disk when this returns. Err (the refusal's message) when full.
    pub fn add(&mut self, d: &pb::PartialDescriptor) -> Result<(), String> {
        if self.seq_of.contains_key(&slice_key(d)) {
            return Ok(());
        }
        if self.items.len() >= self.capacity {
            return Err(format!(
                "{} stores are waiting for shards to acknowledge them (pending_capacity {}): \
                 refusing new frames until they are",
                self.items.len(),
                self.capacity
            ));
        }
        let mut record = vec![b'+'];
        record.extend(d.encode_to_vec());
        self.log.append(&record).map_err(|e| e.to_string())?;
        self.insert(d.clone());
        Ok(())
    }

    /// The next `limit` slices of the pass under way, and whether they end it. A pass
    /// takes every slice that was waiting when it began, oldest first, so a retry that
    /// sends a batch a round reaches each of them within one pass, however many wait.
    pub fn next_batch(&mut self, limit: usize) -> (Vec<pb::PartialDescriptor>, bool) {
        let (from, end) = self.pass.unwrap_or((0, self.next));
        let batch: Vec<(u64, pb::PartialDescriptor)> = self
            .items
            .range(from..end)
            .take(limit)
            .map(|(s, d)| (*s, d.clone()))
            .collect();
        let after = batch.last().map_or(end, |(s, _)| s + 1);
        let last = self.items.range(after..end).next().is_none();
        self.pass = if last { None } else { Some((after, end)) };
        (batch.into_iter().map(|(_, d)| d).collect(), last)
    }

    /// Every shard that must hold `d` has acknowledged it.
    pub fn done(&mut self, d: &pb::PartialDescriptor) -> std::io::Result<()> {
        let key = slice_key(d);
        if !self.remove(&key) {
            return Ok(());
        }
        let mut record = vec![b'-'];
        for v in [key.0, key.1, key.2, key.3] {
            record.extend(v.to_le_bytes());
        }
        self.log.append(&record)?;
        self.done_since_compaction += 1;
        if self.done_since_compaction > 1000.max(2 * self.items.len()) {
            // Rewrite the log with what is still waiting, so it does not grow for ever.
            let records: Vec<Vec<u8>> = self
                .items
                .values()
                .map(|d| {
                    let mut r = vec![b'+'];
                    r.extend(d.encode_to_vec());
                    r
                })
                .collect();
            self.log.rewrite(&records)?;
            self.done_since_compaction = 0;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn slice(frame: u32) -> pb::PartialDescriptor {
        pb::PartialDescriptor {
            robot_id: 1,
            frame_index: frame,
            label_lo: 0,
            label_hi: 10,
            label_offsets: vec![2],
            counts: vec![1],
            ..Default::default()
        }
    }

    #[test]
    fn waiting_slices_survive_a_restart_and_the_queue_is_bounded() {
        let dir = std::env::temp_dir().join(format!("swarmrec-pending-{}", std::process::id()));
        let path = dir.join("pending-stores.log");
        let _ = std::fs::remove_file(&path);
        {
            let (log, records) = RecordLog::open(Some(&path), false).unwrap();
            let mut q = PendingStores::new(log, records, 2);
            q.add(&slice(1)).unwrap();
            q.add(&slice(2)).unwrap();
            q.add(&slice(2)).unwrap(); // the same slice again: kept once
            assert!(q.add(&slice(3)).unwrap_err().contains("pending_capacity 2"));
            q.done(&slice(1)).unwrap();
        }
        let (log, records) = RecordLog::open(Some(&path), false).unwrap();
        let mut q = PendingStores::new(log, records, 2);
        assert_eq!(q.next_batch(10), (vec![slice(2)], true));
        assert_eq!(q.room(), 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_pass_reaches_every_slice_waiting_when_it_began_a_batch_at_a_time() {
        let (log, records) = RecordLog::open(None, false).unwrap();
        let mut q = PendingStores::new(log, records, 10);
        for f in 1..=5 {
            q.add(&slice(f)).unwrap();
        }
        assert_eq!(q.next_batch(2), (vec![slice(1), slice(2)], false));
        q.done(&slice(3)).unwrap(); // acknowledged meanwhile: the pass skips it
        q.add(&slice(6)).unwrap(); // added after the pass began: the next pass's
        assert_eq!(q.next_batch(2), (vec![slice(4), slice(5)], true));
        assert_eq!(
            q.next_batch(10),
            (vec![slice(1), slice(2), slice(4), slice(5), slice(6)], true)
        );
    }
}
