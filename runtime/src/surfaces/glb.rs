//! glTF 2.0 binary files (`.glb`) of meshes ([`write_glb`]): one mesh of indexed triangles with positions
//! and normals and one material; with a texture [`Atlas`], each patch's triangles (one, or two sharing a
//! side) have vertices of their own with their UVs, and the atlas is a PNG inside the file, the material's
//! base color, unlit (`KHR_materials_unlit`: the colors are what a camera saw, lighting included).
//!
//! The positions are the scene's, in its units (glTF reads them as metres). glTF's up is +y; a scene whose
//! up is +z (Blender's, such as NeRF-synthetic's lego) is turned by its node, −90° about x, so that it
//! stands upright in viewers with its vertices unchanged.
//!
//! The JSON document is built with `serde_json` (the crate the runtime already reads JSON with): it is one
//! fixed shape of a few dozen fields, spelled here as the glTF specification spells them; the tests read
//! the files back with the `gltf` crate and CI checks them with the Khronos glTF validator.

use std::path::Path;

use glam::Vec3;
use image::ImageFormat;
use serde_json::{json, Value};

use crate::cameras::paths::Up;
use crate::error::{Error, Result};
use crate::surfaces::atlas::{Atlas, Patch};
use crate::surfaces::mesh::Mesh;

/// The header's magic: `glTF`.
const MAGIC: u32 = 0x4654_6C67;
/// The JSON chunk's type: `JSON`.
const JSON_CHUNK: u32 = 0x4E4F_534A;
/// The binary chunk's type: `BIN\0`.
const BIN_CHUNK: u32 = 0x004E_4942;
/// Buffer view targets.
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
/// Accessor component types.
const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;
/// Sampler filter and wrap modes.
const LINEAR: u32 = 9729;
const CLAMP_TO_EDGE: u32 = 33071;

/// Writes `mesh` as a glTF 2.0 binary file at `path`, whole or not at all, textured with `texture` (laid
/// out for the mesh's triangles) if given; `up` is the scene's up axis (see the module's doc).
pub fn write_glb(mesh: &Mesh, texture: Option<&Atlas>, up: Up, path: &Path) -> Result<()> {
    let bytes = glb_bytes(mesh, texture, up).map_err(|e| match e {
        Error::Invalid(reason) => Error::write(path, reason),
        e => e,
    })?;
    crate::whole_file::write_whole(path, &bytes)
}

/// The bytes of the glTF 2.0 binary file of `mesh` (see [`write_glb`]).
pub fn glb_bytes(mesh: &Mesh, texture: Option<&Atlas>, up: Up) -> Result<Vec<u8>> {
    mesh.check()?;
    if mesh.triangles.is_empty() {
        return Err(Error::Invalid(
            "the mesh has no triangles, and a glTF mesh needs at least one".into(),
        ));
    }
    if let Some(atlas) = texture {
        let triangles: usize = atlas
            .patches
            .iter()
            .map(|p| 1 + usize::from(p.second.is_some()))
            .sum();
        let n = mesh.vertices.len();
        let in_range = |p: &Patch| {
            p.first
                .iter()
                .chain(p.second.iter().flatten())
                .all(|&v| (v as usize) < n)
        };
        if triangles != mesh.triangles.len() || !atlas.patches.iter().all(in_range) {
            return Err(Error::Invalid(format!(
                "the texture's patches hold {triangles} triangles, not the mesh's {}",
                mesh.triangles.len()
            )));
        }
    }
    let Attributes {
        positions,
        normals,
        uvs,
        indices,
    } = Attributes::new(mesh, texture);
    let mut bin = Binary::default();
    let floats =
        |rows: &[[f32; 3]]| -> Vec<u8> { rows.iter().flatten().flat_map(|x| x.to_le_bytes()).collect() };
    let position_view = bin.view(&floats(&positions), Some(ARRAY_BUFFER));
    let normal_view = bin.view(&floats(&normals), Some(ARRAY_BUFFER));
    let index_bytes: Vec<u8> = indices.iter().flat_map(|i| i.to_le_bytes()).collect();
    let index_view = bin.view(&index_bytes, Some(ELEMENT_ARRAY_BUFFER));
    let (min, max) = mesh_bounds(&positions);
    let mut accessors = vec![
        json!({"bufferView": position_view, "componentType": FLOAT, "count": positions.len(), "type": "VEC3",
               "min": min, "max": max}),
        json!({"bufferView": normal_view, "componentType": FLOAT, "count": normals.len(), "type": "VEC3"}),
        json!({"bufferView": index_view, "componentType": UNSIGNED_INT, "count": indices.len(),
               "type": "SCALAR"}),
    ];
    let mut attributes = json!({"POSITION": 0, "NORMAL": 1});
    let mut document = json!({
        "asset": {"version": "2.0", "generator": "nerfjit"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [node(up)],
    });
    let material = match texture {
        None => json!({
            "name": "surface",
            "pbrMetallicRoughness": {"baseColorFactor": [0.85, 0.8, 0.7, 1.0], "metallicFactor": 0.0,
                                     "roughnessFactor": 1.0},
        }),
        Some(atlas) => {
            let uv_bytes: Vec<u8> = uvs.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
            let uv_view = bin.view(&uv_bytes, Some(ARRAY_BUFFER));
            accessors.push(
                json!({"bufferView": uv_view, "componentType": FLOAT, "count": uvs.len(), "type": "VEC2"}),
            );
            attributes["TEXCOORD_0"] = json!(3);
            let mut png = std::io::Cursor::new(Vec::new());
            atlas
                .image
                .write_to(&mut png, ImageFormat::Png)
                .map_err(|e| Error::Invalid(format!("cannot encode the texture as PNG: {e}")))?;
            let image_view = bin.view(png.get_ref(), None);
            document["images"] = json!([{"bufferView": image_view, "mimeType": "image/png"}]);
            document["samplers"] = json!([{"magFilter": LINEAR, "minFilter": LINEAR,
                                           "wrapS": CLAMP_TO_EDGE, "wrapT": CLAMP_TO_EDGE}]);
            document["textures"] = json!([{"sampler": 0, "source": 0}]);
            document["extensionsUsed"] = json!(["KHR_materials_unlit"]);
            json!({
                "name": "texture",
                "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0,
                                         "roughnessFactor": 1.0},
                "extensions": {"KHR_materials_unlit": {}},
            })
        }
    };
    document["materials"] = json!([material]);
    document["meshes"] =
        json!([{"primitives": [{"attributes": attributes, "indices": 2, "material": 0, "mode": 4}]}]);
    document["accessors"] = Value::Array(accessors);
    document["bufferViews"] = Value::Array(bin.views);
    document["buffers"] = json!([{"byteLength": bin.bytes.len()}]);
    container(&document, &bin.bytes)
}

/// The vertices' attributes and the triangles' indices as written.
struct Attributes {
    positions: Vec<[f32; 3]>,
    /// Unit normals, as glTF requires (+y for a vertex no triangle gave one).
    normals: Vec<[f32; 3]>,
    /// Empty without a texture.
    uvs: Vec<[f32; 2]>,
    indices: Vec<u32>,
}

impl Attributes {
    /// The mesh's own vertices; or, with a texture, each patch's corners as vertices of their own, with
    /// their UVs: three for a triangle alone, four for a pair (see [`Patch`]).
    fn new(mesh: &Mesh, texture: Option<&Atlas>) -> Attributes {
        let unit = |k: usize| Vec3::from(mesh.normals[k]).normalize_or(Vec3::Y).to_array();
        match texture {
            None => Attributes {
                positions: mesh.vertices.clone(),
                normals: (0..mesh.vertices.len()).map(unit).collect(),
                uvs: Vec::new(),
                indices: mesh.triangles.iter().flatten().copied().collect(),
            },
            Some(atlas) => {
                let mut vertices: Vec<(u32, [f32; 2])> = Vec::with_capacity(2 * mesh.triangles.len());
                let mut indices = Vec::with_capacity(3 * mesh.triangles.len());
                for (k, patch) in atlas.patches.iter().enumerate() {
                    let base = vertices.len() as u32;
                    let [a, b, c, d] = atlas.layout.uvs(k);
                    let [x, y, z] = patch.first;
                    vertices.extend([(x, a), (y, b), (z, c)]);
                    indices.extend([base, base + 1, base + 2]);
                    if let Some([w, ..]) = patch.second {
                        vertices.push((w, d));
                        indices.extend([base + 3, base + 2, base + 1]);
                    }
                }
                Attributes {
                    positions: vertices.iter().map(|&(v, _)| mesh.vertices[v as usize]).collect(),
                    normals: vertices.iter().map(|&(v, _)| unit(v as usize)).collect(),
                    uvs: vertices.iter().map(|&(_, uv)| uv).collect(),
                    indices,
                }
            }
        }
    }
}

/// The scene's one node: the mesh, turned so that the scene's up is glTF's +y.
fn node(up: Up) -> Value {
    match up {
        Up::Y => json!({"mesh": 0}),
        // −90° about x: (x, y, z) → (x, z, −y); the quaternion (x, y, z, w).
        Up::Z => {
            let half = std::f32::consts::FRAC_1_SQRT_2;
            json!({"mesh": 0, "rotation": [-half, 0.0, 0.0, half]})
        }
    }
}

/// The smallest and largest value of each coordinate of `positions` (not empty).
fn mesh_bounds(positions: &[[f32; 3]]) -> ([f32; 3], [f32; 3]) {
    positions
        .iter()
        .fold(([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]), |(lo, hi), p| {
            (
                [0, 1, 2].map(|a| lo[a].min(p[a])),
                [0, 1, 2].map(|a| hi[a].max(p[a])),
            )
        })
}

/// The binary chunk being laid out: its bytes and the buffer views into them.
#[derive(Default)]
struct Binary {
    bytes: Vec<u8>,
    views: Vec<Value>,
}

impl Binary {
    /// Appends `data` as a new buffer view (for `target`, if any), padded with zeros to a multiple of 4
    /// bytes so that every view starts aligned; returns the view's index.
    fn view(&mut self, data: &[u8], target: Option<u32>) -> usize {
        let mut view = json!({"buffer": 0, "byteOffset": self.bytes.len(), "byteLength": data.len()});
        if let Some(target) = target {
            view["target"] = json!(target);
        }
        self.bytes.extend_from_slice(data);
        self.bytes.resize(self.bytes.len().next_multiple_of(4), 0);
        self.views.push(view);
        self.views.len() - 1
    }
}

/// The GLB container: the 12-byte header, the JSON chunk (padded with spaces to 4 bytes) and the binary
/// chunk (already a multiple of 4 bytes).
fn container(document: &Value, bin: &[u8]) -> Result<Vec<u8>> {
    let mut json = serde_json::to_vec(document).map_err(|e| Error::Invalid(e.to_string()))?;
    json.resize(json.len().next_multiple_of(4), b' ');
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let word = |n: usize| -> Result<[u8; 4]> {
        u32::try_from(n).map(u32::to_le_bytes).map_err(|_| {
            Error::Invalid(format!(
                "the glTF file would be {total} bytes, more than GLB's 4 GiB"
            ))
        })
    };
    let mut bytes = Vec::with_capacity(total);
    for w in [MAGIC.to_le_bytes(), 2u32.to_le_bytes(), word(total)?] {
        bytes.extend_from_slice(&w);
    }
    for (kind, data) in [(JSON_CHUNK, json.as_slice()), (BIN_CHUNK, bin)] {
        bytes.extend_from_slice(&word(data.len())?);
        bytes.extend_from_slice(&kind.to_le_bytes());
        bytes.extend_from_slice(data);
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surfaces::atlas::{bake_atlas, pair_triangles, AtlasLayout};
    use crate::ClosureFn;
    use gltf::image::Source;
    use gltf::mesh::util::ReadIndices;
    use gltf::texture::{MagFilter, MinFilter, WrappingMode};

    /// A unit cube [0, 1]³ as 12 outward triangles.
    fn cube() -> Mesh {
        let vertices = (0..8)
            .map(|c| [(c & 1) as f32, ((c >> 1) & 1) as f32, ((c >> 2) & 1) as f32 - 0.5])
            .collect();
        let quads = [
            [0, 2, 3, 1],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 6, 7, 3],
            [0, 4, 6, 2],
            [1, 3, 7, 5],
        ];
        let triangles = quads
            .iter()
            .flat_map(|&[a, b, c, d]| [[a, b, c], [a, c, d]])
            .collect();
        Mesh::from_triangles(vertices, triangles)
    }

    /// The header and the chunks as the format lays them out: magic, version 2 and the file's length; the
    /// JSON chunk padded with spaces and the binary chunk with zeros to 4 bytes, the buffer's length that
    /// of the binary chunk. Returns the binary chunk's length.
    fn check_container(bytes: &[u8]) -> usize {
        let glb = gltf::binary::Glb::from_slice(bytes).unwrap();
        assert_eq!(&glb.header.magic, b"glTF");
        assert_eq!(glb.header.version, 2);
        assert_eq!(glb.header.length as usize, bytes.len());
        let word = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
        let json_length = word(12);
        assert_eq!(&bytes[16..20], b"JSON");
        assert_eq!(json_length % 4, 0);
        assert_eq!(json_length, glb.json.len());
        let document: Value = serde_json::from_slice(&glb.json).unwrap();
        let text = serde_json::to_vec(&document).unwrap();
        assert!(glb.json[text.len()..].iter().all(|&b| b == b' '));
        let bin_at = 20 + json_length;
        let bin_length = word(bin_at);
        assert_eq!(&bytes[bin_at + 4..bin_at + 8], b"BIN\0");
        assert_eq!(bin_length % 4, 0);
        assert_eq!(bin_at + 8 + bin_length, bytes.len());
        assert_eq!(document["buffers"][0]["byteLength"], json!(bin_length));
        bin_length
    }

    #[test]
    fn a_mesh_reads_back_with_its_positions_normals_indices_and_bounds() {
        let mesh = cube();
        let bytes = glb_bytes(&mesh, None, Up::Y).unwrap();
        check_container(&bytes);
        let gltf = gltf::Gltf::from_slice(&bytes).unwrap();
        let blob = gltf.blob.as_deref().unwrap();
        let primitive = gltf.meshes().next().unwrap().primitives().next().unwrap();
        assert_eq!(primitive.mode(), gltf::mesh::Mode::Triangles);
        let position = primitive.get(&gltf::Semantic::Positions).unwrap();
        assert_eq!(position.count(), 8);
        assert_eq!(position.min().unwrap(), json!([0.0, 0.0, -0.5]));
        assert_eq!(position.max().unwrap(), json!([1.0, 1.0, 0.5]));
        assert_eq!(position.data_type(), gltf::accessor::DataType::F32);
        assert_eq!(
            position.view().unwrap().target(),
            Some(gltf::buffer::Target::ArrayBuffer)
        );
        let indices = primitive.indices().unwrap();
        assert_eq!(
            (indices.count(), indices.data_type()),
            (36, gltf::accessor::DataType::U32)
        );
        assert_eq!(
            indices.view().unwrap().target(),
            Some(gltf::buffer::Target::ElementArrayBuffer)
        );
        let reader = primitive.reader(|_| Some(blob));
        assert_eq!(
            reader.read_positions().unwrap().collect::<Vec<_>>(),
            mesh.vertices
        );
        for (read, normal) in reader.read_normals().unwrap().zip(&mesh.normals) {
            assert!(
                Vec3::from(read).abs_diff_eq(Vec3::from(*normal), 1e-6),
                "{read:?} {normal:?}"
            );
            assert!((Vec3::from(read).length() - 1.0).abs() < 1e-6);
        }
        let Some(ReadIndices::U32(read)) = reader.read_indices() else {
            panic!("u32 indices")
        };
        assert_eq!(read.collect::<Vec<_>>(), mesh.triangles.concat());
        assert!(reader.read_tex_coords(0).is_none());
        let pbr = primitive.material().pbr_metallic_roughness();
        assert_eq!((pbr.metallic_factor(), pbr.roughness_factor()), (0.0, 1.0));
        assert!(pbr.base_color_texture().is_none() && !primitive.material().unlit());
        let node = gltf.nodes().next().unwrap();
        assert_eq!(node.transform().decomposed().1, [0.0, 0.0, 0.0, 1.0]);
        assert_eq!(gltf.images().len() + gltf.extensions_used().count(), 0);
        let e = glb_bytes(&Mesh::default(), None, Up::Y).unwrap_err().to_string();
        assert!(e.contains("no triangles"), "{e}");
    }

    #[test]
    fn a_textured_mesh_has_each_patch_its_uvs_and_the_atlas_as_png() {
        let mesh = cube();
        let patches = pair_triangles(&mesh);
        let pairs = patches.iter().filter(|p| p.second.is_some()).count();
        assert!(pairs >= 4, "{patches:?}");
        let layout = AtlasLayout::new(patches.len(), 4).unwrap();
        let color = ClosureFn::new(3, 3, |p, c| c.copy_from_slice(&[p[0], p[1], p[2] + 0.5]));
        let atlas = bake_atlas(&mesh, patches.clone(), &color, layout).unwrap();
        let bytes = glb_bytes(&mesh, Some(&atlas), Up::Z).unwrap();
        check_container(&bytes);
        let gltf = gltf::Gltf::from_slice(&bytes).unwrap();
        let blob = gltf.blob.as_deref().unwrap();
        let primitive = gltf.meshes().next().unwrap().primitives().next().unwrap();
        let reader = primitive.reader(|_| Some(blob));
        let positions: Vec<[f32; 3]> = reader.read_positions().unwrap().collect();
        let uvs: Vec<[f32; 2]> = reader.read_tex_coords(0).unwrap().into_f32().collect();
        let n = 3 * patches.len() + pairs;
        assert_eq!((positions.len(), uvs.len()), (n, n));
        // The mesh's triangles, each turned to start at its smallest position, in its order of corners.
        let turned = |t: [[f32; 3]; 3]| {
            (0..3)
                .map(|k| [t[k], t[(k + 1) % 3], t[(k + 2) % 3]])
                .fold(t, |a, b| {
                    if b.partial_cmp(&a) == Some(std::cmp::Ordering::Less) {
                        b
                    } else {
                        a
                    }
                })
        };
        let corners = |t: [u32; 3]| t.map(|v| mesh.vertices[v as usize]);
        let mut want: Vec<_> = mesh.triangles.iter().map(|&t| turned(corners(t))).collect();
        let Some(ReadIndices::U32(read)) = reader.read_indices() else {
            panic!("u32 indices")
        };
        let indices: Vec<u32> = read.collect();
        let mut got: Vec<_> = indices
            .chunks_exact(3)
            .map(|t| turned([0, 1, 2].map(|k| positions[t[k] as usize])))
            .collect();
        let order = |a: &[[f32; 3]; 3], b: &[[f32; 3]; 3]| a.partial_cmp(b).unwrap();
        want.sort_by(order);
        got.sort_by(order);
        assert_eq!(got, want);
        // Every vertex at its patch's corner, whose texel holds the color of its position.
        for (k, (p, uv)) in positions.iter().zip(&uvs).enumerate() {
            let (width, height) = atlas.image.dimensions();
            let (x, y) = (uv[0] * width as f32, uv[1] * height as f32);
            let texel = atlas.image.get_pixel(x as u32, y as u32).0;
            let want = [p[0], p[1], p[2] + 0.5].map(|c| (c * 255.0).round() as u8);
            assert_eq!(texel, want, "vertex {k} at {p:?}, {uv:?}");
        }
        let material = primitive.material();
        assert!(material.unlit());
        assert!(gltf.extensions_used().eq(["KHR_materials_unlit"]));
        let pbr = material.pbr_metallic_roughness();
        assert_eq!((pbr.metallic_factor(), pbr.roughness_factor()), (0.0, 1.0));
        let info = pbr.base_color_texture().unwrap();
        assert_eq!(info.tex_coord(), 0);
        let sampler = info.texture().sampler();
        assert_eq!(sampler.mag_filter(), Some(MagFilter::Linear));
        assert_eq!(sampler.min_filter(), Some(MinFilter::Linear));
        assert_eq!(sampler.wrap_s(), WrappingMode::ClampToEdge);
        assert_eq!(sampler.wrap_t(), WrappingMode::ClampToEdge);
        let Source::View { view, mime_type } = info.texture().source().source() else {
            panic!("an embedded image")
        };
        assert_eq!(mime_type, "image/png");
        let png = &blob[view.offset()..view.offset() + view.length()];
        let image = image::load_from_memory_with_format(png, ImageFormat::Png)
            .unwrap()
            .to_rgb8();
        assert_eq!(image, atlas.image);
        // Lego's z up is glTF's y: the node turns (0, 0, 1) to (0, 1, 0).
        let rotation = gltf.nodes().next().unwrap().transform().decomposed().1;
        let turned = glam::Quat::from_array(rotation) * Vec3::Z;
        assert!(turned.abs_diff_eq(Vec3::Y, 1e-6), "{turned}");
    }
}
