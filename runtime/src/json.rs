//! Reading typed values out of JSON files with errors that name the file and the key path.

use std::path::Path;

use glam::{Mat4, Vec2, Vec3};
use serde_json::Value;

use crate::error::{Error, Result};

/// A JSON value together with the file it came from and its key path (e.g. `cameras[2].eye`).
#[derive(Debug)]
pub(crate) struct Node<'a> {
    file: &'a Path,
    at: String,
    value: &'a Value,
}

/// Reads and parses a JSON file.
pub(crate) fn read(path: &Path) -> Result<Value> {
    let text = crate::input::read_text_capped(path).map_err(|e| {
        let reason = match e.kind() {
            std::io::ErrorKind::NotFound => "file not found".to_string(),
            _ => e.to_string(),
        };
        Error::read(path, reason)
    })?;
    serde_json::from_str(&text).map_err(|e| Error::format(path, format!("invalid JSON: {e}")))
}

impl<'a> Node<'a> {
    /// The document root of `file`.
    pub(crate) fn root(file: &'a Path, value: &'a Value) -> Self {
        Node {
            file,
            at: String::new(),
            value,
        }
    }

    fn error(&self, reason: impl std::fmt::Display) -> Error {
        if self.at.is_empty() {
            Error::format(self.file, reason)
        } else {
            Error::format(self.file, format!("{}: {reason}", self.at))
        }
    }

    fn kind(&self) -> &'static str {
        match self.value {
            Value::Null => "null",
            Value::Bool(_) => "a boolean",
            Value::Number(_) => "a number",
            Value::String(_) => "a string",
            Value::Array(_) => "an array",
            Value::Object(_) => "an object",
        }
    }

    /// The value under `key`, which must exist.
    pub(crate) fn get(&self, key: &str) -> Result<Node<'a>> {
        let Value::Object(map) = self.value else {
            return Err(self.error(format!("expected an object, found {}", self.kind())));
        };
        let at = if self.at.is_empty() {
            key.to_string()
        } else {
            format!("{}.{key}", self.at)
        };
        match map.get(key) {
            Some(value) => Ok(Node {
                file: self.file,
                at,
                value,
            }),
            None => Err(self.error(format!("missing key '{key}'"))),
        }
    }

    /// The value under `key`, if this object has it.
    pub(crate) fn opt(&self, key: &str) -> Result<Option<Node<'a>>> {
        let Value::Object(map) = self.value else {
            return Err(self.error(format!("expected an object, found {}", self.kind())));
        };
        map.contains_key(key).then(|| self.get(key)).transpose()
    }

    /// The elements of an array.
    pub(crate) fn items(&self) -> Result<Vec<Node<'a>>> {
        let Value::Array(items) = self.value else {
            return Err(self.error(format!("expected an array, found {}", self.kind())));
        };
        Ok(items
            .iter()
            .enumerate()
            .map(|(i, value)| Node {
                file: self.file,
                at: format!("{}[{i}]", self.at),
                value,
            })
            .collect())
    }

    /// A string.
    pub(crate) fn str(&self) -> Result<&'a str> {
        self.value
            .as_str()
            .ok_or_else(|| self.error(format!("expected a string, found {}", self.kind())))
    }

    /// A finite number.
    pub(crate) fn f32(&self) -> Result<f32> {
        match self.value.as_f64() {
            Some(x) if x.is_finite() => Ok(x as f32),
            _ => Err(self.error(format!("expected a number, found {}", self.kind()))),
        }
    }

    /// A non-negative integer that fits in `u32`.
    pub(crate) fn u32(&self) -> Result<u32> {
        self.value
            .as_u64()
            .and_then(|x| u32::try_from(x).ok())
            .ok_or_else(|| self.error(format!("expected a non-negative integer, found {}", self.value)))
    }

    /// An array of exactly `N` numbers.
    pub(crate) fn f32s<const N: usize>(&self) -> Result<[f32; N]> {
        let items = self.items()?;
        if items.len() != N {
            return Err(self.error(format!("expected {N} numbers, found {}", items.len())));
        }
        let mut out = [0.0; N];
        for (x, item) in out.iter_mut().zip(&items) {
            *x = item.f32()?;
        }
        Ok(out)
    }

    /// An array of 2 numbers.
    pub(crate) fn vec2(&self) -> Result<Vec2> {
        self.f32s::<2>().map(Vec2::from)
    }

    /// An array of 3 numbers.
    pub(crate) fn vec3(&self) -> Result<Vec3> {
        self.f32s::<3>().map(Vec3::from)
    }

    /// A 4×4 matrix given as 4 rows of 4 numbers.
    pub(crate) fn mat4_rows(&self) -> Result<Mat4> {
        let rows = self.items()?;
        if rows.len() != 4 {
            return Err(self.error(format!("expected 4 rows, found {}", rows.len())));
        }
        let mut m = [[0.0; 4]; 4];
        for (row, node) in m.iter_mut().zip(&rows) {
            *row = node.f32s::<4>()?;
        }
        Ok(Mat4::from_cols_array_2d(&m).transpose())
    }

    /// Turns an error about this node's value into one that names it.
    pub(crate) fn invalid(&self, err: Error) -> Error {
        self.error(err)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_name_file_and_key_path() {
        let v: Value = serde_json::from_str(r#"{"a": [{"b": "x"}, {"c": 1}]}"#).unwrap();
        let root = Node::root(Path::new("f.json"), &v);
        let items = root.get("a").unwrap().items().unwrap();
        let e = items[1].get("b").unwrap_err().to_string();
        assert_eq!(e, "f.json: a[1]: missing key 'b'");
        let e = items[0].get("b").unwrap().f32().unwrap_err().to_string();
        assert_eq!(e, "f.json: a[0].b: expected a number, found a string");
        assert_eq!(items[1].get("c").unwrap().u32().unwrap(), 1);
        let e = root.get("a").unwrap().vec3().unwrap_err().to_string();
        assert!(e.contains("expected 3 numbers, found 2"), "{e}");
    }

    #[test]
    fn matrices_are_read_row_by_row() {
        let v: Value = serde_json::from_str("[[1,0,0,5],[0,1,0,6],[0,0,1,7],[0,0,0,1]]").unwrap();
        let m = Node::root(Path::new("m.json"), &v).mat4_rows().unwrap();
        assert_eq!(m.w_axis.truncate(), Vec3::new(5.0, 6.0, 7.0));
    }
}
