//! TensorBoard event files: scalars (loss, PSNR, learning rate, …) written as TensorBoard's
//! `events.out.tfevents.*` records so `tensorboard --logdir` plots a run while it trains.
//!
//! The format is TFRecord (length, masked CRC-32C of the length, data, masked CRC-32C of the data) of
//! `Event` protocol buffers: the first holds `file_version: "brain.Event:2"`, each later one a step,
//! a wall time and one `Summary.Value { tag, simple_value }`. The few protobuf fields are encoded here
//! by hand.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::failure::{Failure, Result};

/// An open TensorBoard event file.
pub struct EventWriter {
    path: PathBuf,
    out: File,
}

impl EventWriter {
    /// Creates `folder` if needed and a new event file in it (a resumed run adds another file, which
    /// TensorBoard reads as the same run).
    pub fn create(folder: &Path) -> Result<EventWriter> {
        let fail = |e: std::io::Error| Failure::Message(format!("cannot write '{}': {e}", folder.display()));
        std::fs::create_dir_all(folder).map_err(fail)?;
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        let path = folder.join(format!(
            "events.out.tfevents.{}.nerfjit.{}.{}",
            now.as_secs(),
            std::process::id(),
            now.subsec_nanos()
        ));
        let out = File::create(&path).map_err(fail)?;
        let mut writer = EventWriter { path, out };
        let mut event = Vec::new();
        double_field(&mut event, 1, now.as_secs_f64());
        bytes_field(&mut event, 3, b"brain.Event:2");
        writer.write_record(&event)?;
        Ok(writer)
    }

    /// The event file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Writes scalar `value` under `tag` at `step`.
    pub fn scalar(&mut self, tag: &str, step: u64, value: f32) -> Result<()> {
        let wall_time = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default()
            .as_secs_f64();
        let mut summary_value = Vec::new();
        bytes_field(&mut summary_value, 1, tag.as_bytes());
        key(&mut summary_value, 2, 5);
        summary_value.extend_from_slice(&value.to_le_bytes());
        let mut summary = Vec::new();
        bytes_field(&mut summary, 1, &summary_value);
        let mut event = Vec::new();
        double_field(&mut event, 1, wall_time);
        key(&mut event, 2, 0);
        varint(&mut event, step);
        bytes_field(&mut event, 5, &summary);
        self.write_record(&event)
    }

    /// Appends one TFRecord holding `data`, flushed at once so TensorBoard sees it while training runs.
    fn write_record(&mut self, data: &[u8]) -> Result<()> {
        let length = (data.len() as u64).to_le_bytes();
        let mut record = Vec::with_capacity(data.len() + 16);
        record.extend_from_slice(&length);
        record.extend_from_slice(&masked_crc(&length).to_le_bytes());
        record.extend_from_slice(data);
        record.extend_from_slice(&masked_crc(data).to_le_bytes());
        self.out
            .write_all(&record)
            .and_then(|()| self.out.flush())
            .map_err(|e| Failure::Message(format!("cannot write '{}': {e}", self.path.display())))
    }
}

/// TFRecord's masked CRC-32C.
fn masked_crc(bytes: &[u8]) -> u32 {
    crc32c::crc32c(bytes).rotate_right(15).wrapping_add(0xa282_ead8)
}

/// A protobuf field key: field number and wire type.
fn key(out: &mut Vec<u8>, field: u64, wire_type: u64) {
    varint(out, (field << 3) | wire_type);
}

fn varint(out: &mut Vec<u8>, mut x: u64) {
    while x >= 0x80 {
        out.push((x as u8) | 0x80);
        x >>= 7;
    }
    out.push(x as u8);
}

fn double_field(out: &mut Vec<u8>, field: u64, x: f64) {
    key(out, field, 1);
    out.extend_from_slice(&x.to_le_bytes());
}

fn bytes_field(out: &mut Vec<u8>, field: u64, bytes: &[u8]) {
    key(out, field, 2);
    varint(out, bytes.len() as u64);
    out.extend_from_slice(bytes);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn masked_crc_matches_tensorflow() {
        // CRC-32C of "123456789" is 0xe3069283 (the standard check value).
        assert_eq!(crc32c::crc32c(b"123456789"), 0xe306_9283);
        assert_eq!(
            masked_crc(b"123456789"),
            0xe306_9283u32.rotate_right(15).wrapping_add(0xa282_ead8)
        );
    }

    #[test]
    fn varints_and_records_are_framed() {
        let mut v = Vec::new();
        varint(&mut v, 300);
        assert_eq!(v, [0xac, 0x02]);
        let dir = std::env::temp_dir().join(format!("nerfjit-tb-{}", std::process::id()));
        let mut w = EventWriter::create(&dir).unwrap();
        w.scalar("loss", 7, 0.25).unwrap();
        let bytes = std::fs::read(w.path()).unwrap();
        // Two records: each a length, its CRC, the data and the data's CRC.
        let mut at = 0;
        let mut records = Vec::new();
        while at < bytes.len() {
            let len = u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap()) as usize;
            assert_eq!(
                u32::from_le_bytes(bytes[at + 8..at + 12].try_into().unwrap()),
                masked_crc(&bytes[at..at + 8])
            );
            let data = &bytes[at + 12..at + 12 + len];
            assert_eq!(
                u32::from_le_bytes(bytes[at + 12 + len..at + 16 + len].try_into().unwrap()),
                masked_crc(data)
            );
            records.push(data.to_vec());
            at += 16 + len;
        }
        assert_eq!(records.len(), 2);
        assert!(records[0].ends_with(b"brain.Event:2"));
        let last = &records[1];
        assert!(last.windows(4).any(|w| w == b"loss") && last.ends_with(&0.25f32.to_le_bytes()));
    }
}
