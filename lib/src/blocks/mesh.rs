//! `nerfjit mesh`: the marching-cubes mesh of a script's scalar function, as PLY, OBJ, STL or glTF binary,
//! with optional colors from a color function (the vertices' in PLY and OBJ, a texture atlas in glTF) and an
//! optional turntable GIF of the mesh.

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::Vec3;
use nerfjit_dsl::{Program, Type};
use nerfjit_jit::KernelCache;
use nerfjit_runtime::surfaces::atlas::{bake_atlas, pair_triangles, Atlas, AtlasLayout, DEFAULT_SIDE};
use nerfjit_runtime::surfaces::glb::write_glb;
use nerfjit_runtime::surfaces::marching::{extract_slab, join, Fields, Part, Pruning, Slab};
use nerfjit_runtime::surfaces::raster::render_mesh;
use nerfjit_runtime::surfaces::regions::Specialize;
use nerfjit_runtime::{chamfer_report, mean_center, read_points, BatchFn, Mesh, PointFrame, Up};

use crate::failure::{Failure, Result};
use crate::settings::block::Block;
use crate::settings::camera::turntable;
use crate::settings::primitives::CallArgs;
use crate::settings::typed::typed_settings;
use nerfjit_field::{check_signature, Compiler, JitFn, Kind, Specializer};

/// What to extract and where to write it.
pub struct MeshArgs<'a> {
    /// The function whose level set is meshed (`fn f(p: vec3) -> f32`).
    pub function: &'a str,
    /// Grid cells per axis.
    pub resolution: usize,
    /// The grid's corners.
    pub bounds: ([f32; 3], [f32; 3]),
    /// The level (0 for an SDF's surface).
    pub level: f32,
    /// `.ply`, `.obj`, `.stl` or `.glb`.
    pub out: &'a Path,
    /// A color function (`fn(p: vec3) -> vec3`, or `fn(p: vec3, d: vec3) -> vec3` seen from outside along
    /// the normal): the vertices' colors of PLY and OBJ files, a glTF file's texture.
    pub color: Option<&'a str>,
    /// Texels along a side of each triangle's patch of a glTF file's texture (see
    /// [`nerfjit_runtime::surfaces::atlas`]); `None` for the largest patches of at most 8 texels that keep
    /// the texture within 4096² texels.
    pub texels: Option<usize>,
    /// A turntable GIF of the mesh, if wanted.
    pub gif: Option<&'a Path>,
    /// The turntable's axis: the scene's up direction.
    pub up: Up,
    /// Evaluate the function only in the blocks of cells where its interval bounds may cross the level
    /// (the same mesh, fewer evaluations); otherwise at every grid point.
    pub prune: bool,
    /// The frame the function was fitted to a point cloud in, when that cloud was scaled into the unit
    /// sphere: the mesh is written in the cloud's own units (the grid's bounds are in the frame's).
    pub frame: Option<PointFrame>,
}

/// Parses `--bounds`: `r` for [−r, r]³, or six numbers `x0,y0,z0,x1,y1,z1`.
pub fn parse_bounds(text: &str) -> std::result::Result<([f32; 3], [f32; 3]), String> {
    let numbers: Vec<f32> = text
        .split(',')
        .map(|x| {
            x.trim()
                .parse::<f32>()
                .map_err(|e| format!("bad number '{x}' in --bounds: {e}"))
        })
        .collect::<std::result::Result<_, _>>()?;
    match numbers[..] {
        [r] if r > 0.0 => Ok(([-r; 3], [r; 3])),
        [x0, y0, z0, x1, y1, z1] if x0 < x1 && y0 < y1 && z0 < z1 => Ok(([x0, y0, z0], [x1, y1, z1])),
        _ => Err(
            "--bounds takes r > 0 (for [-r, r]³) or x0,y0,z0,x1,y1,z1 with each low below its high".into(),
        ),
    }
}

/// `nerfjit mesh`: meshes `args.function` of a script (with the params' initial values) or of a training
/// checkpoint (with the trained ones).
pub fn run(source: &str, args: &MeshArgs) -> Result<String> {
    let (program, params) = crate::checkpoint::load_source(source)?;
    let folder = Path::new(source).parent().and_then(|p| p.to_str()).unwrap_or("");
    let frame = crate::blocks::train_sdf::fitted_frame(&program, folder)?;
    let args = &MeshArgs { frame, ..*args };
    let meshed = extract_and_write(&program, &params, args, &KernelCache::new())?;
    Ok(meshed.map(|(_, summary)| summary).unwrap_or_default())
}

/// Extracts the mesh with `params` (compiling through `cache`), writes it (and the GIF); returns it and a
/// summary line. In an MPI job every rank meshes its slab of the grid's z-layers and rank 0 joins them
/// (the mesh of one process, bit for bit), writes the files and returns the mesh; the other ranks return
/// `None`.
pub fn extract_and_write(
    program: &Program,
    params: &[f32],
    args: &MeshArgs,
    cache: &KernelCache,
) -> Result<Option<(Mesh, String)>> {
    let ext = args.out.extension().and_then(|e| e.to_str()).unwrap_or("");
    if !matches!(ext, "ply" | "obj" | "stl" | "glb") {
        return Err(Failure::Message(format!(
            "cannot write '{}': use a .ply, .obj, .stl or .glb file",
            args.out.display()
        )));
    }
    if args.texels.is_some() && (ext != "glb" || args.color.is_none()) {
        return Err(Failure::Message(format!(
            "cannot texture '{}': only a .glb file with colors (--color) has a texture to size",
            args.out.display()
        )));
    }
    if ext == "stl" && args.color.is_some() {
        return Err(Failure::Message(format!(
            "cannot write colors into '{}': STL has no vertex colors; use a .ply or .obj file",
            args.out.display()
        )));
    }
    for path in std::iter::once(args.out).chain(args.gif) {
        let folder = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        if !folder.is_dir() {
            return Err(Failure::Message(format!(
                "cannot write '{}': folder '{}' does not exist",
                path.display(),
                folder.display()
            )));
        }
    }
    let compiler = Compiler {
        program,
        params,
        cache,
    };
    let t = Instant::now();
    let kernels = MeshKernels::compile(&compiler, args.function, args.prune)?;
    let compile_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let specializer = kernels.specializer(&compiler, args.function)?;
    let Some((mut mesh, pruning)) = extract_on_ranks(kernels.fields(specializer.as_ref()), args)? else {
        return Ok(None);
    };
    let extract_s = t.elapsed().as_secs_f64();
    let mut texture = None;
    if ext == "glb" {
        // glTF's front faces are counter-clockwise seen from outside.
        mesh.face_outwards();
    }
    match args.color {
        Some(color) if ext == "glb" && !mesh.triangles.is_empty() => {
            let t = Instant::now();
            texture = Some((
                texture_atlas(&compiler, color, &mesh, args.texels)?,
                t.elapsed().as_secs_f64(),
            ));
        }
        Some(color) => mesh.colors = vertex_colors(&compiler, color, &mesh)?,
        None => {}
    }
    if let Some(frame) = &args.frame {
        // A similarity: the normals keep their directions.
        for v in &mut mesh.vertices {
            *v = frame.to_input(*v);
        }
    }
    match ext {
        "ply" => mesh.write_ply(args.out)?,
        "obj" => mesh.write_obj(args.out)?,
        "glb" => write_glb(&mesh, texture.as_ref().map(|(atlas, _)| atlas), args.up, args.out)?,
        _ => mesh.write_stl(args.out)?,
    }
    if let Some(gif) = args.gif {
        // Frame the mesh itself (the grid may be much larger), lit from above the camera's left shoulder.
        let frames = turntable(mesh.bounds().unwrap_or(args.bounds), args.up)?
            .iter()
            .map(|camera| {
                let light = camera.rotation() * Vec3::new(0.4, 0.6, -1.0);
                render_mesh(
                    camera,
                    256,
                    256,
                    &mesh,
                    light,
                    [0.85, 0.8, 0.7],
                    [0.1, 0.11, 0.14],
                )
            })
            .collect::<nerfjit_runtime::Result<Vec<_>>>()?;
        crate::frame_files::write_images(gif, frames, 50)?;
    }
    let summary = format!(
        "meshed '{}' at level {} on {}³ cells in {extract_s:.3} s (JIT compile {compile_s:.3} s; {}): {} vertices{}, {} triangles, {} → {}",
        args.function,
        args.level,
        args.resolution,
        pruning_summary(pruning.as_ref(), args.prune),
        mesh.vertices.len(),
        match (&texture, args.color) {
            (Some((atlas, seconds)), Some(c)) => format!(
                " textured by '{c}' in {seconds:.3} s ({}×{} texels: {} patches of {}², {:.1}% of the triangles in pairs)",
                atlas.layout.width(),
                atlas.layout.height(),
                atlas.patches.len(),
                atlas.layout.patch,
                200.0 * atlas.patches.iter().filter(|p| p.second.is_some()).count() as f64
                    / mesh.triangles.len() as f64
            ),
            (None, Some(c)) => format!(" colored by '{c}'"),
            _ => String::new(),
        },
        mesh.triangles.len(),
        if mesh.is_closed() { "closed" } else { "open (the surface leaves the grid or is not closed)" },
        args.out.display()
    );
    Ok(Some((mesh, summary)))
}

/// The mesh `args` asks for, of `fields`, with what pruning did (its evaluations summed over the ranks): on
/// rank 0 of an MPI job from every rank's slab of the grid, `None` on the other ranks.
fn extract_on_ranks(fields: Fields, args: &MeshArgs) -> Result<Option<(Mesh, Option<Pruning>)>> {
    let cluster = crate::cluster::current();
    let part = Part {
        index: cluster.rank(),
        of: cluster.size(),
    };
    let mut mine = None;
    // Each rank's item: its points evaluated, then its slab.
    let slabs = crate::cluster::split(part.of, |_| {
        let (slab, pruning) = extract_slab(fields, args.bounds, args.resolution, args.level, part)?;
        let evaluated = pruning.map_or(0, |p| p.points_evaluated);
        mine = pruning;
        let mut bytes = (evaluated as u64).to_le_bytes().to_vec();
        bytes.extend(slab.to_bytes());
        nerfjit_runtime::Result::Ok(bytes)
    })
    .map_err(Failure::Message)?;
    let Some(slabs) = slabs else {
        return Ok(None);
    };
    let mut evaluated = 0;
    let mut parts = Vec::with_capacity(slabs.len());
    for bytes in &slabs {
        let (count, slab) = bytes.split_at(8.min(bytes.len()));
        evaluated += count.try_into().map_or(0, u64::from_le_bytes) as usize;
        parts.push(Slab::from_bytes(slab)?);
    }
    let pruning = mine.map(|p| Pruning {
        points_evaluated: evaluated,
        ..p
    });
    Ok(Some((join(parts)?, pruning)))
}

/// The kernels meshing a function needs.
pub struct MeshKernels {
    /// Its value.
    pub value: JitFn,
    /// Its value and gradient (for the normals).
    pub gradient: JitFn,
    /// Its interval bounds over boxes, when asked for and informative (see [`Compiler::bounds`]).
    pub bounds: Option<JitFn>,
}

impl MeshKernels {
    /// Compiles the kernels of `function` (`fn(p: vec3) -> f32`) on separate threads; the bounds only if
    /// `prune`.
    pub fn compile(compiler: &Compiler, function: &str, prune: bool) -> Result<MeshKernels> {
        let vec3 = [Type::Vec(3)];
        let ((value, gradient), bounds) = rayon::join(
            || {
                rayon::join(
                    || compiler.function(function, &vec3, &Type::F32, Kind::Value),
                    || compiler.function(function, &vec3, &Type::F32, Kind::Gradient),
                )
            },
            || match prune {
                true => compiler.bounds(function, &vec3, &Type::F32),
                false => Ok(None),
            },
        );
        Ok(MeshKernels {
            value: value?,
            gradient: gradient?,
            bounds: bounds?,
        })
    }

    /// The specializer of `function` over boxes of space, when its bounds are compiled.
    fn specializer(&self, compiler: &Compiler, function: &str) -> Result<Option<Specializer>> {
        match &self.bounds {
            Some(_) => Ok(Some(compiler.specializer(
                function,
                &[Type::Vec(3)],
                &Type::F32,
            )?)),
            None => Ok(None),
        }
    }

    /// What marching cubes evaluates: the value, the gradient, the bounds and `specializer` where it pays.
    fn fields<'a>(&'a self, specializer: Option<&'a Specializer>) -> Fields<'a> {
        Fields {
            field: &self.value,
            gradient: Some(&self.gradient),
            bounds_of: self.bounds.as_ref().map(|b| b as &dyn BatchFn),
            specialize: specializer.filter(|s| s.pays()).map(|s| s as &dyn Specialize),
        }
    }
}

/// The mesh of the level `level` of `function` (`fn(p: vec3) -> f32`) with `params`, on `resolution`³ cells of
/// `bounds`, in this process alone and kept in memory (for callers such as the Python package): the kernels
/// compiled through `cache`, the grid pruned by interval bounds where they are informative.
pub fn level_set(
    program: &Program,
    params: &[f32],
    function: &str,
    (bounds, resolution, level): (([f32; 3], [f32; 3]), usize, f32),
    cache: &KernelCache,
) -> Result<Mesh> {
    let compiler = Compiler {
        program,
        params,
        cache,
    };
    let kernels = MeshKernels::compile(&compiler, function, true)?;
    let specializer = kernels.specializer(&compiler, function)?;
    let whole = Part { index: 0, of: 1 };
    let (slab, _) = extract_slab(
        kernels.fields(specializer.as_ref()),
        bounds,
        resolution,
        level,
        whole,
    )?;
    Ok(join(vec![slab])?)
}

/// The kernel of a color function: `fn(p: vec3) -> vec3`, or `fn(p: vec3, d: vec3) -> vec3` (a radiance
/// field's color).
fn color_function(compiler: &Compiler, function: &str) -> Result<JitFn> {
    let vec3 = Type::Vec(3);
    let forms = [vec![vec3.clone()], vec![vec3.clone(), vec3.clone()]];
    check_signature(compiler.program, function, &[&forms[0], &forms[1]], &vec3)?;
    let inputs: Vec<Type> = compiler
        .program
        .signature(function)
        .map(|sig| sig.inputs.iter().map(|(_, t)| t.clone()).collect())
        .unwrap_or_default();
    Ok(compiler.function(function, &inputs, &vec3, Kind::Value)?)
}

/// The texture of `mesh` (its triangles facing outwards) from the color `function` (see [`color_function`];
/// a radiance field seen along the inward normal): neighbouring triangles paired, each pair or triangle
/// alone a patch of `texels`² texels, or by default the largest patches of at most 8 texels that keep it
/// within 4096² texels.
fn texture_atlas(compiler: &Compiler, function: &str, mesh: &Mesh, texels: Option<usize>) -> Result<Atlas> {
    let f = color_function(compiler, function)?;
    let patches = pair_triangles(mesh);
    let layout = match texels {
        Some(texels) => AtlasLayout::new(patches.len(), texels)?,
        None => AtlasLayout::fitting(patches.len(), DEFAULT_SIDE).ok_or_else(|| {
            Failure::Message(format!(
                "the texture of {} triangles would be more than {DEFAULT_SIDE} texels a side: lower --res, or \
                 ask for --texels 2 (up to {} texels a side)",
                mesh.triangles.len(),
                nerfjit_runtime::surfaces::atlas::MAX_SIDE
            ))
        })?,
    };
    Ok(bake_atlas(mesh, patches, &f, layout)?)
}

/// The colors of the mesh's vertices from `function` (see [`color_function`]), clamped to [0, 1] (NaN as 0);
/// a radiance field seen along the inward normal, as a camera outside the surface sees it.
fn vertex_colors(compiler: &Compiler, function: &str, mesh: &Mesh) -> Result<Vec<[f32; 3]>> {
    let f = color_function(compiler, function)?;
    let with_direction = f.n_inputs() == 6;
    // The mesh's normals face increasing values: outwards around an SDF's surface (positive volume), inwards
    // around a density's (negative volume).
    let inward = if mesh.volume() >= 0.0 { -1.0 } else { 1.0 };
    let n = mesh.vertices.len();
    let mut columns: Vec<Vec<f32>> = (0..3)
        .map(|a| mesh.vertices.iter().map(|p| p[a]).collect())
        .collect();
    if with_direction {
        columns.extend((0..3).map(|a| mesh.normals.iter().map(|normal| inward * normal[a]).collect()));
    }
    let ins: Vec<&[f32]> = columns.iter().map(Vec::as_slice).collect();
    let rgb = f.eval_columns(&ins);
    let unit = |v: f32| if v.is_finite() { v.clamp(0.0, 1.0) } else { 0.0 };
    Ok((0..n).map(|k| [0, 1, 2].map(|c| unit(rgb[c][k]))).collect())
}

/// What interval pruning did, for the summary line.
fn pruning_summary(pruning: Option<&Pruning>, asked: bool) -> String {
    match pruning {
        Some(p) => format!(
            "field evaluations {:.1}% of the grid's points: interval bounds of {} boxes left {} of {} blocks near the surface{}",
            100.0 * p.points_evaluated as f64 / p.points as f64,
            p.boxes,
            p.blocks_evaluated,
            p.blocks,
            match p.regions {
                0 => String::new(),
                regions => format!(
                    "; {} of {regions} regions evaluated with the function restricted to them",
                    p.regions_specialized
                ),
            }
        ),
        None if asked => "every grid point evaluated: interval arithmetic bounds nothing through dense layers or grid reads".into(),
        None => "every grid point evaluated".into(),
    }
}

/// A checked `mesh { ... }` block: meshes a function with the params as they are at that point of the
/// script (after training), and optionally compares the mesh with a point cloud.
pub struct MeshPlan {
    function: String,
    resolution: usize,
    bounds: ([f32; 3], [f32; 3]),
    level: f32,
    out: PathBuf,
    gif: Option<PathBuf>,
    up: Up,
    compare: Option<(PathBuf, Option<String>)>,
}

typed_settings! {
    /// The settings of a `mesh` block, as read.
    pub struct MeshSettings for crate::settings::schema::MESH {
        function: function,
        resolution: whole,
        bounds: number,
        level: number,
        out: required_output,
        gif: output,
        up: choice,
        compare: value,
    }
}

impl MeshPlan {
    /// Reads and checks a `mesh` block.
    pub fn new(mut b: Block) -> Result<MeshPlan> {
        let s = MeshSettings::read(&mut b)?;
        let (function, resolution) = (s.function, s.resolution as usize);
        let (bound, level) = (s.bounds as f32, s.level as f32);
        let (out, gif) = (s.out, s.gif);
        let up = s.up.as_deref().and_then(Up::named).unwrap_or(Up::Y);
        let compare = match &s.compare {
            None => None,
            Some(v) => {
                let a = CallArgs::new(v, &["file", "key"]).map_err(|d| b.error(d))?;
                let file = a.string("file").map_err(|d| b.error(d))?;
                let key = a
                    .raw("key")
                    .map(|k| k.string().map(str::to_string))
                    .transpose()
                    .map_err(|d| b.error(d))?;
                Some((
                    crate::training::data_source::data_path(&file, b.script_dir()),
                    key,
                ))
            }
        };
        b.finish()?;
        Ok(MeshPlan {
            function,
            resolution,
            bounds: ([-bound; 3], [bound; 3]),
            level,
            out,
            gif,
            up,
            compare,
        })
    }

    /// Meshes (compiling through `cache`), writes and (when asked) compares; returns a summary. `frame`:
    /// the frame of the script's point-cloud fit when it scaled the cloud into the unit sphere; the mesh
    /// is then written and compared in the cloud's units.
    pub fn run(
        &self,
        program: &Program,
        params: &[f32],
        cache: &KernelCache,
        frame: Option<PointFrame>,
    ) -> Result<String> {
        let args = MeshArgs {
            function: &self.function,
            resolution: self.resolution,
            bounds: self.bounds,
            level: self.level,
            out: &self.out,
            gif: self.gif.as_deref(),
            up: self.up,
            prune: true,
            color: None,
            texels: None,
            frame,
        };
        let Some((mesh, mut summary)) = extract_and_write(program, params, &args, cache)? else {
            return Ok(String::new());
        };
        if let Some((file, key)) = &self.compare {
            // The points as the mesh is written: in their own units after a normalized fit, mean-centered
            // (as the fit saw them) otherwise.
            let points = read_points(file, key.as_deref())?;
            let points = match frame {
                Some(_) => points,
                None => mean_center(&points).0,
            };
            let r = chamfer_report(&points, &mesh)?;
            summary += &format!(
                "\ndistance from the {} points to the mesh: mean {:.5} ({:.3}% of the {:.3} bounding-box diagonal), max {:.5}; \
                 from the mesh to the points: mean {:.5} ({:.3}%)",
                points.len(),
                r.mean_points_to_mesh,
                100.0 * r.mean_points_to_mesh / r.bbox_diagonal,
                r.bbox_diagonal,
                r.max_points_to_mesh,
                r.mean_mesh_to_points,
                100.0 * r.mean_mesh_to_points / r.bbox_diagonal
            );
        }
        Ok(summary)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nerfjit_runtime::surfaces::marching::extract_pruned;
    use nerfjit_runtime::Camera;

    #[test]
    fn turntables_circle_their_up_axis_above_the_center() {
        let bounds = ([-1.0, -2.0, 0.0], [1.0, 2.0, 1.0]);
        for up in [Up::Y, Up::Z] {
            let cameras = turntable(bounds, up).unwrap();
            assert_eq!(cameras.len(), 36);
            let height = |c: &Camera| c.position().dot(up.vector());
            let center = Vec3::new(0.0, 0.0, 0.5);
            for c in &cameras {
                // Every eye at the same height above the center, looking at it, upright.
                assert!((height(c) - height(&cameras[0])).abs() < 1e-5);
                assert!(height(c) > center.dot(up.vector()));
                let forward = c.rotation() * Vec3::Z;
                assert!(forward.dot((center - c.position()).normalize()) > 0.9999);
                assert!((c.rotation() * Vec3::Y).dot(up.vector()) > 0.0);
            }
        }
    }

    /// Meshes the `sdf` of `script` over [−1, 1]³ at `resolution`, pruned, with its regions restricted when
    /// `restrict`; also says whether restricting it pays.
    fn mesh_of(script: &str, resolution: usize, restrict: bool) -> (Mesh, Pruning, bool) {
        let program = nerfjit_dsl::compile("city.sdf", script).unwrap();
        let cache = KernelCache::new();
        let compiler = Compiler {
            program: &program,
            params: &program.param_values,
            cache: &cache,
        };
        let kernels = MeshKernels::compile(&compiler, "sdf", true).unwrap();
        let bounds_of = kernels.bounds.expect("boxes have bounds");
        let specializer = compiler.specializer("sdf", &[Type::Vec(3)], &Type::F32).unwrap();
        let specialize = restrict.then_some(&specializer as &dyn Specialize);
        let (mesh, pruning) = extract_pruned(
            &kernels.value,
            Some(&kernels.gradient),
            &bounds_of,
            specialize,
            ([-1.0; 3], [1.0; 3]),
            resolution,
            0.0,
        )
        .unwrap();
        (mesh, pruning, specializer.pays())
    }

    fn city() -> String {
        crate::commands::import::convert(&crate::city_model::city(), "city.vm").unwrap()
    }

    /// The generated city of `nerfjit bench large`, meshed with and without its regions' restrictions: the
    /// same vertices and triangles (normals to rounding), and most regions near the surface restricted.
    #[test]
    fn restricted_regions_give_the_same_mesh_of_a_large_model() {
        let (plain, _, _) = mesh_of(&city(), 96, false);
        let (restricted, pruning, pays) = mesh_of(&city(), 96, true);
        assert!(pays);
        assert!(plain.triangles.len() > 10_000);
        assert_eq!(restricted.vertices, plain.vertices);
        assert_eq!(restricted.triangles, plain.triangles);
        for (a, b) in restricted.normals.iter().zip(&plain.normals) {
            assert!(Vec3::from(*a).abs_diff_eq(Vec3::from(*b), 1e-4), "{a:?} vs {b:?}");
        }
        assert!(pruning.regions_specialized > pruning.regions / 10, "{pruning:?}");
    }

    /// Restrictions with an op a tape does not take (`tanh`, which kernels approximate) give no fields: every
    /// region is evaluated by the full kernels. (`nerfjit mesh` does not restrict such a function at all:
    /// see [`nerfjit_field::Specializer::pays`].)
    #[test]
    fn restrictions_with_approximated_ops_leave_the_full_kernels() {
        let script = city().replacen("fn sdf(", "fn city(", 1)
            + "\nfn sdf(p: vec3) -> f32 = city(p) + 0.001 * tanh(p.x)\n";
        let (mesh, pruning, pays) = mesh_of(&script, 48, true);
        assert!(!pays);
        assert!(!mesh.triangles.is_empty());
        assert!(pruning.regions > 0);
        assert_eq!(pruning.regions_specialized, 0, "{pruning:?}");
    }
}
