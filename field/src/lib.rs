//! Compiled script functions as the runtime sees them: [`BatchFn`]s, [`BatchVjp`]s and volume models
//! backed by JIT kernels. This adapter is the one place where `nerfjit-jit` and `nerfjit-runtime` meet (neither
//! depends on the other): the library's blocks use it, and so can the runtime's tests, to train JIT fields.

use std::sync::{Arc, OnceLock};

mod splat_shader;
pub use splat_shader::{splat_shader, JitSplatShader, SPLAT_SHADER_SOURCE};

use nerfjit_dsl::ir::Op;
use nerfjit_dsl::simplify::Simplifier;
use nerfjit_dsl::{kernel_graphs, Lowered, Program, Report, Signature, Type};
use nerfjit_jit::{fused_products, Kernel, KernelCache, Marcher, Options, Passes, Precision, Stop, Tape};
use nerfjit_runtime::field::{MarchRays, RayMarcher};
use nerfjit_runtime::surfaces::regions::{Specialize, Specialized};
use nerfjit_runtime::volume::composite::Mode;
use nerfjit_runtime::{
    BatchFn, BatchVjp, CoarsePass, GridSpace, HeldScatters, KeptPasses, OccupancyGrid, TrainableModel,
    VolumeModel,
};

/// Why a script function could not be made a field: errors in the script, or anything else (a missing
/// function, a wrong signature, a kernel that did not compile, a render that failed).
#[derive(Debug)]
pub enum FieldError {
    /// Errors in the script, with its sources.
    Script(Report),
    /// Anything else.
    Message(String),
}

impl std::fmt::Display for FieldError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FieldError::Script(report) => write!(f, "{report}"),
            FieldError::Message(m) => write!(f, "{m}"),
        }
    }
}

impl std::error::Error for FieldError {}

impl From<Report> for FieldError {
    fn from(r: Report) -> Self {
        FieldError::Script(r)
    }
}

impl From<nerfjit_jit::JitError> for FieldError {
    fn from(e: nerfjit_jit::JitError) -> Self {
        FieldError::Message(e.to_string())
    }
}

impl From<nerfjit_runtime::Error> for FieldError {
    fn from(e: nerfjit_runtime::Error) -> Self {
        FieldError::Message(e.to_string())
    }
}

/// The adapter's results.
pub type Result<T> = std::result::Result<T, FieldError>;

/// A JIT kernel with the params it reads: evaluates per-point outputs (no reductions); an SDF also carries
/// its fused sphere tracer.
pub struct JitFn {
    kernel: Arc<Kernel>,
    marcher: Option<Marcher>,
    params: Arc<[f32]>,
}

impl JitFn {
    /// The number of IR nodes its kernel computes.
    pub fn nodes(&self) -> usize {
        self.kernel.stats().nodes
    }
}

impl RayMarcher for JitFn {
    fn march(&self, n: usize, rays: &MarchRays, eps: f32, max_steps: u32, t: &mut [f32], hit: &mut [f32]) {
        let marcher = self
            .marcher
            .as_ref()
            .expect("as_marcher returns Some only with a marcher");
        marcher.march(n, rays, &self.params, Stop { eps, max_steps }, t, hit);
    }
}

impl BatchFn for JitFn {
    fn n_inputs(&self) -> usize {
        self.kernel.n_inputs
    }

    fn n_outputs(&self) -> usize {
        self.kernel.n_outputs
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        self.kernel.eval(n, inputs, outputs, &self.params, &mut []);
    }

    fn as_marcher(&self) -> Option<&dyn RayMarcher> {
        self.marcher.as_ref().map(|_| self as &dyn RayMarcher)
    }
}

/// What to compile of a function.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Kind {
    /// Its value.
    Value,
    /// Its value, and a fused sphere tracer (for an SDF).
    Sdf,
    /// Its value and the gradient of each output with respect to the inputs.
    Gradient,
}

/// Compiles functions of a program, bound to param values, through a kernel cache.
pub struct Compiler<'a> {
    /// The program.
    pub program: &'a Program,
    /// The param values the kernels read.
    pub params: &'a [f32],
    /// Where compiled kernels are kept.
    pub cache: &'a KernelCache,
}

impl Compiler<'_> {
    /// Compiles function `name` after checking its signature against `inputs` → `output`.
    pub fn function(&self, name: &str, inputs: &[Type], output: &Type, kind: Kind) -> Result<JitFn> {
        self.compile(&self.lowered(name, inputs, output)?, kind)
    }

    /// Function `name` lowered to IR after checking its signature against `inputs` → `output`.
    pub fn lowered(&self, name: &str, inputs: &[Type], output: &Type) -> Result<Lowered> {
        check_signature(self.program, name, &[inputs], output)?;
        Ok(self.program.lower(name)?)
    }

    /// Compiles a lowered function of the program (its params are the program's).
    pub fn compile(&self, lowered: &Lowered, kind: Kind) -> Result<JitFn> {
        let graph = match kind {
            Kind::Value | Kind::Sdf => kernel_graphs::value(lowered),
            Kind::Gradient => kernel_graphs::with_gradient(lowered),
        };
        // The fused sphere tracer takes elementwise SDFs; one with dense layers is traced through its
        // tiled kernel, a batch of ray positions per step.
        let marcher = match kind {
            Kind::Sdf if !graph.needs_tiles() => Some(Marcher::compile(&graph)?),
            _ => None,
        };
        Ok(JitFn {
            kernel: self.cache.get(&graph, Options::default())?,
            marcher,
            params: self.params.into(),
        })
    }
}

impl Compiler<'_> {
    /// Compiles bounds of function `name` over boxes ([`kernel_graphs::interval`]), or gives `None` where interval
    /// arithmetic bounds nothing (every bound constant: a field of dense layers or grid reads).
    pub fn bounds(&self, name: &str, inputs: &[Type], output: &Type) -> Result<Option<JitFn>> {
        self.compile_bounds(&self.lowered(name, inputs, output)?)
    }

    /// [`Compiler::bounds`] of a lowered function of the program.
    pub fn compile_bounds(&self, lowered: &Lowered) -> Result<Option<JitFn>> {
        let graph = kernel_graphs::interval(lowered);
        let constant = graph.outputs.iter().all(|&v| graph.const_value(v).is_some());
        // Bounds only speed things up: bounds too large to compile are not worth their compile time.
        if constant || graph.len() > nerfjit_jit::MAX_KERNEL_NODES {
            return Ok(None);
        }
        Ok(Some(JitFn {
            kernel: self.cache.get(&graph, Options::default())?,
            marcher: None,
            params: self.params.into(),
        }))
    }
}

impl Compiler<'_> {
    /// Function `name`, to be restricted to boxes of inputs (see [`Specializer`]).
    pub fn specializer(&self, name: &str, inputs: &[Type], output: &Type) -> Result<Specializer> {
        check_signature(self.program, name, &[inputs], output)?;
        let lowered = self.program.lower(name)?;
        let graph = kernel_graphs::value(&lowered);
        let fused = fused_products(&graph);
        let function = Arc::new(Function {
            nodes: graph.len(),
            signature: lowered.signature,
            params_f64: self.params.iter().map(|&x| f64::from(x)).collect(),
            params: self.params.to_vec(),
        });
        Ok(Specializer::new(graph, fused, function))
    }
}

/// What every restriction of a function shares.
struct Function {
    /// Nodes of the function's value graph.
    nodes: usize,
    signature: Signature,
    params_f64: Vec<f64>,
    params: Vec<f32>,
}

/// A function restricted to a box of inputs ([`nerfjit_dsl::simplify`]: the `min`/`max` branches that the
/// box's bounds decide dropped), whose value and gradient run as [`Tape`]s: a region of a mesh evaluates a
/// few thousand points, far less time than compiling a kernel would take. Restrictions with ops a tape does
/// not take (those the kernels approximate by polynomials, such as `exp`) give no fields.
pub struct Specializer {
    /// The restricted graph.
    graph: Arc<nerfjit_dsl::ir::Graph>,
    /// Which of its products the function's kernel fuses into FMAs (the tape rounds the same way).
    fused: Arc<[bool]>,
    /// Its simplifier, made when it is restricted further.
    simplifier: Arc<OnceLock<Simplifier>>,
    function: Arc<Function>,
}

/// Restrictions of graphs this small are not restricted further: there is little left to drop, and
/// bounding the graph costs more than evaluating it on a region's points.
const SPECIALIZE_SMALL_NODES: usize = 64;

/// The fewest nodes (in percent) a restricted graph must drop to be worth evaluating on its own.
const SPECIALIZE_MIN_GAIN_PERCENT: usize = 25;

/// Functions of fewer nodes are meshed without restrictions: restricting the 358-node scene of W7 to the
/// regions of a 512³ mesh took longer (0.31 s) than evaluating it whole (0.23 s); the 6,425-node city of
/// `nerfjit bench large` meshes in 60% of the time.
const SPECIALIZE_MIN_NODES: usize = 1024;

impl Specializer {
    /// Whether restricting the function pays: it is large, has branches to decide, and runs as a tape (a
    /// neural field's dense layers do not: restricting it would only cost time).
    pub fn pays(&self) -> bool {
        let branches = self
            .graph
            .ops()
            .iter()
            .any(|op| matches!(op, Op::Min(..) | Op::Max(..) | Op::Select(..)));
        self.graph.len() >= SPECIALIZE_MIN_NODES
            && branches
            && Tape::with_fusion(&self.graph, &self.function.params, &self.fused).is_ok()
    }

    fn new(graph: nerfjit_dsl::ir::Graph, fused: Vec<bool>, function: Arc<Function>) -> Specializer {
        Specializer {
            graph: Arc::new(graph),
            fused: fused.into(),
            simplifier: Arc::default(),
            function,
        }
    }
}

impl Specialize for Specializer {
    fn restrict(&self, lo: [f32; 3], hi: [f32; 3]) -> nerfjit_runtime::Result<Box<dyn Specialize>> {
        if self.graph.len() <= SPECIALIZE_SMALL_NODES {
            return Ok(Box::new(Specializer {
                graph: self.graph.clone(),
                fused: self.fused.clone(),
                simplifier: self.simplifier.clone(),
                function: self.function.clone(),
            }));
        }
        let simplifier = self.simplifier.get_or_init(|| Simplifier::new(&self.graph));
        let simplified =
            simplifier.simplify(&lo.map(f64::from), &hi.map(f64::from), &self.function.params_f64);
        let fused = simplified
            .origin
            .iter()
            .map(|o| self.fused[o.0 as usize])
            .collect();
        Ok(Box::new(Specializer::new(
            simplified.graph,
            fused,
            self.function.clone(),
        )))
    }

    fn fields(&self, gradient: bool) -> nerfjit_runtime::Result<Option<Specialized>> {
        let kept = self.graph.len() * 100;
        if kept > self.function.nodes * (100 - SPECIALIZE_MIN_GAIN_PERCENT) {
            return Ok(None);
        }
        let boxed = |tape: Tape| -> Box<dyn BatchFn + Send> { Box::new(TapeFn(tape)) };
        let Ok(field) = Tape::with_fusion(&self.graph, &self.function.params, &self.fused) else {
            return Ok(None);
        };
        let lowered = Lowered {
            signature: self.function.signature.clone(),
            graph: self.graph.as_ref().clone(),
        };
        // The gradient's tape is the derivative of the restricted graph, its terms summed in another
        // order than the full gradient kernel's: normals equal to rounding.
        let gradient = gradient
            .then(|| Tape::new(&kernel_graphs::with_gradient(&lowered), &self.function.params).ok())
            .flatten();
        Ok(Some(Specialized {
            field: boxed(field),
            gradient: gradient.map(boxed),
        }))
    }
}

/// A [`Tape`] as the runtime's [`BatchFn`].
pub struct TapeFn(pub Tape);

impl BatchFn for TapeFn {
    fn n_inputs(&self) -> usize {
        self.0.n_inputs
    }

    fn n_outputs(&self) -> usize {
        self.0.n_outputs()
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        self.0.eval(n, inputs, outputs);
    }
}

/// A kernel bound to a param slice, as the runtime's [`BatchFn`] (per-point outputs only).
pub struct Bound<'a> {
    kernel: &'a Kernel,
    params: &'a [f32],
}

impl BatchFn for Bound<'_> {
    fn n_inputs(&self) -> usize {
        self.kernel.n_inputs
    }

    fn n_outputs(&self) -> usize {
        self.kernel.n_outputs
    }

    fn eval(&self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        self.kernel.eval(n, inputs, outputs, self.params, &mut []);
    }
}

/// A param-gradient kernel bound to a param slice, as the runtime's [`BatchVjp`].
pub struct BoundVjp<'a> {
    kernel: &'a Kernel,
    params: &'a [f32],
    n_outputs: usize,
    /// One gradient per param: the kernel's reductions.
    n_grads: usize,
}

impl BatchVjp for BoundVjp<'_> {
    fn n_inputs(&self) -> usize {
        self.kernel.n_inputs - self.n_outputs
    }

    fn n_outputs(&self) -> usize {
        self.n_outputs
    }

    fn n_params(&self) -> usize {
        self.n_grads
    }

    fn vjp(&self, n: usize, inputs: &[&[f32]], cotangents: &[&[f32]], param_grads: &mut [f32]) {
        let all: Vec<&[f32]> = inputs.iter().chain(cotangents).copied().collect();
        // A kernel that also gives the forward pass's values (for kept passes) writes them here.
        let mut values = vec![vec![0.0; n]; self.kernel.n_outputs];
        let mut values: Vec<&mut [f32]> = values.iter_mut().map(Vec::as_mut_slice).collect();
        self.kernel.eval(n, &all, &mut values, self.params, param_grads);
    }

    fn kept_passes(&self) -> Option<Box<dyn KeptPasses + '_>> {
        let passes = self.kernel.passes(self.params)?;
        Some(Box::new(JitPasses(passes)))
    }
}

/// A kernel's [`Passes`] as the runtime's [`KeptPasses`].
struct JitPasses<'a>(Passes<'a>);

impl KeptPasses for JitPasses<'_> {
    fn forward(&mut self, n: usize, inputs: &[&[f32]], outputs: &mut [&mut [f32]]) {
        self.0.forward(n, inputs, outputs);
    }

    fn backward(&mut self, n: usize, cotangents: &[&[f32]], param_grads: &mut [f32]) {
        self.0.backward(n, cotangents, param_grads);
    }

    fn finish(&mut self, param_grads: &mut [f32]) {
        self.0.finish(param_grads);
    }

    fn bytes_per_point(&self) -> usize {
        self.0.bytes_per_point()
    }

    fn hold_scatters(&mut self) -> bool {
        self.0.hold_scatters()
    }

    fn take_scatters(&mut self) -> Option<Box<dyn HeldScatters + '_>> {
        let held = self.0.take_scatters()?;
        Some(Box::new(JitHeldScatters(held)))
    }
}

/// A kernel's [`nerfjit_jit::HeldScatters`] as the runtime's [`HeldScatters`].
struct JitHeldScatters<'a>(nerfjit_jit::HeldScatters<'a>);

impl HeldScatters for JitHeldScatters<'_> {
    fn parts(&self) -> &[std::ops::Range<usize>] {
        self.0.parts()
    }

    fn add(&self, part: usize, grads: &mut [f32]) {
        self.0.add(part, grads);
    }
}

/// A volume field of a script: `density(p)` or `opacity(p)`, and `color(p)` or `color(p, d)`, compiled
/// together forward (4 outputs) and backward (param gradients, and the forward pass's values: see
/// [`BatchVjp::kept_passes`]).
pub struct VolumeField {
    forward: Arc<Kernel>,
    backward: Arc<Kernel>,
    /// The density (or opacity) alone, for occupancy grids: no color network.
    density: Arc<Kernel>,
    /// Whether the first output is a density or the course's per-sample opacity.
    pub mode: Mode,
}

impl VolumeField {
    /// Finds and compiles the field functions of `program`, their dense products in `products`.
    pub fn compile(program: &Program, cache: &KernelCache, products: Precision) -> Result<VolumeField> {
        Self::compile_prefixed(program, cache, "", products)
    }

    /// Finds and compiles the field functions named with `prefix` (`coarse_density`, `coarse_color`
    /// for the coarse field of hierarchical sampling).
    pub fn compile_prefixed(
        program: &Program,
        cache: &KernelCache,
        prefix: &str,
        products: Precision,
    ) -> Result<VolumeField> {
        let options = Options {
            products,
            ..Options::default()
        };
        let has = |name: &str| program.signature(&format!("{prefix}{name}")).is_some();
        let (first, mode) = match (has("density"), has("opacity")) {
            (true, false) => (format!("{prefix}density"), Mode::Density),
            (false, true) => (format!("{prefix}opacity"), Mode::Opacity),
            (true, true) => {
                return Err(FieldError::Message(format!(
                "the script defines both '{prefix}density' and '{prefix}opacity': a volume has one of them"
            )))
            }
            (false, false) => {
                return Err(FieldError::Message(format!(
                    "volume rendering needs 'fn {prefix}density(p: vec3) -> f32' (or the course's per-sample \
                     'fn {prefix}opacity(p: vec3) -> f32') and 'fn {prefix}color(p: vec3) -> vec3'"
                )))
            }
        };
        let color = format!("{prefix}color");
        let vec3 = Type::Vec(3);
        check_signature(program, &first, &[std::slice::from_ref(&vec3)], &Type::F32)?;
        check_signature(
            program,
            &color,
            &[std::slice::from_ref(&vec3), &[vec3.clone(), vec3.clone()]],
            &Type::Vec(3),
        )?;
        let lowered = program.lower_many(&[first.as_str(), color.as_str()])?;
        let forward = cache.get(&kernel_graphs::value(&lowered), options)?;
        // The backward pass of training gives the forward pass's values too, so that it runs either as
        // one kernel over the samples or, split after the field's inputs (a point, maybe a direction), as
        // a forward pass that keeps what the backward pass reads.
        let split = Options {
            split: Some(lowered.graph.n_inputs),
            ..options
        };
        let backward = cache.get(
            &kernel_graphs::forward_backward(&lowered, program.n_params()),
            split,
        )?;
        let density = cache.get(&kernel_graphs::value(&program.lower(&first)?), options)?;
        Ok(VolumeField {
            forward,
            backward,
            density,
            mode,
        })
    }

    /// The density (or opacity) kernel alone bound to `params` (3 inputs, 1 output): what occupancy
    /// grids probe, without the color network's work.
    pub fn bind_density<'a>(&'a self, params: &'a [f32]) -> Bound<'a> {
        Bound {
            kernel: &self.density,
            params,
        }
    }

    /// The occupancy grid of the script's `density` (or `opacity`) with `params` in `resolution`³ cells
    /// over `bounds`, occupied where it (with `thickness`, a cell's optical thickness,
    /// [`nerfjit_runtime::CellThickness`]) may exceed `threshold`: from its interval bounds where they bound
    /// anything (a script's analytic field: the grid misses nothing, see
    /// [`OccupancyGrid::from_bounds`]), else by probing the field ([`OccupancyGrid::build`]: dense layers
    /// and grid reads have no useful bounds).
    pub fn occupancy_grid(
        &self,
        program: &Program,
        params: &[f32],
        cache: &KernelCache,
        (bounds, resolution, threshold, space): (([f32; 3], [f32; 3]), usize, f32, GridSpace),
        thickness: bool,
    ) -> Result<OccupancyGrid> {
        let name = match self.mode {
            Mode::Density => "density",
            Mode::Opacity => "opacity",
        };
        let compiler = Compiler {
            program,
            params,
            cache,
        };
        // Interval bounds hold over boxes of the scene, and of the density: a warped grid's cells, and
        // cells whose thickness is thresholded, are probed.
        let bounds_of = match (space, thickness) {
            (GridSpace::Scene, false) => compiler.bounds(name, &[Type::Vec(3)], &Type::F32)?,
            _ => None,
        };
        let built = match bounds_of {
            Some(bounds_of) => {
                OccupancyGrid::from_bounds(&bounds_of, bounds, resolution, self.mode, threshold)
            }
            None => space.with_grid_field(
                &self.bind_density(params),
                (bounds, resolution),
                (self.mode, thickness),
                |density| OccupancyGrid::build(density, bounds, resolution, self.mode, threshold),
            ),
        };
        Ok(built?.in_space(space))
    }

    /// The forward and backward kernels bound to `params`.
    pub fn bind<'a>(&'a self, params: &'a [f32]) -> (Bound<'a>, BoundVjp<'a>) {
        (
            Bound {
                kernel: &self.forward,
                params,
            },
            BoundVjp {
                kernel: &self.backward,
                params,
                n_outputs: 4,
                n_grads: self.backward.n_reductions,
            },
        )
    }
}

/// Checks that function `name` takes one of `inputs` and returns `output`.
pub fn check_signature(program: &Program, name: &str, inputs: &[&[Type]], output: &Type) -> Result<()> {
    let Some(sig) = program.signature(name) else {
        // Lowering a missing function gives the diagnostic with its hint (a close name, or the list).
        return Err(program.lower(name).err().map_or_else(
            || FieldError::Message(format!("the script needs a function '{name}'")),
            FieldError::Script,
        ));
    };
    let got: Vec<Type> = sig.inputs.iter().map(|(_, t)| t.clone()).collect();
    if inputs.contains(&got.as_slice()) && sig.output.coerces_to(output) {
        return Ok(());
    }
    let forms: Vec<String> = inputs
        .iter()
        .map(|ins| {
            let ts: Vec<String> = ins.iter().map(Type::to_string).collect();
            format!("fn {name}({}) -> {output}", ts.join(", "))
        })
        .collect();
    Err(FieldError::Message(format!(
        "'{name}' must be {}, but the script has {sig}",
        forms.join(" or ")
    )))
}

/// The volume of a script as rendered and trained: one field, or with hierarchical sampling a coarse
/// field (`coarse_density`/`coarse_color`) and the fine one (`density`/`color`) with `importance` more
/// samples per ray drawn from the coarse weights.
pub struct VolumeFields {
    /// The field (the fine one with hierarchical sampling).
    pub fine: VolumeField,
    /// The coarse field and the importance samples per ray, with hierarchical sampling.
    pub coarse: Option<(VolumeField, usize)>,
}

impl VolumeFields {
    /// Compiles the fields of `program`, their dense products in `products`; hierarchical when
    /// `importance` > 0.
    pub fn compile(
        program: &Program,
        cache: &KernelCache,
        importance: usize,
        products: Precision,
    ) -> Result<VolumeFields> {
        let fine = VolumeField::compile(program, cache, products)?;
        let coarse = match importance {
            0 => None,
            n => {
                let coarse =
                    VolumeField::compile_prefixed(program, cache, "coarse_", products).map_err(|e| {
                        FieldError::Message(format!("importance sampling needs a coarse field: {e}"))
                    })?;
                if coarse.mode != fine.mode {
                    return Err(FieldError::Message(
                        "the coarse and fine fields must both be densities or both opacities".into(),
                    ));
                }
                Some((coarse, n))
            }
        };
        Ok(VolumeFields { fine, coarse })
    }

    /// The fields bound to `params`, each with its backward pass.
    pub fn bind<'a>(&'a self, params: &'a [f32]) -> BoundFields<'a> {
        BoundFields {
            fine: self.fine.bind(params),
            coarse: self
                .coarse
                .as_ref()
                .map(|(coarse, importance)| (coarse.bind(params), *importance)),
        }
    }

    /// [`VolumeFields::render`], skipping the cells `grid` marks empty when given.
    pub fn render_with(
        &self,
        camera: &nerfjit_runtime::Camera,
        size: (u32, u32),
        params: &[f32],
        settings: &nerfjit_runtime::VolumeSettings,
        grid: Option<&OccupancyGrid>,
    ) -> Result<nerfjit_runtime::volume::render::VolumeFrame> {
        Ok(self.bind(params).model().render(camera, size, settings, grid)?)
    }

    /// Renders one view (`settings.samples` coarse samples, plus the importance samples).
    pub fn render(
        &self,
        camera: &nerfjit_runtime::Camera,
        width: u32,
        height: u32,
        params: &[f32],
        settings: &nerfjit_runtime::VolumeSettings,
    ) -> Result<nerfjit_runtime::volume::render::VolumeFrame> {
        self.render_with(camera, (width, height), params, settings, None)
    }
}

/// [`VolumeFields`] bound to param values: the runtime's models of them.
pub struct BoundFields<'a> {
    fine: (Bound<'a>, BoundVjp<'a>),
    coarse: Option<((Bound<'a>, BoundVjp<'a>), usize)>,
}

impl BoundFields<'_> {
    /// The volume as rendered.
    pub fn model(&self) -> VolumeModel<'_> {
        VolumeModel {
            field: &self.fine.0,
            coarse: self.coarse.as_ref().map(|((c, _), n)| (c as &dyn BatchFn, *n)),
        }
    }

    /// The volume as trained.
    pub fn trainable(&self) -> TrainableModel<'_> {
        TrainableModel {
            field: &self.fine.0,
            vjp: &self.fine.1,
            coarse: self.coarse.as_ref().map(|((field, vjp), importance)| CoarsePass {
                field,
                vjp,
                importance: *importance,
            }),
            recompute_forward: false,
            appearance: None,
            distortion: 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A script whose density is a shell |p| = 0.6 of half-width 0.005: thinner than the spacing (0.125)
    /// of the probes of an 8³ grid over [-1, 1]³, none of which lies on it.
    const SHELL: &str = "
        fn density(p: vec3) -> f32 = select(step(abs(length(p) - 0.6), 0.005), 10.0, 0.0)
        fn color(p: vec3) -> vec3 = [1, 1, 1]
    ";

    /// A small NeRF with a coarse field: two dense layers each, view-dependent color.
    const NET: &str = "
        param w1: mat<24, 15> = linear_init(seed: 1)
        param b1: vec<24> = uniform(-0.1, 0.1, seed: 2)
        param wd: mat<1, 24> = linear_init(seed: 3)
        param wc: mat<3, 30> = linear_init(seed: 4)
        param v1: mat<16, 15> = linear_init(seed: 5)
        param vd: mat<1, 16> = linear_init(seed: 6)
        fn h(p: vec3) -> vec<24> = relu(dense(w1, b1, harmonic(p, 2)))
        fn density(p: vec3) -> f32 = softplus(dense(wd, h(p)))[0]
        fn color(p: vec3, d: vec3) -> vec3 = sigmoid(dense(wc, concat(h(p), 2.0 * d, d)))
        fn coarse_density(p: vec3) -> f32 = softplus(dense(vd, relu(dense(v1, harmonic(p, 2)))))[0]
        fn coarse_color(p: vec3) -> vec3 = sigmoid(p)
    ";

    /// A hash-grid field read twice (density and color), as the instant recipes have it.
    const HASH_NET: &str = "
        param table: hashgrid<3, levels: 6, features: 2, log2_size: 10, base: 4, finest: 64, bounds: 1.5> = uniform(-0.5, 0.5, seed: 1)
        param w1: mat<16, 12> = kaiming(seed: 2)
        param wd: mat<4, 16> = kaiming(seed: 3)
        param wc: mat<3, 7> = xavier(seed: 4)
        fn g(p: vec3) -> vec<4> = dense(wd, relu(dense(w1, hashgrid(table, p))))
        fn density(p: vec3) -> f32 = softplus(g(p)[0])
        fn color(p: vec3, d: vec3) -> vec3 = sigmoid(dense(wc, concat(g(p), d)))
    ";

    /// Training steps whose backward passes read what the forward passes kept give the steps that
    /// recompute the forward pass (plain and hierarchical, f32 and bf16 products; a hash grid's scatters
    /// held back and added level by level after the step's tasks, one task and several).
    #[test]
    fn kept_forward_passes_train_as_recomputed_ones() {
        use nerfjit_runtime::{Camera, RayBatch, StepWorkspace, VolumeSettings};
        let cache = KernelCache::new();
        let camera = Camera::look_at(
            glam::Vec3::new(0.3, 0.5, -3.0),
            glam::Vec3::ZERO,
            glam::Vec3::Y,
            glam::Vec2::splat(1.5),
            glam::Vec2::ZERO,
        )
        .unwrap();
        let settings = VolumeSettings {
            spacing: nerfjit_runtime::DepthSpacing::Linear,
            near: 2.0,
            far: 4.0,
            samples: 48,
            mode: Mode::Density,
            background: Some([0.0; 3]),
            early_termination: None,
        };
        // 40 rays are one task of the step; 2,000 of 48 samples are three chunks of 32,768 points.
        let cases = [
            (NET, Precision::F32, 0, 40),
            (NET, Precision::F32, 40, 40),
            (NET, Precision::Bf16, 0, 40),
            (HASH_NET, Precision::F32, 0, 40),
            (HASH_NET, Precision::F32, 0, 2000),
            (HASH_NET, Precision::Bf16, 0, 2000),
        ];
        for (source, products, importance, n_rays) in cases {
            let program = nerfjit_dsl::compile("net.sdf", source).unwrap();
            let rays = RayBatch::random_pixels(&camera, 64, 64, n_rays, 5).unwrap().0;
            let targets: Vec<[f32; 3]> = (0..rays.len())
                .map(|k| [0.1 * (k % 7) as f32, 0.5, 0.2])
                .collect();
            let fields = VolumeFields::compile(&program, &cache, importance, products).unwrap();
            let bound = fields.bind(&program.param_values);
            assert!(
                bound.fine.1.kept_passes().is_some(),
                "a network field offers kept passes"
            );
            let step = |recompute_forward: bool| {
                let model = TrainableModel {
                    recompute_forward,
                    ..bound.trainable()
                };
                let mut workspace = StepWorkspace::default();
                let step = model
                    .step(&rays, &targets, &settings, None, None, &mut workspace)
                    .unwrap();
                (step.loss, workspace.grads().to_vec())
            };
            let holds = bound.fine.1.kept_passes().unwrap().hold_scatters();
            assert_eq!(holds, source == HASH_NET, "a hash grid's scatters are held back");
            let (kept, recomputed) = (step(false), step(true));
            // The held scatters are added level by level on the pool's threads: one thread gives the
            // same bits.
            let one_thread = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
            let bits = |g: &[f32]| g.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            let alone = one_thread.install(|| step(false));
            assert_eq!(bits(&alone.1), bits(&kept.1), "{products:?}, {n_rays} rays");
            assert!(
                (kept.0 - recomputed.0).abs() <= 1e-6 * recomputed.0,
                "{products:?}: {} vs {}",
                kept.0,
                recomputed.0
            );
            let scale = recomputed.1.iter().fold(0.0f32, |m, g| m.max(g.abs()));
            assert!(scale > 0.0);
            for (k, (a, b)) in kept.1.iter().zip(&recomputed.1).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-5 * scale,
                    "{products:?}, param {k}: {a} vs {b}"
                );
            }
        }
    }

    #[test]
    fn a_script_density_gets_its_occupancy_grid_from_its_bounds() {
        let program = nerfjit_dsl::compile("shell.sdf", SHELL).unwrap();
        let cache = KernelCache::new();
        let field = VolumeField::compile(&program, &cache, Precision::F32).unwrap();
        let params = &program.param_values;
        let unit = ([-1.0; 3], [1.0; 3]);
        let probed = OccupancyGrid::build(&field.bind_density(params), unit, 8, Mode::Density, 0.5).unwrap();
        assert_eq!(probed.occupied_cells(), 0, "a probe lies on the shell");
        let grid = field
            .occupancy_grid(&program, params, &cache, (unit, 8, 0.5, GridSpace::Scene), false)
            .unwrap();
        // Every cell the shell crosses (its nearest point to the origin closer than 0.605, its farthest
        // farther than 0.595) is occupied.
        let mut crossed = 0;
        for cell in 0..512usize {
            let index = [cell % 8, cell / 8 % 8, cell / 64];
            let lo = index.map(|c| -1.0 + 0.25 * c as f32);
            let nearest: f32 = (0..3).map(|i| 0.0f32.clamp(lo[i], lo[i] + 0.25).powi(2)).sum();
            let farthest: f32 = (0..3)
                .map(|i| lo[i].abs().max((lo[i] + 0.25).abs()).powi(2))
                .sum();
            if nearest.sqrt() < 0.605 && farthest.sqrt() > 0.595 {
                let [x, y, z] = index;
                assert!(grid.cell(x, y, z), "cell {index:?} holds part of the shell");
                crossed += 1;
            }
        }
        assert!(crossed > 100, "{crossed} cells crossed");
        // Bounds of a shell over a box are loose but not useless: the cells far from it are empty.
        assert!(!grid.occupied([0.0; 3]) && !grid.occupied([0.95; 3]));
    }
}
