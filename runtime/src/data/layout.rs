//! Which layout a data set's folder or file is in, decided once for every command.
//!
//! Public copies of DTU, mip-NeRF 360 and other benchmarks often ship several layouts in one folder (a
//! DTU scan with `cameras_sphere.npz` and also `poses_bounds.npy` and a COLMAP `sparse/`; a 360 scene with
//! both a COLMAP model and LLFF bounds), and their cameras disagree. [`layouts_at`] lists every layout a
//! path holds, most specific first ([`PRECEDENCE`]): a DTU / IDR camera archive, LLFF bounds, a
//! nerfstudio `transforms.json`, a COLMAP model (the folder itself, or cameras and images in `sparse/0` or
//! `sparse`), Blender `transforms_*.json`. [`choose_layout`] takes the first, or the one the user names,
//! and keeps the others so that the choice can be reported ([`Chosen::note`]).

use std::path::{Path, PathBuf};

use crate::cameras::camera_files::CameraFormat;
use crate::data::colmap::is_colmap_model;
use crate::data::dtu::dtu_cameras_file;
use crate::data::llff::{is_llff, POSES_FILE};
use crate::data::nerfstudio::is_nerfstudio;
use crate::error::{Error, Result};
use crate::input::read_text_capped;

/// A layout of captured or synthetic views that nerfjit reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// A DTU scan in the IDR / NeuS layout (`cameras_sphere.npz` or `cameras.npz`).
    Dtu,
    /// An LLFF scene (`poses_bounds.npy`).
    Llff,
    /// A nerfstudio / instant-ngp `transforms.json`.
    Nerfstudio,
    /// A COLMAP model (`cameras`, `images`, `points3D` as `.txt` or `.bin`).
    Colmap,
    /// Blender / NeRF-synthetic `transforms_*.json`.
    Blender,
}

/// The layouts in the order a folder holding several is read: the most specific first.
pub const PRECEDENCE: [Layout; 5] = [
    Layout::Dtu,
    Layout::Llff,
    Layout::Nerfstudio,
    Layout::Colmap,
    Layout::Blender,
];

impl Layout {
    /// The name users write (`--format dtu`, the reader `dtu(...)`).
    pub fn name(self) -> &'static str {
        match self {
            Layout::Dtu => "dtu",
            Layout::Llff => "llff",
            Layout::Nerfstudio => "nerfstudio",
            Layout::Colmap => "colmap",
            Layout::Blender => "blender",
        }
    }

    /// The layout called `name`, if any.
    pub fn parse(name: &str) -> Option<Layout> {
        PRECEDENCE.into_iter().find(|l| l.name() == name)
    }

    /// Its name for people: "DTU", "LLFF", ...
    pub fn title(self) -> &'static str {
        match self {
            Layout::Dtu => "DTU",
            Layout::Llff => "LLFF",
            Layout::Nerfstudio => "nerfstudio",
            Layout::Colmap => "COLMAP",
            Layout::Blender => "Blender",
        }
    }
}

/// One layout found at a path, and what its reader takes: the scan's or scene's folder (DTU, LLFF), the
/// model's folder (COLMAP), the `transforms.json` (nerfstudio), or the Blender transforms file (a folder
/// of Blender files: the folder).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Found {
    /// The layout.
    pub layout: Layout,
    /// What its reader takes.
    pub source: PathBuf,
    /// The file or folder that shows it, for people (e.g. `poses_bounds.npy`, `sparse/0`).
    pub evidence: String,
}

impl Found {
    fn new(layout: Layout, source: PathBuf, evidence: impl Into<String>) -> Found {
        Found {
            layout,
            source,
            evidence: evidence.into(),
        }
    }

    /// "DTU (cameras_sphere.npz)".
    pub fn describe(&self) -> String {
        format!("{} ({})", self.layout.title(), self.evidence)
    }
}

/// The Blender transforms files looked for in a folder.
const BLENDER_FILES: &[&str] = &[
    "transforms_train.json",
    "transforms_val.json",
    "transforms_test.json",
];

/// The COLMAP models looked for in a folder, below it.
const COLMAP_FOLDERS: &[&str] = &["sparse/0", "sparse"];

/// Every layout `path` holds, in [`PRECEDENCE`] order: for a folder, each layout whose files it holds
/// (a COLMAP model in the folder itself or in `sparse/0` or `sparse`); for a file, nerfstudio or Blender
/// transforms by their keys. Empty when it holds none (or does not exist).
pub fn layouts_at(path: &Path) -> Vec<Found> {
    let mut found = Vec::new();
    if path.is_file() {
        let text = read_text_capped(path).unwrap_or_default();
        let file = || path.to_path_buf();
        let name = path
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        if is_nerfstudio(&text) {
            found.push(Found::new(Layout::Nerfstudio, file(), name));
        } else if CameraFormat::of_text(&text) == Some(CameraFormat::Blender) {
            found.push(Found::new(Layout::Blender, file(), name));
        }
        return found;
    }
    if !path.is_dir() {
        return found;
    }
    if let Some(archive) = dtu_cameras_file(path) {
        let name = archive.file_name().map(|n| n.to_string_lossy().into_owned());
        found.push(Found::new(
            Layout::Dtu,
            path.to_path_buf(),
            name.unwrap_or_default(),
        ));
    }
    if is_llff(path) {
        found.push(Found::new(Layout::Llff, path.to_path_buf(), POSES_FILE));
    }
    let transforms = path.join("transforms.json");
    let transforms_text = read_text_capped(&transforms).unwrap_or_default();
    if is_nerfstudio(&transforms_text) {
        found.push(Found::new(Layout::Nerfstudio, transforms, "transforms.json"));
    }
    if is_colmap_model(path) {
        found.push(Found::new(
            Layout::Colmap,
            path.to_path_buf(),
            "cameras, images, points3D",
        ));
    } else if let Some(sub) = COLMAP_FOLDERS.iter().find(|s| is_complete_model(&path.join(s))) {
        found.push(Found::new(Layout::Colmap, path.join(sub), *sub));
    }
    let blender: Vec<&str> = BLENDER_FILES
        .iter()
        .copied()
        .filter(|f| path.join(f).is_file())
        .collect();
    if !blender.is_empty() {
        found.push(Found::new(
            Layout::Blender,
            path.to_path_buf(),
            blender.join(", "),
        ));
    }
    found
}

/// Whether `folder` holds a COLMAP model's cameras and images (LLFF scenes ship a `sparse/0` with
/// `cameras.bin` and `points3D.bin` only, which is no model to read).
fn is_complete_model(folder: &Path) -> bool {
    is_colmap_model(folder)
        && ["images.txt", "images.bin"]
            .iter()
            .any(|f| folder.join(f).is_file())
}

/// The layout a path is read as, and the other layouts it also holds.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Chosen {
    /// The layout read.
    pub found: Found,
    /// The other layouts the path holds, most specific first.
    pub others: Vec<Found>,
    /// Whether the user named it (otherwise it was the most specific).
    pub named: bool,
}

impl Chosen {
    /// When the path holds several layouts, a line saying which it is read as and why, and how to choose
    /// another; `None` when it holds one.
    pub fn note(&self, path: &Path) -> Option<String> {
        if self.others.is_empty() {
            return None;
        }
        let others: Vec<String> = self.others.iter().map(Found::describe).collect();
        let why = if self.named {
            "as asked"
        } else {
            "the most specific (name another with --format)"
        };
        Some(format!(
            "note: '{}' holds several layouts: read as {}, {why}; it also holds {}",
            path.display(),
            self.found.describe(),
            others.join(", ")
        ))
    }
}

/// The layout to read `path` as: `wanted` when given (an error saying what the path holds when it does
/// not hold that one), else the most specific it holds; `None` when it holds none of them (the caller
/// may read it otherwise, e.g. as the course's camera file).
pub fn choose_layout(path: &Path, wanted: Option<Layout>) -> Result<Option<Chosen>> {
    let mut all = layouts_at(path);
    let index = match wanted {
        None if all.is_empty() => return Ok(None),
        None => 0,
        Some(layout) => all.iter().position(|f| f.layout == layout).ok_or_else(|| {
            let held = match all.is_empty() {
                true => "none of the layouts nerfjit reads".to_string(),
                false => all.iter().map(Found::describe).collect::<Vec<_>>().join(", "),
            };
            Error::Invalid(format!(
                "'{}' holds no {} data set: it holds {held}",
                path.display(),
                layout.title()
            ))
        })?,
    };
    let found = all.remove(index);
    Ok(Some(Chosen {
        found,
        others: all,
        named: wanted.is_some(),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::scratch_folder;

    fn touch(dir: &Path, file: &str, text: &str) {
        let path = dir.join(file);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, text).unwrap();
    }

    const NERFSTUDIO: &str = r#"{"camera_model": "OPENCV", "fl_x": 10, "frames": []}"#;
    const BLENDER: &str = r#"{"camera_angle_x": 0.7, "frames": []}"#;

    #[test]
    fn a_folder_with_every_layout_lists_them_most_specific_first() {
        let dir = scratch_folder("layouts");
        touch(dir.path(), "transforms_test.json", BLENDER);
        touch(dir.path(), "sparse/0/cameras.txt", "");
        touch(dir.path(), "sparse/0/images.txt", "");
        touch(dir.path(), "transforms.json", NERFSTUDIO);
        touch(dir.path(), "poses_bounds.npy", "");
        touch(dir.path(), "cameras_sphere.npz", "");
        let found = layouts_at(dir.path());
        let layouts: Vec<Layout> = found.iter().map(|f| f.layout).collect();
        assert_eq!(layouts, PRECEDENCE);
        assert_eq!(found[2].source, dir.path().join("transforms.json"));
        assert_eq!(found[3].source, dir.path().join("sparse/0"));
        assert_eq!(found[4].evidence, "transforms_test.json");

        let chosen = choose_layout(dir.path(), None).unwrap().unwrap();
        assert_eq!(chosen.found.layout, Layout::Dtu);
        assert_eq!(chosen.others.len(), 4);
        let note = chosen.note(dir.path()).unwrap();
        assert!(
            note.contains("read as DTU (cameras_sphere.npz)")
                && note.contains("LLFF (poses_bounds.npy), nerfstudio (transforms.json), COLMAP (sparse/0)"),
            "{note}"
        );
        let llff = choose_layout(dir.path(), Some(Layout::Llff)).unwrap().unwrap();
        assert_eq!((llff.found.layout, llff.others.len()), (Layout::Llff, 4));
        assert!(llff.note(dir.path()).unwrap().contains("as asked"));
    }

    #[test]
    fn one_layout_has_no_note_and_a_missing_one_says_what_is_there() {
        let dir = scratch_folder("layout-one");
        touch(dir.path(), "cameras.bin", "");
        let chosen = choose_layout(dir.path(), None).unwrap().unwrap();
        assert_eq!(chosen.found.layout, Layout::Colmap);
        assert_eq!(chosen.found.source, dir.path());
        assert_eq!(chosen.note(dir.path()), None);
        let err = choose_layout(dir.path(), Some(Layout::Dtu))
            .unwrap_err()
            .to_string();
        assert!(err.contains("holds no DTU data set: it holds COLMAP"), "{err}");
        let empty = scratch_folder("layout-none");
        assert_eq!(choose_layout(empty.path(), None).unwrap(), None);
        let err = choose_layout(empty.path(), Some(Layout::Llff))
            .unwrap_err()
            .to_string();
        assert!(err.contains("none of the layouts"), "{err}");
    }

    #[test]
    fn files_are_told_apart_by_their_keys() {
        let dir = scratch_folder("layout-files");
        touch(dir.path(), "a.json", NERFSTUDIO);
        touch(dir.path(), "b.json", BLENDER);
        touch(dir.path(), "c.json", r#"{"image_size": [2, 2], "cameras": []}"#);
        let layout = |f: &str| layouts_at(&dir.path().join(f)).first().map(|f| f.layout);
        assert_eq!(layout("a.json"), Some(Layout::Nerfstudio));
        assert_eq!(layout("b.json"), Some(Layout::Blender));
        assert_eq!(layout("c.json"), None);
        assert_eq!(layout("missing.json"), None);
        for l in PRECEDENCE {
            assert_eq!(Layout::parse(l.name()), Some(l));
        }
        assert_eq!(Layout::parse("mipnerf"), None);
    }
}
