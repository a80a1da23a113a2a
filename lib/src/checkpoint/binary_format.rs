//! The binary checkpoint format: a [safetensors](https://github.com/huggingface/safetensors) file, which
//! PyTorch, NumPy and JAX users open with `safetensors.*.load_file`. Each param is a tensor named after it,
//! in its shape (`f32` as a scalar, `vec<n>` as `[n]`, `mat<r, c>` as `[r, c]` row-major, an `mlp`'s layer
//! `l` as `NAME.l.weight` `[out, in]` and `NAME.l.bias` `[out]` like PyTorch's `nn.Linear`, a grid's table
//! flat); Adam's moments are `adam.m.NAME…` and `adam.v.NAME…`. The metadata holds the format, the step,
//! Adam's step count, the fraction of its run the training had done (`run_fraction`, where a schedule
//! over the run resumes) and the script (name, source and `--set` overrides). A run that skips empty space
//! also keeps its occupancy grid as it last rendered with it: the tensor `occupancy` (`u8`, the cells'
//! bits packed 8 to a byte, x fastest) with its box (`occupancy_bounds`, JSON `[lo, hi]`) and
//! `occupancy_resolution` in the metadata (and `occupancy_space: contracted` for a grid over contracted
//! coordinates), so that renders and scores of the checkpoint skip exactly the cells the run's validation
//! skipped. A run with `appearance: true` keeps its training views' colour transforms and their Adam
//! states in the tensor `appearance` (`f32`, `[views, 37]`: each view's 12 values, then its Adam state
//! `[steps, m…, v…]`).

use std::borrow::Cow;
use std::collections::HashMap;
use std::io::Read;
use std::ops::Range;
use std::path::Path;

use nerfjit_dsl::{Program, Type};
use nerfjit_runtime::{Adam, GridSpace, OccupancyGrid};
use safetensors::tensor::{Dtype, SafeTensors, View};

use super::{Kept, Saved, Script, VIEW_STATE};
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

/// A tensor to write, encoded when the writer asks: f32 values in a shape (little-endian), or bytes.
enum Tensor<'a> {
    Floats { shape: Vec<usize>, values: &'a [f32] },
    Bytes { shape: [usize; 1], bytes: &'a [u8] },
}

impl View for Tensor<'_> {
    fn dtype(&self) -> Dtype {
        match self {
            Tensor::Floats { .. } => Dtype::F32,
            Tensor::Bytes { .. } => Dtype::U8,
        }
    }

    fn shape(&self) -> &[usize] {
        match self {
            Tensor::Floats { shape, .. } => shape,
            Tensor::Bytes { shape, .. } => shape,
        }
    }

    fn data(&self) -> Cow<'_, [u8]> {
        match self {
            Tensor::Floats { values, .. } => {
                Cow::Owned(values.iter().flat_map(|x| x.to_le_bytes()).collect())
            }
            Tensor::Bytes { bytes, .. } => Cow::Borrowed(bytes),
        }
    }

    fn data_len(&self) -> usize {
        match self {
            Tensor::Floats { values, .. } => 4 * values.len(),
            Tensor::Bytes { bytes, .. } => bytes.len(),
        }
    }
}

/// The name of the occupancy grid's tensor.
const OCCUPANCY: &str = "occupancy";

/// The name of the colour transforms' tensor.
const APPEARANCE: &str = "appearance";

/// The metadata key of the fraction of its run the training had done.
const RUN_FRACTION: &str = "run_fraction";

/// Writes the checkpoint of `program` to `path`, atomically (the safetensors writer fills a temporary file
/// beside it, then renames it into place), readable by all like the run's other outputs; with what
/// the run keeps: the occupancy grid it renders with and its colour transforms, if it has them.
pub fn write(
    path: &Path,
    program: &Program,
    step: u32,
    params: &[f32],
    adam: &Adam,
    kept: Kept,
) -> Result<()> {
    let occupancy = kept.occupancy;
    let script = Script::of(program);
    let mut metadata = HashMap::from([
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
            let tensor = Tensor::Floats {
                shape: e.shape.clone(),
                values: &values[e.range.clone()],
            };
            tensors.push((format!("{prefix}{}", e.name), tensor));
        }
    }
    if let Some(fraction) = kept.run_fraction {
        metadata.insert(RUN_FRACTION.to_string(), fraction.to_string());
    }
    let packed = occupancy.map(|grid| grid.packed_cells());
    if let (Some(grid), Some(bytes)) = (occupancy, &packed) {
        let (lo, hi) = grid.bounds();
        metadata.insert(
            "occupancy_bounds".to_string(),
            serde_json::to_string(&[lo, hi]).unwrap_or_default(),
        );
        metadata.insert("occupancy_resolution".to_string(), grid.resolution().to_string());
        if grid.space() != GridSpace::Scene {
            metadata.insert("occupancy_space".to_string(), grid.space().name().to_string());
        }
        let tensor = Tensor::Bytes {
            shape: [bytes.len()],
            bytes,
        };
        tensors.push((OCCUPANCY.to_string(), tensor));
    }
    if let Some(state) = &kept.appearance {
        let tensor = Tensor::Floats {
            shape: vec![state.len() / VIEW_STATE, VIEW_STATE],
            values: state,
        };
        tensors.push((APPEARANCE.to_string(), tensor));
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
    let run_fraction = match header["__metadata__"].get(RUN_FRACTION) {
        None => None,
        Some(f) => Some(
            f.as_str()
                .and_then(|f| f.parse::<f64>().ok())
                .filter(|f| (0.0..=1.0).contains(f))
                .ok_or_else(|| bad(&format!("its '{RUN_FRACTION}' is not a number from 0 to 1")))?,
        ),
    };
    let overrides: Vec<String> = serde_json::from_str(meta("script_overrides")?)
        .map_err(|_| bad("its 'script_overrides' is not a list of strings"))?;
    let script = Script {
        name: meta("script_name")?.to_string(),
        source: meta("script_source")?.to_string(),
        overrides,
    };
    let program = script.compile_embedded(path)?;
    let occupancy_len = match header["__metadata__"].get("occupancy_resolution") {
        Some(resolution) => {
            let r: u64 = resolution
                .as_str()
                .and_then(|r| r.parse().ok())
                .filter(|&r| (1..=256).contains(&r))
                .ok_or_else(|| bad("its 'occupancy_resolution' is not a grid resolution"))?;
            (r * r * r).div_ceil(8)
        }
        None => 0,
    };
    let appearance_len = match header.get(APPEARANCE) {
        Some(entry) => {
            let shape: Option<Vec<u64>> = entry["shape"]
                .as_array()
                .map(|s| s.iter().filter_map(|x| x.as_u64()).collect());
            match shape.as_deref() {
                Some(&[views, n]) if n == VIEW_STATE as u64 && entry["dtype"] == "F32" => 4 * views * n,
                _ => {
                    return Err(bad(&format!(
                        "its tensor '{APPEARANCE}' is not F32 [views, {VIEW_STATE}]"
                    )))
                }
            }
        }
        None => 0,
    };
    let data_len = 3 * 4 * program.n_params() as u64 + occupancy_len + appearance_len;
    if file_len != 8 + header_len + data_len {
        return Err(bad(&format!(
            "it holds {} bytes of values but its script's params and Adam's moments need {data_len}: \
             the file is truncated or was changed",
            file_len.saturating_sub(8 + header_len)
        )));
    }
    let bytes = nerfjit_runtime::input::read_capped(path).map_err(|e| bad(&e.to_string()))?;
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
        run_fraction,
    };
    Ok((program, saved))
}

/// The header of a binary checkpoint and the bytes of its tensor `name`, if it has one: read from the
/// header and that tensor alone.
fn read_tensor(path: &Path, name: &str) -> Result<Option<(serde_json::Value, Vec<u8>)>> {
    let bad = |why: String| Failure::Message(format!("checkpoint '{}' is not usable: {why}", path.display()));
    let mut file = std::fs::File::open(path).map_err(|e| bad(e.to_string()))?;
    let file_len = file.metadata().map_err(|e| bad(e.to_string()))?.len();
    let mut n = [0u8; 8];
    file.read_exact(&mut n).map_err(|e| bad(e.to_string()))?;
    let header_len = u64::from_le_bytes(n);
    if header_len > MAX_HEADER_BYTES || header_len > file_len.saturating_sub(8) {
        return Err(bad(format!("its header claims {header_len} bytes")));
    }
    let mut header = vec![0u8; header_len as usize];
    file.read_exact(&mut header).map_err(|e| bad(e.to_string()))?;
    let header: serde_json::Value =
        serde_json::from_slice(&header).map_err(|e| bad(format!("its header is not JSON ({e})")))?;
    let Some(entry) = header.get(name) else {
        return Ok(None);
    };
    let offsets: Option<Vec<u64>> = entry["data_offsets"]
        .as_array()
        .map(|o| o.iter().filter_map(|x| x.as_u64()).collect());
    let Some(&[start, end]) = offsets.as_deref() else {
        return Err(bad(format!("its tensor '{name}' lacks its data offsets")));
    };
    let begin = 8 + header_len + start;
    if !(start <= end && begin + (end - start) <= file_len) {
        return Err(bad(format!(
            "its tensor '{name}''s offsets {start}..{end} are out of the file"
        )));
    }
    std::io::Seek::seek(&mut file, std::io::SeekFrom::Start(begin)).map_err(|e| bad(e.to_string()))?;
    let mut bytes = vec![0u8; (end - start) as usize];
    file.read_exact(&mut bytes).map_err(|e| bad(e.to_string()))?;
    Ok(Some((header, bytes)))
}

/// The occupancy grid a binary checkpoint keeps (see the [module docs](self)), if it keeps one: read from
/// its header and that tensor alone.
pub fn read_occupancy(path: &Path) -> Result<Option<OccupancyGrid>> {
    let bad = |why: String| Failure::Message(format!("checkpoint '{}' is not usable: {why}", path.display()));
    let Some((header, bytes)) = read_tensor(path, OCCUPANCY)? else {
        return Ok(None);
    };
    let meta = &header["__metadata__"];
    let bounds: Option<[[f32; 3]; 2]> = meta["occupancy_bounds"]
        .as_str()
        .and_then(|b| serde_json::from_str(b).ok());
    let resolution: Option<usize> = meta["occupancy_resolution"].as_str().and_then(|r| r.parse().ok());
    let (Some([lo, hi]), Some(resolution)) = (bounds, resolution) else {
        return Err(bad("its occupancy grid lacks its bounds or resolution".into()));
    };
    let space = match meta.get("occupancy_space") {
        None => GridSpace::Scene,
        Some(name) => name.as_str().and_then(GridSpace::named).ok_or_else(|| {
            bad(format!(
                "its occupancy grid's space {name} is not 'scene' or 'contracted'"
            ))
        })?,
    };
    let grid = OccupancyGrid::from_packed_cells((lo, hi), resolution, &bytes)
        .map_err(|e| bad(format!("its occupancy grid: {e}")))?;
    Ok(Some(grid.in_space(space)))
}

/// The state of the colour transforms a binary checkpoint keeps (see the [module docs](self)), if it keeps
/// them: [`VIEW_STATE`] floats a view.
pub fn read_appearance(path: &Path) -> Result<Option<Vec<f32>>> {
    let Some((_, bytes)) = read_tensor(path, APPEARANCE)? else {
        return Ok(None);
    };
    let state: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    if !bytes.len().is_multiple_of(4 * VIEW_STATE) || !state.iter().all(|x| x.is_finite()) {
        return Err(Failure::Message(format!(
            "checkpoint '{}' is not usable: its tensor '{APPEARANCE}' is not {VIEW_STATE} finite floats a view",
            path.display()
        )));
    }
    Ok(Some(state))
}
