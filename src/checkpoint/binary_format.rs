//! The binary checkpoint format: a [safetensors](https://github.com/huggingface/safetensors) file, which
//! PyTorch, NumPy and JAX users open with `safetensors.*.load_file`. Each param is a tensor named after it,
//! in its shape (`f32` as a scalar, `vec<n>` as `[n]`, `mat<r, c>` as `[r, c]` row-major, an `mlp`'s layer
//! `l` as `NAME.l.weight` `[out, in]` and `NAME.l.bias` `[out]` like PyTorch's `nn.Linear`, a grid's table
//! flat); Adam's moments are `adam.m.NAME…` and `adam.v.NAME…`. The metadata holds the format, the step,
//! Adam's step count and the script (name, source and `--set` overrides).

use std::borrow::Cow;
use std::collections::HashMap;
use std::io::Read;
use std::ops::Range;
use std::path::Path;

use nerfjit_dsl::{Program, Type};
use nerfjit_runtime::Adam;
use safetensors::tensor::{Dtype, SafeTensors, View};

use super::{Saved, Script};
use crate::failure::{Failure, Result};

/// The format's name in the metadata.
const FORMAT: &str = "nerfjit-checkpoint-2";

/// The largest header read (the script's source is in it): safetensors' own limit.
const MAX_HEADER_BYTES: u64 = 100_000_000;

/// One tensor of a program's params: its name, shape and values in the flat param vector.
struct Entry {
    name: String,
    shape: Vec<usize>,
    range: Range<usize>,
}

/// The tensors of `program`'s params, in declaration order.
fn entries(program: &Program) -> Vec<Entry> {
    let mut entries = Vec::new();
    for p in &program.params {
        let at = p.offset;
        let whole = |shape: Vec<usize>| Entry {
            name: p.name.clone(),
            shape,
            range: at..at + p.ty.scalars(),
        };
        match &p.ty {
            Type::F32 => entries.push(whole(Vec::new())),
            Type::Mat(r, c) => entries.push(whole(vec![*r, *c])),
            Type::Mlp(shape) => {
                let mut offset = at;
                for (l, (rows, cols)) in shape.layers().into_iter().enumerate() {
                    let (weights, biases) = (offset..offset + rows * cols, offset + rows * cols);
                    entries.push(Entry {
                        name: format!("{}.{l}.weight", p.name),
                        shape: vec![rows, cols],
                        range: weights,
                    });
                    entries.push(Entry {
                        name: format!("{}.{l}.bias", p.name),
                        shape: vec![rows],
                        range: biases..biases + rows,
                    });
                    offset = biases + rows;
                }
            }
            ty => entries.push(whole(vec![ty.scalars()])),
        }
    }
    entries
}

/// A tensor to write: f32 values in a shape, encoded little-endian when the writer asks.
struct Floats<'a> {
    shape: Vec<usize>,
    values: &'a [f32],
}

impl View for Floats<'_> {
    fn dtype(&self) -> Dtype {
        Dtype::F32
    }

    fn shape(&self) -> &[usize] {
        &self.shape
    }

    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Owned(self.values.iter().flat_map(|x| x.to_le_bytes()).collect())
    }

    fn data_len(&self) -> usize {
        4 * self.values.len()
    }
}

/// Writes the checkpoint of `program` to `path`, atomically (the safetensors writer fills a temporary file
/// beside it, then renames it into place), readable by all like the run's other outputs.
pub fn write(path: &Path, program: &Program, step: u32, params: &[f32], adam: &Adam) -> Result<()> {
    let script = Script::of(program);
    let metadata = HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("step".to_string(), step.to_string()),
        ("adam_steps".to_string(), adam.steps().to_string()),
        ("script_name".to_string(), script.name),
        ("script_source".to_string(), script.source),
        (
            "script_overrides".to_string(),
            serde_json::to_string(&script.overrides).unwrap_or_default(),
        ),
    ]);
    let (m, v) = adam.moments();
    let mut tensors = Vec::new();
    for e in entries(program) {
        for (prefix, values) in [("", params), ("adam.m.", m), ("adam.v.", v)] {
            let tensor = Floats {
                shape: e.shape.clone(),
                values: &values[e.range.clone()],
            };
            tensors.push((format!("{prefix}{}", e.name), tensor));
        }
    }
    let fail =
        |e: &dyn std::fmt::Display| Failure::Message(format!("cannot write '{}': {e}", path.display()));
    safetensors::tensor::serialize_to_file(tensors, Some(metadata), path).map_err(|e| fail(&e))?;
    // The writer's temporary file is private (0600).
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let readable = std::fs::Permissions::from_mode(0o644);
        std::fs::set_permissions(path, readable).map_err(|e| fail(&e))?;
    }
    Ok(())
}

/// Reads a binary checkpoint: its script (compiled again) and the values, which must fit that script.
/// The file's size is checked against what the script's params need before its data is read.
pub fn read(path: &Path, bad: &dyn Fn(&str) -> Failure) -> Result<(Program, Saved)> {
    let mut file = std::fs::File::open(path).map_err(|e| bad(&e.to_string()))?;
    let file_len = file.metadata().map_err(|e| bad(&e.to_string()))?.len();
    let mut n = [0u8; 8];
    file.read_exact(&mut n)
        .map_err(|_| bad("it is too short to be a checkpoint"))?;
    let header_len = u64::from_le_bytes(n);
    if header_len > MAX_HEADER_BYTES || header_len > file_len - 8 {
        return Err(bad(&format!(
            "its header claims {header_len} bytes but the file holds {file_len}: it is not a \
             checkpoint (a safetensors file) or it is truncated"
        )));
    }
    let mut header = vec![0u8; header_len as usize];
    file.read_exact(&mut header).map_err(|e| bad(&e.to_string()))?;
    let header: serde_json::Value =
        serde_json::from_slice(&header).map_err(|e| bad(&format!("its header is not JSON ({e})")))?;
    let meta = |key: &str| -> Result<&str> {
        header["__metadata__"][key]
            .as_str()
            .ok_or_else(|| bad(&format!("its metadata has no '{key}'")))
    };
    if meta("format")? != FORMAT {
        return Err(bad(&format!(
            "it is in format '{}', not {FORMAT}",
            meta("format")?
        )));
    }
    let count = |key: &str| -> Result<u32> {
        meta(key)?
            .parse()
            .map_err(|_| bad(&format!("its '{key}' is not a step count")))
    };
    let (step, adam_steps) = (count("step")?, count("adam_steps")?);
    let overrides: Vec<String> = serde_json::from_str(meta("script_overrides")?)
        .map_err(|_| bad("its 'script_overrides' is not a list of strings"))?;
    let script = Script {
        name: meta("script_name")?.to_string(),
        source: meta("script_source")?.to_string(),
        overrides,
    };
    let program = script.compile_embedded(path)?;
    let data_len = 3 * 4 * program.n_params() as u64;
    if file_len != 8 + header_len + data_len {
        return Err(bad(&format!(
            "it holds {} bytes of values but its script's params and Adam's moments need {data_len}: \
             the file is truncated or was changed",
            file_len.saturating_sub(8 + header_len)
        )));
    }
    let bytes = nerfjit_runtime::data::input::read_capped(path).map_err(|e| bad(&e.to_string()))?;
    let tensors = SafeTensors::deserialize(&bytes).map_err(|e| bad(&e.to_string()))?;
    let n = program.n_params();
    let (mut params, mut m, mut v) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    for e in entries(&program) {
        for (prefix, values) in [("", &mut params), ("adam.m.", &mut m), ("adam.v.", &mut v)] {
            let name = format!("{prefix}{}", e.name);
            let t = tensors
                .tensor(&name)
                .map_err(|_| bad(&format!("it has no tensor '{name}'")))?;
            if t.dtype() != Dtype::F32 || t.shape() != e.shape {
                return Err(bad(&format!(
                    "tensor '{name}' is {:?} {:?}, not F32 {:?}",
                    t.dtype(),
                    t.shape(),
                    e.shape
                )));
            }
            let out = &mut values[e.range.clone()];
            for (x, b) in out.iter_mut().zip(t.data().chunks_exact(4)) {
                *x = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                if !x.is_finite() {
                    return Err(bad(&format!("tensor '{name}' holds {x}")));
                }
            }
        }
    }
    let adam = Adam::from_moments(0.0, adam_steps, m, v).map_err(|e| bad(&e.to_string()))?;
    let saved = Saved {
        script,
        step,
        params,
        adam,
    };
    Ok((program, saved))
}
