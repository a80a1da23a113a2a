//! The `.bake` file: a trained field baked into Gaussian splats by `nerfjit bake`, as a safetensors file
//! (float32 tensors `positions` (N, 3), `colors` (N, 3), `opacities` (N), `scales` (N, 3), `rotations`
//! (N, 4), as [`Splats`] holds them, and where the splats have them `sh` (N, 9), the degree-one spherical
//! harmonics, coefficient by coefficient, each an RGB triple) whose metadata says its format, the background its views are drawn
//! on and the checkpoint it was baked from (whose data gives the views it is scored on).

use std::borrow::Cow;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use nerfjit_runtime::splats::Splats;
use safetensors::tensor::{Dtype, View};

use crate::failure::{Failure, Result};

/// The metadata's `format` of a bake of splats.
const FORMAT: &str = "nerfjit-bake-splats-1";

/// A baked scene.
#[derive(Debug, Clone, PartialEq)]
pub struct Bake {
    /// Its splats.
    pub splats: Splats,
    /// The color its views are drawn on (the field's training background).
    pub background: [f32; 3],
    /// The checkpoint it was baked from.
    pub source: PathBuf,
}

/// Whether `path` names a baked scene (by its `.bake` extension).
pub fn is_bake(path: &Path) -> bool {
    path.extension().is_some_and(|e| e == "bake")
}

/// A float32 tensor.
struct Floats {
    shape: Vec<usize>,
    values: Vec<f32>,
}

impl Floats {
    /// Rows of `W` values as an (N, W) tensor (or (N) for `W` = 1).
    fn rows<const W: usize>(rows: &[[f32; W]]) -> Floats {
        let shape = if W == 1 {
            vec![rows.len()]
        } else {
            vec![rows.len(), W]
        };
        Floats {
            shape,
            values: rows.iter().flatten().copied().collect(),
        }
    }
}

impl View for Floats {
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

/// Writes `bake` to `path` (whole or not at all).
pub fn write(path: &Path, bake: &Bake) -> Result<()> {
    bake.splats.check()?;
    let s = &bake.splats;
    let opacities: Vec<[f32; 1]> = s.opacities.iter().map(|&o| [o]).collect();
    let metadata = HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        (
            "background".to_string(),
            serde_json::json!(bake.background).to_string(),
        ),
        ("source".to_string(), bake.source.to_string_lossy().into_owned()),
    ]);
    let mut tensors = vec![
        ("positions", Floats::rows(&s.positions)),
        ("colors", Floats::rows(&s.colors)),
        ("opacities", Floats::rows(&opacities)),
        ("scales", Floats::rows(&s.scales)),
        ("rotations", Floats::rows(&s.rotations)),
    ];
    if !s.sh.is_empty() {
        let flat: Vec<[f32; 9]> =
            s.sh.iter()
                .map(|h| std::array::from_fn(|k| h[k / 3][k % 3]))
                .collect();
        tensors.push(("sh", Floats::rows(&flat)));
    }
    let bytes = safetensors::tensor::serialize(tensors, Some(metadata))
        .map_err(|e| Failure::Message(format!("cannot write '{}': {e}", path.display())))?;
    Ok(nerfjit_runtime::write_whole(path, &bytes)?)
}

/// Reads the baked scene at `path`; says what is wrong with a file that is not one.
pub fn read(path: &Path) -> Result<Bake> {
    let bad = |what: &str| Failure::Message(format!("'{}' is not a baked scene: {what}", path.display()));
    let bytes = nerfjit_runtime::input::read_capped(path)
        .map_err(|e| Failure::Message(format!("cannot read '{}': {e}", path.display())))?;
    let file = safetensors::SafeTensors::deserialize(&bytes).map_err(|e| bad(&e.to_string()))?;
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).map_err(|e| bad(&e.to_string()))?;
    let metadata = header.metadata().clone().unwrap_or_default();
    let meta = |key: &str| {
        metadata
            .get(key)
            .ok_or_else(|| bad(&format!("its metadata has no '{key}'")))
    };
    if meta("format")? != FORMAT {
        return Err(bad(&format!("its format is '{}', not {FORMAT}", meta("format")?)));
    }
    let background: [f32; 3] =
        serde_json::from_str(meta("background")?).map_err(|_| bad("its background is not three numbers"))?;
    let floats = |name: &str, width: usize| -> Result<Vec<f32>> {
        let tensor = file
            .tensor(name)
            .map_err(|_| bad(&format!("it has no tensor '{name}'")))?;
        let shape = tensor.shape();
        let fits = tensor.dtype() == Dtype::F32
            && match width {
                1 => shape.len() == 1,
                w => shape.len() == 2 && shape[1] == w,
            };
        if !fits {
            return Err(bad(&format!(
                "'{name}' is {:?} {shape:?}, not float32 rows of {width}",
                tensor.dtype()
            )));
        }
        Ok(tensor
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect())
    };
    fn rows_of<const W: usize>(values: Vec<f32>) -> Vec<[f32; W]> {
        values
            .chunks_exact(W)
            .map(|c| std::array::from_fn(|i| c[i]))
            .collect()
    }
    let splats = Splats {
        positions: rows_of(floats("positions", 3)?),
        colors: rows_of(floats("colors", 3)?),
        opacities: floats("opacities", 1)?,
        scales: rows_of(floats("scales", 3)?),
        rotations: rows_of(floats("rotations", 4)?),
        sh: match file.names().contains(&"sh") {
            true => rows_of::<9>(floats("sh", 9)?)
                .into_iter()
                .map(|h| std::array::from_fn(|k| std::array::from_fn(|c| h[3 * k + c])))
                .collect(),
            false => Vec::new(),
        },
    };
    splats.check().map_err(|e| bad(&e.to_string()))?;
    Ok(Bake {
        splats,
        background,
        source: PathBuf::from(meta("source")?),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bake() -> Bake {
        Bake {
            splats: Splats {
                positions: vec![[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]],
                colors: vec![[0.1, 0.2, 0.3], [1.0, 0.0, 0.5]],
                opacities: vec![0.9, 0.25],
                scales: vec![[0.01, 0.02, 0.03], [0.5, 0.5, 0.5]],
                rotations: vec![[1.0, 0.0, 0.0, 0.0], [0.0, 0.6, 0.8, 0.0]],
                sh: vec![[[0.1, -0.2, 0.3], [0.0, 0.5, -0.5], [1.0, 2.0, 3.0]]; 2],
            },
            background: [1.0, 1.0, 1.0],
            source: PathBuf::from("runs/lego.ckpt.safetensors"),
        }
    }

    #[test]
    fn a_bake_reads_back_as_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("scene.bake");
        write(&path, &bake()).unwrap();
        assert_eq!(read(&path).unwrap(), bake());
        let mut alike_from_every_side = bake();
        alike_from_every_side.splats.sh.clear();
        write(&path, &alike_from_every_side).unwrap();
        assert_eq!(read(&path).unwrap(), alike_from_every_side);
    }

    #[test]
    fn files_that_are_not_bakes_say_what_is_wrong() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("scene.bake");
        std::fs::write(&path, b"not a safetensors file").unwrap();
        let message = read(&path).unwrap_err().to_string();
        assert!(message.contains("is not a baked scene"), "{message}");
        let mut broken = bake();
        broken.splats.opacities[1] = 2.0;
        assert!(write(&path, &broken)
            .unwrap_err()
            .to_string()
            .contains("splat 1: its opacity"));
        let missing = read(&dir.path().join("none.bake")).unwrap_err().to_string();
        assert!(missing.contains("cannot read"), "{missing}");
    }
}
