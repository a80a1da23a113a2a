//! Fuzz target for every data parser: the first byte picks a format, the rest is the file's content,
//! written to a scratch folder and read by the loader a user's command would call. Any content must give
//! data or an error, never a panic, a hang or an allocation beyond what the file holds.
#![no_main]

use std::path::{Path, PathBuf};

use libfuzzer_sys::fuzz_target;
use nerfjit_runtime::cameras::{camera_files, camera_path};
use nerfjit_runtime::data::{colmap, dtu, llff, nerfstudio, pointcloud};

/// The formats, by the first byte modulo their count.
const FORMATS: [&str; 15] = [
    "points.npy",
    "points.npz",
    "points.ply",
    "points.xyz",
    "box_cameras.json",
    "transforms.json",
    "nerfstudio.json",
    "camera_path.json",
    "colmap.bin",
    "colmap.txt",
    "checkpoint.safetensors",
    "checkpoint.ckpt.json",
    "model.vm",
    "llff/poses_bounds.npy",
    "dtu/cameras_sphere.npz",
];

/// A 1×1 grayscale PNG: the one image of the scratch folder's LLFF scene and DTU scan, so that their
/// loaders go on to read the fuzzed pose or camera file.
const ONE_PIXEL_PNG: [u8; 67] = [
    137, 80, 78, 71, 13, 10, 26, 10, 0, 0, 0, 13, 73, 72, 68, 82, 0, 0, 0, 1, 0, 0, 0, 1, 8, 0, 0, 0, 0, 58,
    126, 155, 85, 0, 0, 0, 10, 73, 68, 65, 84, 120, 156, 99, 96, 0, 0, 0, 2, 0, 1, 72, 175, 164, 113, 0, 0, 0,
    0, 73, 69, 78, 68, 174, 66, 96, 130,
];

/// A scratch folder of this process.
fn scratch() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("nerfjit-fuzz-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("colmap")).unwrap();
    for images in ["llff/images", "dtu/image"] {
        std::fs::create_dir_all(dir.join(images)).unwrap();
        std::fs::write(dir.join(images).join("000.png"), ONE_PIXEL_PNG).unwrap();
    }
    dir
}

fuzz_target!(|data: &[u8]| {
    let Some((&pick, content)) = data.split_first() else {
        return;
    };
    let dir = scratch();
    let name = FORMATS[usize::from(pick) % FORMATS.len()];
    let file = dir.join(name);
    std::fs::write(&file, content).unwrap();
    read(name, &file, &dir);
    std::fs::remove_file(&file).ok();
});

/// Three binary files from one input: two little-endian u16 lengths, then the files' bytes.
fn split_binary(content: &[u8]) -> Vec<&[u8]> {
    if content.len() < 4 {
        return vec![content];
    }
    let (lengths, rest) = content.split_at(4);
    let a = usize::from(u16::from_le_bytes([lengths[0], lengths[1]])).min(rest.len());
    let b = usize::from(u16::from_le_bytes([lengths[2], lengths[3]])).min(rest.len() - a);
    vec![&rest[..a], &rest[a..a + b], &rest[a + b..]]
}

/// Reads `file` as the format `name` says; the result is dropped.
fn read(name: &str, file: &Path, dir: &Path) {
    match name {
        "points.npz" => drop(pointcloud::read_points(file, Some("verts"))),
        "points.npy" | "points.ply" | "points.xyz" => drop(pointcloud::read_points(file, None)),
        "box_cameras.json" => drop(camera_files::load_box_cameras(file)),
        "transforms.json" => drop(camera_files::load_blender_cameras(file)),
        "nerfstudio.json" => drop(nerfstudio::load_nerfstudio(file)),
        "camera_path.json" => drop(camera_path::load_camera_path(file)),
        "colmap.bin" | "colmap.txt" => {
            let model = dir.join("colmap");
            let content = std::fs::read(file).unwrap();
            let (parts, extension) = if name == "colmap.bin" {
                (split_binary(&content), "bin")
            } else {
                (content.split(|&b| b == b'%').take(3).collect(), "txt")
            };
            for (part, stem) in parts.iter().zip(["cameras", "images", "points3D"]) {
                std::fs::write(model.join(format!("{stem}.{extension}")), part).unwrap();
            }
            drop(colmap::load_colmap(&model, &dir.join("images")));
            std::fs::remove_dir_all(&model).ok();
            std::fs::create_dir_all(&model).unwrap();
        }
        "llff/poses_bounds.npy" => drop(llff::load_llff(&dir.join("llff"), 1)),
        "dtu/cameras_sphere.npz" => drop(dtu::load_dtu(&dir.join("dtu"), false)),
        "checkpoint.safetensors" | "checkpoint.ckpt.json" => drop(nerfjit::checkpoint::load_trained(file)),
        _ => drop(nerfjit::commands::import::run(file, Some(&dir.join("model.sdf")))),
    }
}
