//! Reading PLY files (ASCII or binary little-endian) into columns of numbers, shared by the
//! mesh reader ([`crate::surfaces::mesh::Mesh::read_ply`]) and the point-cloud reader.
//!
//! Every element's properties become columns: a number per row for scalar properties, a list
//! per row for list properties (e.g. a face's `vertex_indices`). Values are kept as `f64`,
//! which holds every PLY scalar type exactly.

use std::path::Path;

use crate::error::{Error, Result};

/// A scalar type of a PLY property.
#[derive(Debug, Clone, Copy)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Scalar> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    /// The little-endian value in `b`, which has exactly `self.size()` bytes.
    fn read_le(self, b: &[u8]) -> f64 {
        let mut buf = [0u8; 8];
        buf[..b.len()].copy_from_slice(b);
        let [b0, b1, b2, b3, ..] = buf;
        match self {
            Scalar::I8 => f64::from(b0 as i8),
            Scalar::U8 => f64::from(b0),
            Scalar::I16 => f64::from(i16::from_le_bytes([b0, b1])),
            Scalar::U16 => f64::from(u16::from_le_bytes([b0, b1])),
            Scalar::I32 => f64::from(i32::from_le_bytes([b0, b1, b2, b3])),
            Scalar::U32 => f64::from(u32::from_le_bytes([b0, b1, b2, b3])),
            Scalar::F32 => f64::from(f32::from_le_bytes([b0, b1, b2, b3])),
            Scalar::F64 => f64::from_le_bytes(buf),
        }
    }
}

/// The type of a property: one scalar, or a list with its length stored first.
#[derive(Debug, Clone, Copy)]
enum Kind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

/// The values of one property of an element: a number per row, or a list per row.
#[derive(Debug)]
pub(crate) struct Column {
    /// For list properties, `rows + 1` offsets into `values`: row `r` is
    /// `values[starts[r]..starts[r + 1]]`. `None` for scalar properties.
    starts: Option<Vec<usize>>,
    /// The numbers of all rows, one after the other.
    values: Vec<f64>,
}

impl Column {
    /// An empty column of `kind` with room for `rows` rows.
    fn new(kind: Kind, rows: usize) -> Column {
        match kind {
            Kind::Scalar(_) => Column {
                starts: None,
                values: Vec::with_capacity(rows),
            },
            Kind::List { .. } => {
                let mut starts = Vec::with_capacity(rows + 1);
                starts.push(0);
                Column {
                    starts: Some(starts),
                    values: Vec::with_capacity(3 * rows),
                }
            }
        }
    }

    /// Ends the list of the current row (nothing for scalar properties).
    fn end_row(&mut self) {
        if let Some(starts) = &mut self.starts {
            starts.push(self.values.len());
        }
    }
}

/// One element of a PLY file (e.g. `vertex` or `face`) with all its rows.
#[derive(Debug)]
pub(crate) struct Element {
    /// Its name in the header.
    pub name: String,
    /// Its number of rows.
    pub count: usize,
    /// Its properties in header order: (name, values).
    pub columns: Vec<(String, Column)>,
}

impl Element {
    /// The values of scalar property `name`, if the element has one.
    pub(crate) fn scalar(&self, name: &str) -> Option<&[f64]> {
        self.columns
            .iter()
            .find(|(n, c)| n == name && c.starts.is_none())
            .map(|(_, c)| c.values.as_slice())
    }

    /// The (row offsets, items) of list property `name`, if the element has one.
    pub(crate) fn list(&self, name: &str) -> Option<(&[usize], &[f64])> {
        self.columns
            .iter()
            .find(|(n, _)| n == name)
            .and_then(|(_, c)| Some((c.starts.as_deref()?, c.values.as_slice())))
    }
}

/// The elements of a PLY file, in file order.
#[derive(Debug)]
pub(crate) struct Ply {
    /// The elements.
    pub elements: Vec<Element>,
}

impl Ply {
    /// The element called `name`, if any.
    pub(crate) fn element(&self, name: &str) -> Option<&Element> {
        self.elements.iter().find(|e| e.name == name)
    }
}

/// An element as declared in the header.
struct ElementDef {
    name: String,
    count: usize,
    properties: Vec<(String, Kind)>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Format {
    Ascii,
    BinaryLe,
}

/// The parsed header: format, elements, and the byte offset where data starts, plus the number
/// of header lines (for line numbers of ASCII data).
struct Header {
    format: Format,
    elements: Vec<ElementDef>,
    data_start: usize,
    lines: usize,
}

fn parse_header(bytes: &[u8]) -> std::result::Result<Header, String> {
    if !(bytes.starts_with(b"ply\n") || bytes.starts_with(b"ply\r\n")) {
        return Err("not a PLY file (it does not start with 'ply')".into());
    }
    let mut format = None;
    let mut elements: Vec<ElementDef> = Vec::new();
    let mut pos = 0;
    let mut line_no = 0;
    loop {
        let Some(len) = bytes[pos..].iter().position(|&c| c == b'\n') else {
            return Err("the header has no 'end_header' line".into());
        };
        let line = String::from_utf8_lossy(&bytes[pos..pos + len]);
        pos += len + 1;
        line_no += 1;
        let words: Vec<&str> = line.split_whitespace().collect();
        let bad = || format!("header line {line_no} '{}' is malformed", line.trim());
        match words.as_slice() {
            ["ply"] if line_no == 1 => {}
            ["end_header"] => break,
            ["comment", ..] | ["obj_info", ..] | [] => {}
            ["format", "ascii", _] => format = Some(Format::Ascii),
            ["format", "binary_little_endian", _] => format = Some(Format::BinaryLe),
            ["format", other, _] => {
                return Err(format!(
                    "format '{other}' is not supported (only ascii and binary_little_endian)"
                ))
            }
            ["element", name, count] => elements.push(ElementDef {
                name: name.to_string(),
                count: count.parse().map_err(|_| bad())?,
                properties: Vec::new(),
            }),
            ["property", rest @ ..] => {
                let element = elements
                    .last_mut()
                    .ok_or(format!("header line {line_no}: property before any element"))?;
                let scalar = |name: &str| {
                    Scalar::parse(name)
                        .ok_or(format!("header line {line_no}: unknown property type '{name}'"))
                };
                let (name, kind) = match rest {
                    ["list", count, item, name] => (
                        name,
                        Kind::List {
                            count: scalar(count)?,
                            item: scalar(item)?,
                        },
                    ),
                    [ty, name] => (name, Kind::Scalar(scalar(ty)?)),
                    _ => return Err(bad()),
                };
                element.properties.push((name.to_string(), kind));
            }
            _ => return Err(bad()),
        }
    }
    let format = format.ok_or("the header has no 'format' line")?;
    if let Some(empty) = elements.iter().find(|e| e.properties.is_empty() && e.count > 0) {
        // Rows of no properties take no bytes, so no file size bounds their count (2^64 would loop forever).
        return Err(format!(
            "element '{}' declares {} rows but no properties: rows without values are not read",
            empty.name, empty.count
        ));
    }
    Ok(Header {
        format,
        elements,
        data_start: pos,
        lines: line_no,
    })
}

/// Columns for `def`, with room for at most `room` rows reserved up front (headers may lie).
fn empty_columns(def: &ElementDef, room: usize) -> Vec<(String, Column)> {
    let rows = def.count.min(room);
    def.properties
        .iter()
        .map(|(name, kind)| (name.clone(), Column::new(*kind, rows)))
        .collect()
}

/// A list length read from the file: a non-negative integer.
fn list_len(value: f64, what: impl Fn() -> String) -> std::result::Result<usize, String> {
    if value >= 0.0 && value.fract() == 0.0 && value <= u32::MAX as f64 {
        Ok(value as usize)
    } else {
        Err(format!(
            "{}: list length {value} is not a non-negative integer",
            what()
        ))
    }
}

fn read_binary(header: &Header, data: &[u8]) -> std::result::Result<Vec<Element>, String> {
    let mut pos = 0;
    let mut take = |n: usize, what: &dyn Fn() -> String| {
        let end = pos + n;
        if end > data.len() {
            return Err(format!("the data ends early, in {}", what()));
        }
        let bytes = &data[pos..end];
        pos = end;
        Ok(bytes)
    };
    let mut elements = Vec::new();
    for def in &header.elements {
        let mut columns = empty_columns(def, data.len());
        for row in 0..def.count {
            let what = || format!("{} {row}", def.name);
            for ((_, kind), (_, column)) in def.properties.iter().zip(&mut columns) {
                match *kind {
                    Kind::Scalar(s) => column.values.push(s.read_le(take(s.size(), &what)?)),
                    Kind::List { count, item } => {
                        let len = list_len(count.read_le(take(count.size(), &what)?), what)?;
                        let bytes = take(len * item.size(), &what)?;
                        let items = bytes.chunks_exact(item.size()).map(|b| item.read_le(b));
                        column.values.extend(items);
                    }
                }
                column.end_row();
            }
        }
        elements.push(Element {
            name: def.name.clone(),
            count: def.count,
            columns,
        });
    }
    Ok(elements)
}

fn read_ascii(header: &Header, data: &[u8]) -> std::result::Result<Vec<Element>, String> {
    let text = std::str::from_utf8(data).map_err(|_| "the ASCII data is not valid text".to_string())?;
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(k, line)| (header.lines + 1 + k, line))
        .filter(|(_, line)| !line.trim().is_empty());
    let mut elements = Vec::new();
    for def in &header.elements {
        let mut columns = empty_columns(def, data.len());
        for row in 0..def.count {
            let Some((line_no, line)) = lines.next() else {
                return Err(format!("the data ends early, before {} {row}", def.name));
            };
            let mut words = line.split_whitespace();
            let mut number = || {
                let word = words
                    .next()
                    .ok_or(format!("line {line_no}: {} {row} has too few values", def.name))?;
                word.parse::<f64>()
                    .map_err(|_| format!("line {line_no}: '{word}' is not a number"))
            };
            for ((_, kind), (_, column)) in def.properties.iter().zip(&mut columns) {
                match kind {
                    Kind::Scalar(_) => column.values.push(number()?),
                    Kind::List { .. } => {
                        let len = list_len(number()?, || format!("line {line_no}"))?;
                        for _ in 0..len {
                            column.values.push(number()?);
                        }
                    }
                }
                column.end_row();
            }
            if words.next().is_some() {
                return Err(format!(
                    "line {line_no}: {} {row} has more values than its {} properties",
                    def.name,
                    def.properties.len()
                ));
            }
        }
        elements.push(Element {
            name: def.name.clone(),
            count: def.count,
            columns,
        });
    }
    Ok(elements)
}

/// Reads the PLY file at `path`; errors name the file and what is wrong (e.g. the line of a
/// bad ASCII value or the element row where binary data ends).
pub(crate) fn read_ply(path: &Path) -> Result<Ply> {
    let bytes = crate::input::read_capped(path).map_err(|e| Error::read(path, e))?;
    let header = parse_header(&bytes).map_err(|e| Error::format(path, e))?;
    let data = &bytes[header.data_start..];
    let elements = match header.format {
        Format::Ascii => read_ascii(&header, data),
        Format::BinaryLe => read_binary(&header, data),
    }
    .map_err(|e| Error::format(path, e))?;
    Ok(Ply { elements })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    fn temp_file(name: &str, bytes: &[u8]) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nerfjit-ply-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        path
    }

    #[test]
    fn ascii_and_binary_files_give_the_same_columns() {
        let ascii = "ply\r\nformat ascii 1.0\ncomment hi\nelement vertex 2\nproperty float x\n\
                     property uchar red\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
                     0.5 7\n-2 255\n\n3 0 1 1\n";
        let mut binary = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n\
                           property uchar red\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
            .to_vec();
        for (x, red) in [(0.5f32, 7u8), (-2.0, 255)] {
            binary.extend_from_slice(&x.to_le_bytes());
            binary.push(red);
        }
        binary.push(3);
        for i in [0i32, 1, 1] {
            binary.extend_from_slice(&i.to_le_bytes());
        }
        for (name, bytes) in [("a.ply", ascii.as_bytes()), ("b.ply", &binary)] {
            let ply = read_ply(&temp_file(name, bytes)).unwrap();
            let vertex = ply.element("vertex").unwrap();
            assert_eq!(vertex.count, 2);
            assert_eq!(vertex.scalar("x").unwrap(), [0.5, -2.0]);
            assert_eq!(vertex.scalar("red").unwrap(), [7.0, 255.0]);
            assert!(vertex.scalar("y").is_none());
            let (starts, items) = ply.element("face").unwrap().list("vertex_indices").unwrap();
            assert_eq!((starts, items), ([0, 3].as_slice(), [0.0, 1.0, 1.0].as_slice()));
        }
    }

    #[test]
    fn bad_files_name_the_problem() {
        let head =
            "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nend_header\n";
        let cases: [(&str, String, &str); 7] = [
            ("magic.ply", "PLY\n".into(), "does not start with 'ply'"),
            ("noend.ply", "ply\nformat ascii 1.0\n".into(), "no 'end_header'"),
            (
                "big.ply",
                "ply\nformat binary_big_endian 1.0\nend_header\n".into(),
                "binary_big_endian' is not supported",
            ),
            (
                "type.ply",
                "ply\nformat ascii 1.0\nelement v 1\nproperty quad x\nend_header\n".into(),
                "unknown property type 'quad'",
            ),
            (
                "short.ply",
                format!("{head}1 2\n3\n"),
                "line 8: vertex 1 has too few values",
            ),
            (
                "word.ply",
                format!("{head}1 2\n3 abc\n"),
                "line 8: 'abc' is not a number",
            ),
            (
                "long.ply",
                format!("{head}1 2 3\n"),
                "line 7: vertex 0 has more values",
            ),
        ];
        for (name, text, message) in cases {
            let path = temp_file(name, text.as_bytes());
            let e = read_ply(&path).unwrap_err().to_string();
            assert!(e.starts_with(&path.display().to_string()), "{e}");
            assert!(e.contains(message), "{name}: {e}");
        }
        let path = temp_file(
            "trunc.ply",
            b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nend_header\n\0\0\0\0\0",
        );
        let e = read_ply(&path).unwrap_err().to_string();
        assert!(e.contains("the data ends early, in vertex 1"), "{e}");
    }

    #[test]
    fn rows_without_properties_are_refused_whatever_their_count() {
        for count in ["1", "18446744073709551615"] {
            let text = format!("ply\nformat binary_little_endian 1.0\nelement nothing {count}\nend_header\n");
            let e = read_ply(&temp_file("empty.ply", text.as_bytes()))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains(&format!(
                    "element 'nothing' declares {count} rows but no properties"
                )),
                "{e}"
            );
        }
        let none =
            "ply\nformat ascii 1.0\nelement nothing 0\nelement vertex 1\nproperty float x\nend_header\n2\n";
        let ply = read_ply(&temp_file("zero.ply", none.as_bytes())).unwrap();
        assert_eq!(ply.element("vertex").unwrap().scalar("x").unwrap(), [2.0]);
    }
}
