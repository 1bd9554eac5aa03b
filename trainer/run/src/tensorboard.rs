//! TensorBoard scalars: an event file (`events.out.tfevents.<time>.<host>`) that TensorBoard
//! reads, written with no TensorFlow or protobuf dependency.
//!
//! The format is TFRecord: per record a little-endian u64 length, its masked CRC-32C, the
//! payload and the payload's masked CRC-32C. Each payload is a `tensorflow.Event` protobuf; we
//! encode the few fields we use by hand: `wall_time` (1, double), `step` (2, int64),
//! `file_version` (3, string, the first record) and `summary` (5) holding `Summary.Value`s
//! with `tag` (1, string) and `simple_value` (2, float).

use std::io::Write;
use std::path::{Path, PathBuf};

pub struct EventWriter {
    file: std::fs::File,
    path: PathBuf,
}

fn masked_crc(data: &[u8]) -> u32 {
    let c = crc32c::crc32c(data);
    (c.rotate_right(15)).wrapping_add(0xa282_ead8)
}

fn varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn key(out: &mut Vec<u8>, field: u32, wire: u8) {
    varint(out, ((field as u64) << 3) | wire as u64);
}

fn bytes_field(out: &mut Vec<u8>, field: u32, b: &[u8]) {
    key(out, field, 2);
    varint(out, b.len() as u64);
    out.extend_from_slice(b);
}

fn now() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0)
}

impl EventWriter {
    /// Start a new event file in `dir` (one per process run, as TensorBoard expects: a resumed
    /// run adds a file and TensorBoard joins them by step).
    pub fn create(dir: &Path) -> std::io::Result<EventWriter> {
        let host = std::fs::read_to_string("/etc/hostname").map(|h| h.trim().to_string()).unwrap_or_else(|_| "localhost".into());
        let path = dir.join(format!("events.out.tfevents.{}.{}.{}", now() as u64, host, std::process::id()));
        let file = crate::safe_fs::open_append(&path)?;
        let mut w = EventWriter { file, path };
        let mut ev = Vec::new();
        key(&mut ev, 1, 1);
        ev.extend_from_slice(&now().to_le_bytes());
        bytes_field(&mut ev, 3, b"brain.Event:2");
        w.record(&ev)?;
        Ok(w)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn record(&mut self, payload: &[u8]) -> std::io::Result<()> {
        let len = (payload.len() as u64).to_le_bytes();
        let mut buf = Vec::with_capacity(payload.len() + 16);
        buf.extend_from_slice(&len);
        buf.extend_from_slice(&masked_crc(&len).to_le_bytes());
        buf.extend_from_slice(payload);
        buf.extend_from_slice(&masked_crc(payload).to_le_bytes());
        self.file.write_all(&buf)
    }

    /// Write scalars (tag, value) at `step`; non-finite values are skipped.
    /// A `SessionLog` START at `step`: TensorBoard discards the events of this run from `step`
    /// on that earlier files hold (how a resumed run hides what was logged after its checkpoint).
    pub fn session_start(&mut self, step: u64) -> std::io::Result<()> {
        let mut log = Vec::new();
        key(&mut log, 1, 0);
        varint(&mut log, 1); // SessionLog.SessionStatus.START
        let mut ev = Vec::new();
        key(&mut ev, 1, 1);
        ev.extend_from_slice(&now().to_le_bytes());
        key(&mut ev, 2, 0);
        varint(&mut ev, step);
        bytes_field(&mut ev, 6, &log);
        self.record(&ev)?;
        self.file.flush()
    }

    pub fn scalars(&mut self, step: u64, values: &[(&str, f64)]) -> std::io::Result<()> {
        let mut summary = Vec::new();
        for (tag, v) in values.iter().filter(|(_, v)| v.is_finite()) {
            let mut val = Vec::new();
            bytes_field(&mut val, 1, tag.as_bytes());
            key(&mut val, 2, 5);
            val.extend_from_slice(&(*v as f32).to_le_bytes());
            bytes_field(&mut summary, 1, &val);
        }
        if summary.is_empty() {
            return Ok(());
        }
        let mut ev = Vec::new();
        key(&mut ev, 1, 1);
        ev.extend_from_slice(&now().to_le_bytes());
        key(&mut ev, 2, 0);
        varint(&mut ev, step);
        bytes_field(&mut ev, 5, &summary);
        self.record(&ev)?;
        self.file.flush()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Read the records back, checking both CRCs of each.
    fn read_records(path: &Path) -> Vec<Vec<u8>> {
        let data = std::fs::read(path).unwrap();
        let (mut i, mut out) = (0, Vec::new());
        while i < data.len() {
            let len_b = &data[i..i + 8];
            let n = u64::from_le_bytes(len_b.try_into().unwrap()) as usize;
            assert_eq!(u32::from_le_bytes(data[i + 8..i + 12].try_into().unwrap()), masked_crc(len_b));
            let payload = &data[i + 12..i + 12 + n];
            assert_eq!(u32::from_le_bytes(data[i + 12 + n..i + 16 + n].try_into().unwrap()), masked_crc(payload));
            out.push(payload.to_vec());
            i += 16 + n;
        }
        out
    }

    #[test]
    fn records_have_valid_crcs_and_carry_the_scalars() {
        // The CRC-32C check value of "123456789" is 0xE3069283 (RFC 3720).
        assert_eq!(crc32c::crc32c(b"123456789"), 0xE306_9283);
        let dir = std::env::temp_dir().join(format!("lmac-tb-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut w = EventWriter::create(&dir).unwrap();
        w.scalars(1234, &[("test_return_mean", 0.5), ("loss", f64::NAN)]).unwrap();
        let recs = read_records(w.path());
        assert_eq!(recs.len(), 2);
        assert!(recs[0].windows(13).any(|s| s == b"brain.Event:2"));
        let r = &recs[1];
        assert!(r.windows(16).any(|s| s == b"test_return_mean"));
        assert!(!r.windows(4).any(|s| s == b"loss"), "NaN values are skipped");
        // step 1234 as a varint after key (2 << 3 | 0) = 0x10
        assert!(r.windows(3).any(|s| s == [0x10, 0xd2, 0x09]));
        assert!(r.windows(4).any(|s| s == 0.5f32.to_le_bytes()));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
