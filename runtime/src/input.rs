//! Reading input files with a cap: a data file, checkpoint or camera file is read only up to
//! [`MAX_INPUT_BYTES`], so that a stream that never ends (`/dev/zero`, a FIFO) or an absurd file is
//! refused with a message instead of being read until memory runs out.

use std::fs::File;
use std::io::{self, Read};
use std::path::Path;

/// Most bytes an input file may hold (4 GiB).
pub const MAX_INPUT_BYTES: u64 = 4 << 30;

/// The bytes of the file at `path`, or an `InvalidData` error if it holds more than `MAX_INPUT_BYTES`.
pub fn read_capped(path: &Path) -> io::Result<Vec<u8>> {
    read_at_most(path, MAX_INPUT_BYTES)
}

/// The text of the file at `path` (UTF-8), capped as [`read_capped`].
pub fn read_text_capped(path: &Path) -> io::Result<String> {
    read_text_at_most(path, MAX_INPUT_BYTES)
}

/// The text of the file at `path` (UTF-8), or an `InvalidData` error if it holds more than `cap` bytes.
pub fn read_text_at_most(path: &Path, cap: u64) -> io::Result<String> {
    String::from_utf8(read_at_most(path, cap)?)
        .map_err(|_| io::Error::new(io::ErrorKind::InvalidData, "not UTF-8 text"))
}

/// All bytes of `reader` (e.g. an archive's entry), or an `InvalidData` error if it holds more than
/// `MAX_INPUT_BYTES`.
pub fn read_stream_capped(reader: impl Read) -> io::Result<Vec<u8>> {
    read_stream_at_most(reader, MAX_INPUT_BYTES, 0)
}

fn read_at_most(path: &Path, cap: u64) -> io::Result<Vec<u8>> {
    let file = File::open(path)?;
    let hint = file.metadata().map_or(0, |m| m.len());
    read_stream_at_most(file, cap, hint)
}

fn read_stream_at_most(reader: impl Read, cap: u64, size_hint: u64) -> io::Result<Vec<u8>> {
    let mut bytes = Vec::with_capacity(size_hint.min(cap) as usize);
    reader.take(cap + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > cap {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!("longer than the {cap} bytes an input file may hold"),
        ));
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn files_within_the_cap_are_read_and_longer_ones_or_endless_streams_refused() {
        let path = std::env::temp_dir().join(format!("nerfjit-input-{}.txt", std::process::id()));
        std::fs::write(&path, b"0123456789").unwrap();
        assert_eq!(read_at_most(&path, 10).unwrap(), b"0123456789");
        let e = read_at_most(&path, 9).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidData);
        assert!(e.to_string().contains("longer than the 9 bytes"), "{e}");
        std::fs::write(&path, [0xff, 0xfe]).unwrap();
        assert!(read_text_capped(&path)
            .unwrap_err()
            .to_string()
            .contains("not UTF-8"));
        std::fs::remove_file(&path).unwrap();
        let endless = read_at_most(Path::new("/dev/zero"), 1 << 20).unwrap_err();
        assert_eq!(endless.kind(), io::ErrorKind::InvalidData);
    }
}
