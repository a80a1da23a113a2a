//! Reading and writing float32 RGB images as NumPy `.npy` files of shape (H, W, 3).

use std::path::Path;

use crate::error::{check_output_folder, check_size, Error, Result};

/// A float RGB image in row-major pixel order.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageF32 {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width·height` pixels, row by row.
    pub pixels: Vec<[f32; 3]>,
}

const MAGIC: &[u8] = b"\x93NUMPY";

/// A Python literal of a `.npy` header dictionary.
#[derive(Debug, PartialEq)]
enum Literal {
    Str(String),
    Bool(bool),
    Int(u64),
    Tuple(Vec<Literal>),
}

/// A parser of the Python dictionary literal in a `.npy` header.
struct Parser<'a> {
    text: &'a [u8],
    pos: usize,
}

impl Parser<'_> {
    fn skip_space(&mut self) {
        while self.text.get(self.pos).is_some_and(|c| c.is_ascii_whitespace()) {
            self.pos += 1;
        }
    }

    /// Consumes `c` (after spaces) if it comes next.
    fn eat(&mut self, c: u8) -> bool {
        self.skip_space();
        let found = self.text.get(self.pos) == Some(&c);
        if found {
            self.pos += 1;
        }
        found
    }

    fn expect(&mut self, c: u8) -> std::result::Result<(), String> {
        if self.eat(c) {
            Ok(())
        } else {
            Err(format!("expected '{}' at byte {}", c as char, self.pos))
        }
    }

    fn dict(&mut self) -> std::result::Result<Vec<(String, Literal)>, String> {
        self.expect(b'{')?;
        let mut entries = Vec::new();
        while !self.eat(b'}') {
            let Literal::Str(key) = self.literal()? else {
                return Err("dictionary keys must be strings".into());
            };
            self.expect(b':')?;
            entries.push((key, self.literal()?));
            if !self.eat(b',') {
                self.expect(b'}')?;
                break;
            }
        }
        Ok(entries)
    }

    fn literal(&mut self) -> std::result::Result<Literal, String> {
        self.skip_space();
        let rest = &self.text[self.pos.min(self.text.len())..];
        match rest.first() {
            Some(&quote @ (b'\'' | b'"')) => {
                let end = rest[1..]
                    .iter()
                    .position(|&c| c == quote)
                    .ok_or("unterminated string")?;
                self.pos += end + 2;
                Ok(Literal::Str(String::from_utf8_lossy(&rest[1..=end]).into_owned()))
            }
            Some(b'(') => {
                self.pos += 1;
                let mut items = Vec::new();
                while !self.eat(b')') {
                    items.push(self.literal()?);
                    if !self.eat(b',') {
                        self.expect(b')')?;
                        break;
                    }
                }
                Ok(Literal::Tuple(items))
            }
            Some(c) if c.is_ascii_digit() => {
                let len = rest.iter().take_while(|c| c.is_ascii_digit()).count();
                self.pos += len;
                let digits = std::str::from_utf8(&rest[..len]).unwrap_or_default();
                digits
                    .parse()
                    .map(Literal::Int)
                    .map_err(|_| format!("integer {digits} is too large"))
            }
            _ if rest.starts_with(b"True") => {
                self.pos += 4;
                Ok(Literal::Bool(true))
            }
            _ if rest.starts_with(b"False") => {
                self.pos += 5;
                Ok(Literal::Bool(false))
            }
            _ => Err(format!("unexpected text at byte {}", self.pos)),
        }
    }
}

/// Splits a `.npy` file into its header text and its data.
fn split_header(bytes: &[u8]) -> std::result::Result<(&[u8], &[u8]), String> {
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err("not a .npy file (bad magic bytes)".into());
    }
    let (len, start): (usize, usize) = match bytes[6] {
        1 => (usize::from(u16::from_le_bytes([bytes[8], bytes[9]])), 10),
        2 | 3 if bytes.len() >= 12 => {
            let len = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
            (len as usize, 12)
        }
        v => return Err(format!("unsupported .npy version {v}.{}", bytes[7])),
    };
    let end = start
        .checked_add(len)
        .filter(|&end| end <= bytes.len())
        .ok_or("truncated header")?;
    Ok((&bytes[start..end], &bytes[end..]))
}

/// Checks the header dictionary; returns (height, width).
fn image_shape(header: &[u8]) -> std::result::Result<(u32, u32), String> {
    let entries = Parser { text: header, pos: 0 }
        .dict()
        .map_err(|e| format!("bad header: {e}"))?;
    let get = |key: &str| {
        entries
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v)
            .ok_or(format!("header has no '{key}'"))
    };
    match get("descr")? {
        Literal::Str(d) if d == "<f4" => {}
        other => {
            return Err(format!(
                "dtype is {other:?}, expected little-endian float32 '<f4'"
            ))
        }
    }
    if get("fortran_order")? != &Literal::Bool(false) {
        return Err("fortran_order must be False".into());
    }
    let shape = get("shape")?;
    if let Literal::Tuple(dims) = shape {
        if let [Literal::Int(h), Literal::Int(w), Literal::Int(3)] = dims.as_slice() {
            if let (Ok(h), Ok(w)) = (u32::try_from(*h), u32::try_from(*w)) {
                if h > 0 && w > 0 {
                    return Ok((h, w));
                }
            }
        }
    }
    Err(format!(
        "shape is {shape:?}, expected (height, width, 3) with height, width > 0"
    ))
}

/// Reads a float32 little-endian `.npy` image of shape (H, W, 3), C order.
pub fn read_npy_rgb(path: &Path) -> Result<ImageF32> {
    let bytes = std::fs::read(path).map_err(|e| Error::read(path, e))?;
    let (header, data) = split_header(&bytes).map_err(|e| Error::format(path, e))?;
    let (height, width) = image_shape(header).map_err(|e| Error::format(path, e))?;
    let n = width as usize * height as usize;
    let expected = n as u64 * 12;
    if data.len() as u64 != expected {
        let what = if (data.len() as u64) < expected {
            "truncated"
        } else {
            "too long"
        };
        return Err(Error::format(
            path,
            format!(
                "data {what}: shape ({height}, {width}, 3) needs {expected} bytes, found {}",
                data.len()
            ),
        ));
    }
    let pixels = data
        .chunks_exact(12)
        .map(|px| {
            let c = |k: usize| f32::from_le_bytes([px[k], px[k + 1], px[k + 2], px[k + 3]]);
            [c(0), c(4), c(8)]
        })
        .collect();
    Ok(ImageF32 {
        width,
        height,
        pixels,
    })
}

/// Writes `image` as a float32 little-endian `.npy` file (version 1.0) of shape (H, W, 3).
pub fn write_npy_rgb(path: &Path, image: &ImageF32) -> Result<()> {
    check_size(image.width, image.height)?;
    if image.pixels.len() != image.width as usize * image.height as usize {
        return Err(Error::Invalid(format!(
            "{} pixels do not fill a {}×{} image",
            image.pixels.len(),
            image.width,
            image.height
        )));
    }
    let mut header = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, {}, 3), }}",
        image.height, image.width
    );
    // Pad with spaces so that the data starts at a multiple of 64 bytes; end with a newline.
    let unpadded = MAGIC.len() + 4 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut bytes = Vec::with_capacity(10 + header.len() + image.pixels.len() * 12);
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&[1, 0]);
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for px in &image.pixels {
        for c in px {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
    }
    check_output_folder(path)?;
    std::fs::write(path, bytes).map_err(|e| Error::write(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    fn temp_path(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nerfjit-npy-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    fn image() -> ImageF32 {
        ImageF32 {
            width: 3,
            height: 2,
            pixels: (0..6)
                .map(|k| [k as f32, 0.5 * k as f32, -1.0 / (k + 1) as f32])
                .collect(),
        }
    }

    #[test]
    fn round_trip() {
        let path = temp_path("img.npy");
        write_npy_rgb(&path, &image()).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!((bytes.len() - 6 * 12) % 64, 0, "data is 64-byte aligned");
        assert_eq!(read_npy_rgb(&path).unwrap(), image());
    }

    /// Writes a header with `dict` followed by `data_len` zero bytes.
    fn with_header(name: &str, version: u8, dict: &str, data_len: usize) -> PathBuf {
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&[version, 0]);
        if version == 1 {
            bytes.extend_from_slice(&(dict.len() as u16).to_le_bytes());
        } else {
            bytes.extend_from_slice(&(dict.len() as u32).to_le_bytes());
        }
        bytes.extend_from_slice(dict.as_bytes());
        bytes.resize(bytes.len() + data_len, 0);
        let path = temp_path(name);
        std::fs::write(&path, bytes).unwrap();
        path
    }

    #[test]
    fn version_2_headers_and_double_quotes_are_read() {
        let dict = "{\"descr\": \"<f4\", \"shape\": (1, 2, 3), \"fortran_order\": False}\n";
        let path = with_header("v2.npy", 2, dict, 24);
        let img = read_npy_rgb(&path).unwrap();
        assert_eq!((img.width, img.height), (2, 1));
    }

    #[test]
    fn bad_files_give_errors_naming_the_file() {
        let cases = [
            (
                "f8.npy",
                "{'descr': '<f8', 'fortran_order': False, 'shape': (1, 1, 3), }",
                24,
                "expected little-endian float32",
            ),
            (
                "fortran.npy",
                "{'descr': '<f4', 'fortran_order': True, 'shape': (1, 1, 3), }",
                12,
                "fortran_order",
            ),
            (
                "shape.npy",
                "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2), }",
                16,
                "expected (height, width, 3)",
            ),
            (
                "rgba.npy",
                "{'descr': '<f4', 'fortran_order': False, 'shape': (1, 1, 4), }",
                16,
                "expected (height, width, 3)",
            ),
            (
                "short.npy",
                "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2, 3), }",
                40,
                "data truncated: shape (2, 2, 3) needs 48 bytes, found 40",
            ),
            (
                "syntax.npy",
                "{'descr': '<f4' 'shape': (2, 2, 3)}",
                48,
                "bad header",
            ),
        ];
        for (name, dict, len, message) in cases {
            let path = with_header(name, 1, dict, len);
            let e = read_npy_rgb(&path).unwrap_err().to_string();
            assert!(e.starts_with(&path.display().to_string()), "{e}");
            assert!(e.contains(message), "{name}: {e}");
        }
        let path = temp_path("magic.npy");
        std::fs::write(&path, b"PK\x03\x04 not numpy").unwrap();
        assert!(read_npy_rgb(&path).unwrap_err().to_string().contains("bad magic"));
        let e = read_npy_rgb(Path::new("/nonexistent.npy")).unwrap_err();
        assert!(e.to_string().starts_with("cannot read /nonexistent.npy"));
        let e = write_npy_rgb(Path::new("no-such-folder/a.npy"), &image()).unwrap_err();
        assert!(e.to_string().contains("folder 'no-such-folder' does not exist"));
    }

    #[test]
    fn course_image_reads_when_present() {
        let path = Path::new("/work/shared/data/assignment3/box_0.npy");
        if !path.exists() {
            eprintln!("note: {} not found, skipping", path.display());
            return;
        }
        let img = read_npy_rgb(path).unwrap();
        assert_eq!((img.width, img.height), (256, 256));
        assert!(img.pixels.iter().flatten().all(|c| (0.0..=1.0).contains(c)));
        let mean: f32 = img.pixels.iter().flatten().sum::<f32>() / (256.0 * 256.0 * 3.0);
        assert!(mean > 0.0, "image is not all black");
    }
}
