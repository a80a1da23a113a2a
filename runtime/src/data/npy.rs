//! NumPy `.npy` files: reading and writing float32 RGB images of shape (H, W, 3), and reading
//! (N, 3) arrays of points, e.g. the entries of an `.npz` archive. One header parser serves both.

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
#[derive(Debug)]
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
        .ok_or("truncated .npy header")?;
    Ok((&bytes[start..end], &bytes[end..]))
}

/// The element type of a `.npy` array: little-endian float32 (`'<f4'`) or float64 (`'<f8'`).
#[derive(Debug, Clone, Copy)]
pub(crate) enum Dtype {
    /// `'<f4'`.
    F32,
    /// `'<f8'`.
    F64,
}

impl Dtype {
    /// Bytes per element.
    fn size(self) -> usize {
        match self {
            Dtype::F32 => 4,
            Dtype::F64 => 8,
        }
    }
}

/// A parsed `.npy` array that borrows its data from the file's bytes.
#[derive(Debug)]
pub(crate) struct NpyArray<'a> {
    /// The dimensions, e.g. `[height, width, 3]`.
    pub(crate) shape: Vec<usize>,
    /// The element type.
    pub(crate) dtype: Dtype,
    /// Whether the data is in Fortran (column-major) rather than C (row-major) order.
    pub(crate) fortran_order: bool,
    /// The bytes after the header: at least the array's size, more if the file has extra
    /// bytes at its end.
    pub(crate) data: &'a [u8],
}

impl NpyArray<'_> {
    /// The elements in stored order, float64 rounded to float32.
    pub(crate) fn to_f32(&self) -> Vec<f32> {
        let len: usize = self.shape.iter().product();
        let data = &self.data[..len * self.dtype.size()];
        match self.dtype {
            Dtype::F32 => data
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
            Dtype::F64 => data
                .chunks_exact(8)
                .map(|b| f64::from_le_bytes(std::array::from_fn(|k| b[k])) as f32)
                .collect(),
        }
    }

    /// The elements in stored order as float64 (float32 widened exactly).
    pub(crate) fn to_f64(&self) -> Vec<f64> {
        let len: usize = self.shape.iter().product();
        let data = &self.data[..len * self.dtype.size()];
        match self.dtype {
            Dtype::F32 => data
                .chunks_exact(4)
                .map(|b| f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])))
                .collect(),
            Dtype::F64 => data
                .chunks_exact(8)
                .map(|b| f64::from_le_bytes(std::array::from_fn(|k| b[k])))
                .collect(),
        }
    }
}

/// `shape` as a Python tuple, e.g. `(2, 3)` or `(5,)`.
fn shape_text(shape: &[usize]) -> String {
    let dims: Vec<String> = shape.iter().map(usize::to_string).collect();
    match dims.as_slice() {
        [one] => format!("({one},)"),
        _ => format!("({})", dims.join(", ")),
    }
}

/// Parses the bytes of a `.npy` file: its header (a float32 or float64 dtype, the order and
/// the shape) and its data, checked to be long enough for the shape. Errors say what is wrong.
pub(crate) fn parse(bytes: &[u8]) -> std::result::Result<NpyArray<'_>, String> {
    let (header, data) = split_header(bytes)?;
    let entries = Parser { text: header, pos: 0 }
        .dict()
        .map_err(|e| format!("bad header: {e}"))?;
    let get = |key: &str| {
        entries
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v)
            .ok_or(format!("the header has no '{key}'"))
    };
    let dtype = match get("descr")? {
        Literal::Str(d) if d == "<f4" => Dtype::F32,
        Literal::Str(d) if d == "<f8" => Dtype::F64,
        Literal::Str(d) => {
            return Err(format!(
                "dtype is '{d}', expected little-endian float32 '<f4' or float64 '<f8'"
            ))
        }
        _ => return Err("the header's 'descr' is not a string".into()),
    };
    let Literal::Bool(fortran_order) = *get("fortran_order")? else {
        return Err("the header's 'fortran_order' is neither True nor False".into());
    };
    let Literal::Tuple(dims) = get("shape")? else {
        return Err("the header's 'shape' is not a tuple".into());
    };
    let shape = dims
        .iter()
        .map(|d| match d {
            Literal::Int(d) => usize::try_from(*d).ok(),
            _ => None,
        })
        .collect::<Option<Vec<usize>>>()
        .ok_or("the header's 'shape' is not a tuple of sizes")?;
    let needed = shape
        .iter()
        .try_fold(dtype.size(), |n, &d| n.checked_mul(d))
        .ok_or(format!("shape {} is too large", shape_text(&shape)))?;
    if data.len() < needed {
        return Err(format!(
            "data truncated: shape {} needs {needed} bytes, found {}",
            shape_text(&shape),
            data.len()
        ));
    }
    Ok(NpyArray {
        shape,
        dtype,
        fortran_order,
        data,
    })
}

/// Reads a float32 little-endian `.npy` image of shape (H, W, 3), C order.
pub fn read_npy_rgb(path: &Path) -> Result<ImageF32> {
    let bytes = crate::input::read_capped(path).map_err(|e| Error::read(path, e))?;
    let array = parse(&bytes).map_err(|e| Error::format(path, e))?;
    let (height, width) = image_shape(&array).map_err(|e| Error::format(path, e))?;
    let pixels = array
        .to_f32()
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    Ok(ImageF32 {
        width,
        height,
        pixels,
    })
}

/// Checks that `array` is a float32 C-order image without extra data; returns (height, width).
fn image_shape(array: &NpyArray) -> std::result::Result<(u32, u32), String> {
    match array.dtype {
        Dtype::F32 => {}
        Dtype::F64 => return Err("dtype is '<f8', expected little-endian float32 '<f4'".into()),
    }
    if array.fortran_order {
        return Err("fortran_order must be False".into());
    }
    let shape = shape_text(&array.shape);
    let bad_shape = || format!("shape is {shape}, expected (height, width, 3) with height, width > 0");
    let [h, w, 3] = array.shape[..] else {
        return Err(bad_shape());
    };
    let (Ok(height @ 1..), Ok(width @ 1..)) = (u32::try_from(h), u32::try_from(w)) else {
        return Err(bad_shape());
    };
    let needed = array.shape.iter().product::<usize>() * 4;
    if array.data.len() > needed {
        return Err(format!(
            "data too long: shape {shape} needs {needed} bytes, found {}",
            array.data.len()
        ));
    }
    Ok((height, width))
}

/// The points of `.npy` bytes holding an array of shape (N, 3), float32 or float64, C or
/// Fortran order; errors say what is wrong (dtype, shape, truncated data, non-finite values).
pub(crate) fn parse_points(bytes: &[u8]) -> std::result::Result<Vec<[f32; 3]>, String> {
    let array = parse(bytes)?;
    let n = match array.shape[..] {
        [n, 3] => n,
        _ => return Err(format!("shape is {}, expected (N, 3)", shape_text(&array.shape))),
    };
    let values = array.to_f32();
    let at = |point: usize, axis: usize| {
        if array.fortran_order {
            values[axis * n + point]
        } else {
            values[point * 3 + axis]
        }
    };
    let points: Vec<[f32; 3]> = (0..n).map(|k| [at(k, 0), at(k, 1), at(k, 2)]).collect();
    if let Some(k) = points.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        return Err(format!("point {k} {:?} is not finite", points[k]));
    }
    Ok(points)
}

/// Writes `image` as a float32 little-endian `.npy` file (version 1.0) of shape (H, W, 3).
pub fn write_npy_rgb(path: &Path, image: &ImageF32) -> Result<()> {
    check_size(image.width, image.height)?;
    let values: Vec<f32> = image.pixels.iter().flatten().copied().collect();
    write_npy_f32(path, &[image.height as usize, image.width as usize, 3], &values)
}

/// Writes `values` as a float32 little-endian `.npy` file (version 1.0) of the given C-order
/// `shape`, which NumPy (`np.load`) and PyTorch read.
pub fn write_npy_f32(path: &Path, shape: &[usize], values: &[f32]) -> Result<()> {
    let count: usize = shape.iter().product();
    if count != values.len() {
        return Err(Error::Invalid(format!(
            "{} values do not fill an array of shape {shape:?}",
            values.len()
        )));
    }
    let mut header = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': {}, }}",
        shape_text(shape)
    );
    // Pad with spaces so that the data starts at a multiple of 64 bytes; end with a newline.
    let unpadded = MAGIC.len() + 4 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut bytes = Vec::with_capacity(10 + header.len() + values.len() * 4);
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&[1, 0]);
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for v in values {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    check_output_folder(path)?;
    crate::whole_file::write_whole(path, &bytes)
}

#[cfg(test)]
pub(crate) mod tests {
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
    fn float_arrays_of_any_shape_read_back() {
        for shape in [vec![5], vec![2, 3], vec![2, 3, 4]] {
            let n: usize = shape.iter().product();
            let values: Vec<f32> = (0..n).map(|k| k as f32 * 0.25 - 1.0).collect();
            let path = temp_path("any.npy");
            write_npy_f32(&path, &shape, &values).unwrap();
            let bytes = std::fs::read(&path).unwrap();
            let array = parse(&bytes).unwrap();
            assert_eq!((array.shape.clone(), array.to_f32()), (shape.clone(), values));
        }
        let e = write_npy_f32(&temp_path("bad.npy"), &[2, 2], &[1.0]).unwrap_err();
        assert_eq!(e.to_string(), "1 values do not fill an array of shape [2, 2]");
    }

    #[test]
    fn round_trip() {
        let path = temp_path("img.npy");
        write_npy_rgb(&path, &image()).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!((bytes.len() - 6 * 12) % 64, 0, "data is 64-byte aligned");
        assert_eq!(read_npy_rgb(&path).unwrap(), image());
    }

    /// A `.npy` file of format `version` (1 or 2) with header dictionary `dict` and `data`.
    fn npy_bytes_of_version(version: u8, dict: &str, data: &[u8]) -> Vec<u8> {
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&[version, 0]);
        if version == 1 {
            bytes.extend_from_slice(&(dict.len() as u16).to_le_bytes());
        } else {
            bytes.extend_from_slice(&(dict.len() as u32).to_le_bytes());
        }
        bytes.extend_from_slice(dict.as_bytes());
        bytes.extend_from_slice(data);
        bytes
    }

    /// A version 1.0 `.npy` file with header dictionary `dict` and `data`.
    pub(crate) fn npy_bytes(dict: &str, data: &[u8]) -> Vec<u8> {
        npy_bytes_of_version(1, dict, data)
    }

    /// The `.npy` bytes of `points` as float32 (N, 3) in C order.
    pub(crate) fn npy_f32(points: &[[f32; 3]]) -> Vec<u8> {
        let dict = format!(
            "{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, 3), }}\n",
            points.len()
        );
        let data: Vec<u8> = points.iter().flatten().flat_map(|c| c.to_le_bytes()).collect();
        npy_bytes(&dict, &data)
    }

    /// Writes a header with `dict` followed by `data_len` zero bytes.
    fn with_header(name: &str, version: u8, dict: &str, data_len: usize) -> PathBuf {
        let path = temp_path(name);
        std::fs::write(&path, npy_bytes_of_version(version, dict, &vec![0; data_len])).unwrap();
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

    #[test]
    fn float32_float64_and_fortran_order() {
        let points = [[1.0, 2.0, 3.0], [-4.0, 0.5, 6.0]];
        assert_eq!(parse_points(&npy_f32(&points)).unwrap(), points);
        // Fortran order, float64, double quotes: columns x, y, z one after the other.
        let columns = [1.0f64, -4.0, 2.0, 0.5, 3.0, 6.0];
        let data: Vec<u8> = columns.iter().flat_map(|c| c.to_le_bytes()).collect();
        let dict = "{\"descr\": \"<f8\", \"fortran_order\": True, \"shape\": (2, 3)}";
        assert_eq!(parse_points(&npy_bytes(dict, &data)).unwrap(), points);
    }

    #[test]
    fn bad_arrays_say_what_is_wrong() {
        let cases = [
            (
                "{'descr': '<i4', 'fortran_order': False, 'shape': (1, 3), }",
                12,
                "dtype is '<i4'",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (3,), }",
                12,
                "shape is (3,), expected (N, 3)",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 4), }",
                32,
                "expected (N, 3)",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }",
                20,
                "needs 24 bytes, found 20",
            ),
            ("{'descr': '<f4', 'shape': (2, 3), }", 24, "no 'fortran_order'"),
        ];
        for (dict, len, message) in cases {
            let e = parse_points(&npy_bytes(dict, &vec![0; len])).unwrap_err();
            assert!(e.contains(message), "{dict}: {e}");
        }
        let e = parse_points(&npy_f32(&[[0.0, f32::NAN, 0.0]])).unwrap_err();
        assert!(e.contains("point 0") && e.contains("not finite"), "{e}");
        assert!(parse_points(b"PK\x03\x04....").unwrap_err().contains("bad magic"));
    }
}
