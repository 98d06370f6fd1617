//! The append-only record log of `swarmrec/runtime/storage.py`, byte for byte: each
//! record is a 4-byte little-endian length and a serialized message. A service
//! appends before it answers and replays on start; a truncated last record (a crash
//! mid-append) is cut off, so a log moves between the Python and the compiled
//! implementation of a kind in either direction.

use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::path::Path;

/// Largest record (the Python log's limit; max_message_bytes is capped below it).
pub const MAX_RECORD_BYTES: usize = 1 << 24;

pub struct RecordLog {
    file: Option<File>,
    path: Option<std::path::PathBuf>,
    fsync: bool,
    /// Bytes of a truncated last record cut off when opened.
    pub truncated_bytes: u64,
}

fn scan(data: &[u8]) -> (Vec<&[u8]>, usize) {
    let (mut records, mut pos) = (Vec::new(), 0usize);
    while data.len() - pos >= 4 {
        let n = u32::from_le_bytes(data[pos..pos + 4].try_into().expect("4 bytes")) as usize;
        if n > MAX_RECORD_BYTES || data.len() - pos - 4 < n {
            break;
        }
        records.push(&data[pos + 4..pos + 4 + n]);
        pos += 4 + n;
    }
    (records, pos)
}

impl RecordLog {
    /// Opens (creating its folder) the log at `path`, or a log kept nowhere for None;
    /// returns it with every whole record, oldest first.
    pub fn open(path: Option<&Path>, fsync: bool) -> std::io::Result<(RecordLog, Vec<Vec<u8>>)> {
        let Some(path) = path else {
            return Ok((
                RecordLog {
                    file: None,
                    path: None,
                    fsync,
                    truncated_bytes: 0,
                },
                Vec::new(),
            ));
        };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        let mut data = Vec::new();
        if path.exists() {
            File::open(path)?.read_to_end(&mut data)?;
        }
        let (records, good) = scan(&data);
        let records: Vec<Vec<u8>> = records.into_iter().map(<[u8]>::to_vec).collect();
        let truncated_bytes = (data.len() - good) as u64;
        if truncated_bytes > 0 {
            OpenOptions::new().write(true).open(path)?.set_len(good as u64)?;
        }
        let file = OpenOptions::new().create(true).append(true).open(path)?;
        Ok((
            RecordLog {
                file: Some(file),
                path: Some(path.to_path_buf()),
                fsync,
                truncated_bytes,
            },
            records,
        ))
    }

    /// Every whole record in the file now, oldest first (none for a log kept nowhere): an
    /// index shard taking a group back reads its own records of it again.
    pub fn records(&self) -> std::io::Result<Vec<Vec<u8>>> {
        let Some(path) = &self.path else { return Ok(Vec::new()) };
        let data = std::fs::read(path)?;
        Ok(scan(&data).0.into_iter().map(<[u8]>::to_vec).collect())
    }

    /// Replaces every record with `records` (compaction): written to a new file, synced,
    /// then renamed over the log, so a crash leaves the old log or the new one whole.
    pub fn rewrite(&mut self, records: &[Vec<u8>]) -> std::io::Result<()> {
        let Some(path) = self.path.clone() else { return Ok(()) };
        let mut name = path.file_name().unwrap_or_default().to_os_string();
        name.push(".tmp");
        let tmp = path.with_file_name(name);
        {
            let mut f = File::create(&tmp)?;
            let mut buf = Vec::new();
            for r in records {
                if r.len() > MAX_RECORD_BYTES {
                    return Err(std::io::Error::other(format!(
                        "record of {} bytes is over {MAX_RECORD_BYTES}",
                        r.len()
                    )));
                }
                buf.extend_from_slice(&(r.len() as u32).to_le_bytes());
                buf.extend_from_slice(r);
            }
            f.write_all(&buf)?;
            f.sync_all()?;
        }
        self.file = None;
        std::fs::rename(&tmp, &path)?;
        self.file = Some(OpenOptions::new().create(true).append(true).open(&path)?);
        Ok(())
    }

    /// Appends one record; it is in the file (and synced if asked) on return.
    pub fn append(&mut self, record: &[u8]) -> std::io::Result<()> {
        if record.len() > MAX_RECORD_BYTES {
            return Err(std::io::Error::other(format!(
                "record of {} bytes exceeds the log's limit of {MAX_RECORD_BYTES}",
                record.len()
            )));
        }
        let Some(file) = self.file.as_mut() else { return Ok(()) };
        let mut buf = Vec::with_capacity(4 + record.len());
        buf.extend_from_slice(&(record.len() as u32).to_le_bytes());
        buf.extend_from_slice(record);
        file.write_all(&buf)?; // one write: a crash leaves a whole record or a cut one
        if self.fsync {
            file.sync_data()?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_come_back_and_a_cut_last_record_is_dropped() {
        let dir = std::env::temp_dir().join(format!("swarmrec-log-{}", std::process::id()));
        let path = dir.join("x.log");
        let _ = std::fs::remove_file(&path);
        {
            let (mut log, old) = RecordLog::open(Some(&path), false).unwrap();
            assert!(old.is_empty());
            log.append(b"one").unwrap();
            log.append(b"").unwrap();
            log.append(b"three").unwrap();
        }
        // A crash in the middle of an append: a length and half a body.
        let mut f = OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(&[9, 0, 0, 0, b'x']).unwrap();
        drop(f);
        let (mut log, records) = RecordLog::open(Some(&path), false).unwrap();
        assert_eq!(records, vec![b"one".to_vec(), Vec::new(), b"three".to_vec()]);
        assert_eq!(log.truncated_bytes, 5);
        log.append(b"four").unwrap();
        let (_, records) = RecordLog::open(Some(&path), false).unwrap();
        assert_eq!(records.len(), 4);
        assert_eq!(log.records().unwrap().len(), 4);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
