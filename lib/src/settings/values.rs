//! The values of block settings that have a grammar of their own (`schedule: exponential(...)`,
//! `optimizer: adam(...)`, `skip_empty: grid(...)`, ...): their parsers and what they parse into. The
//! schema checks settings with them and the blocks read their settings with them, so they sit below both.

use glam::Vec3;
use nerfjit_dsl::config::{Spanned, Value};
use nerfjit_dsl::Diagnostic;
use nerfjit_runtime::{DepthSpacing, GridSpace, OccupancyGrid, Schedule};

use crate::settings::primitives::{triple, CallArgs};

/// Empty-space skipping: an occupancy grid of the field, built once before rendering.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SkipEmpty {
    /// The grid's corners: nothing outside is rendered.
    pub bounds: ([f32; 3], [f32; 3]),
    /// Cells per axis.
    pub resolution: usize,
    /// Values at or below this count as empty: a cell's density (or opacity), or with `thickness` its
    /// optical thickness.
    pub threshold: f32,
    /// The threshold is on each cell's optical thickness, its density times the length a ray crosses in
    /// it ([`nerfjit_runtime::CellThickness`]), rather than on the density itself.
    pub thickness: bool,
    /// The space the grid's box is in: the scene's, or mip-NeRF 360's contraction (all of space).
    pub space: GridSpace,
}

impl SkipEmpty {
    /// Whether `grid` (one a run kept) has this setting's bounds, resolution and space, so that a render
    /// of this setting may skip its cells rather than build a grid of its own (the threshold is the one
    /// the grid was made with).
    pub fn fits(&self, grid: &OccupancyGrid) -> bool {
        (grid.bounds(), grid.resolution(), grid.space()) == (self.bounds, self.resolution, self.space)
    }
}

/// The `spacing` setting: `linear`, or `lindisp(split: 6)` (half the samples evenly in depth up to `split`,
/// half evenly in disparity beyond it).
pub fn depth_spacing(v: &Spanned) -> Result<DepthSpacing, Diagnostic> {
    match &v.value {
        Value::Name(n) if n == "linear" => Ok(DepthSpacing::Linear),
        Value::Call(n, _) if n == "lindisp" => {
            let a = CallArgs::new(v, &["split"])?;
            let split = a.number("split", None)?;
            if !(split.is_finite() && split > 0.0 && split < 1e9) {
                return Err(Diagnostic::new(
                    v.span,
                    format!("split {split} must be a positive depth"),
                ));
            }
            Ok(DepthSpacing::LinDisp { split: split as f32 })
        }
        _ => Err(Diagnostic::new(
            v.span,
            format!("expected a depth spacing, found {}", v.describe()),
        )
        .with_hint("write linear or lindisp(split: 6)")),
    }
}

/// `skip_empty: grid(bounds: r or [x0, y0, z0, x1, y1, z1], resolution: 64, threshold: 1e-4, space: scene)`
/// (or `thickness: 0.01` instead of `threshold`), or `none` (exact: for `--set` to switch a script's grid
/// off).
pub fn skip_empty(v: &Spanned) -> Result<Option<SkipEmpty>, Diagnostic> {
    if matches!(&v.value, Value::Name(n) if n == "none") {
        return Ok(None);
    }
    let a = CallArgs::new(v, &["bounds", "resolution", "threshold", "thickness", "space"])?;
    let space =
        GridSpace::named(&a.choice("space", &["scene", "contracted", "ndc"], "scene")?).unwrap_or_default();
    let bounds = match a.raw("bounds") {
        None => {
            return Err(Diagnostic::new(v.span, "'grid' needs 'bounds'").with_hint("write grid(bounds: 1.5)"))
        }
        Some(b) if matches!(b.value, Value::Number(_)) => {
            let r = b.number()? as f32;
            ([-r; 3], [r; 3])
        }
        Some(b) => {
            let x = b.numbers(6)?;
            (
                [x[0] as f32, x[1] as f32, x[2] as f32],
                [x[3] as f32, x[4] as f32, x[5] as f32],
            )
        }
    };
    let resolution = a.number("resolution", Some(64.0))?;
    if !(1.0..=256.0).contains(&resolution) || resolution.fract() != 0.0 {
        return Err(Diagnostic::new(
            v.span,
            "the grid's resolution is a whole number from 1 to 256",
        ));
    }
    let thickness = a.raw("thickness").is_some();
    if thickness && a.raw("threshold").is_some() {
        return Err(
            Diagnostic::new(v.span, "the grid takes a 'threshold' or a 'thickness', not both").with_hint(
                "thickness: 0.01 bounds each cell's optical thickness, threshold: 0.3 its density",
            ),
        );
    }
    let threshold = if thickness {
        a.number("thickness", None)?
    } else {
        a.number("threshold", Some(1e-4))?
    };
    Ok(Some(SkipEmpty {
        bounds,
        resolution: resolution as usize,
        threshold: threshold as f32,
        thickness,
        space,
    }))
}

// The settings of `train` and `train sdf`.

/// The `grid_seed` setting: `points` or `points(dilate: n)` (n cells around each point, 2 by default;
/// 0 to 16), or `none`.
pub fn grid_seed(v: &Spanned) -> Result<Option<usize>, Diagnostic> {
    let hint = "write points or points(dilate: 2)";
    match &v.value {
        Value::Name(n) if n == "none" => Ok(None),
        Value::Name(n) if n == "points" => Ok(Some(2)),
        Value::Call(n, _) if n == "points" => {
            let a = CallArgs::new(v, &["dilate"])?;
            let dilate = match a.raw("dilate") {
                Some(d) => crate::settings::primitives::whole(d, 0, 16)?,
                None => 2,
            };
            Ok(Some(dilate as usize))
        }
        _ => Err(
            Diagnostic::new(v.span, format!("expected a grid seed, found {}", v.describe())).with_hint(hint),
        ),
    }
}

/// How a training grid follows the field: rebuilt from probes of every cell, or instant-ngp's running
/// maximum refreshed at random points (`grid_update: ema(decay: 0.95, fraction: 0.125)`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum GridUpdate {
    /// Probes of every cell, dilated by a cell.
    Rebuild,
    /// The running maximum, refreshed at each update.
    Ema {
        /// How much of a cell's maximum an update keeps.
        decay: f32,
        /// The fraction of the cells each update probes.
        fraction: f32,
    },
}

/// The `grid_update` setting: `rebuild` (the default) or `ema(decay: 0.95, fraction: 0.125)` (both
/// arguments optional).
pub fn grid_update(v: Option<Spanned>) -> Result<GridUpdate, Diagnostic> {
    let Some(v) = v else {
        return Ok(GridUpdate::Rebuild);
    };
    let hint = "write rebuild or ema(decay: 0.95, fraction: 0.125)";
    match &v.value {
        Value::Name(name) if name == "rebuild" => return Ok(GridUpdate::Rebuild),
        Value::Name(name) if name == "ema" => {}
        Value::Call(name, _) if name == "ema" => {}
        _ => {
            return Err(
                Diagnostic::new(v.span, format!("expected a grid update, found {}", v.describe()))
                    .with_hint(hint),
            )
        }
    }
    let (decay, fraction) = match &v.value {
        Value::Call(..) => {
            let a = CallArgs::new(&v, &["decay", "fraction"])?;
            let arg = |slot: &str, lo: f64, default: f64| match a.raw(slot) {
                None => Ok(default),
                Some(x) => crate::settings::primitives::ranged(x, lo, 1.0),
            };
            (arg("decay", 0.0, 0.95)?, arg("fraction", 1e-6, 0.125)?)
        }
        _ => (0.95, 0.125),
    };
    Ok(GridUpdate::Ema {
        decay: decay as f32,
        fraction: fraction as f32,
    })
}

/// The `val_minutes` setting: one number or a list of them, in minutes of training, as seconds in order.
pub fn minutes_list(v: &Spanned) -> Result<Vec<f64>, Diagnostic> {
    let items = match &v.value {
        Value::List(items) => items
            .iter()
            .map(|x| crate::settings::primitives::ranged(x, 0.0, 1e6))
            .collect(),
        _ => crate::settings::primitives::ranged(v, 0.0, 1e6).map(|x| vec![x]),
    };
    let mut seconds: Vec<f64> = items?.into_iter().map(|m| 60.0 * m).collect();
    seconds.sort_by(f64::total_cmp);
    Ok(seconds)
}

/// Adam's decay rates and ε: the `optimizer` setting.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamSettings {
    /// Decay of the first moment.
    pub beta1: f32,
    /// Decay of the second moment.
    pub beta2: f32,
    /// Added to √v̂ in the denominator.
    pub eps: f32,
    /// Whether grid tables are updated as PyTorch's SparseAdam updates them (entries with a zero gradient
    /// left alone), as instant-ngp does.
    pub sparse: bool,
}

impl Default for AdamSettings {
    /// Kingma and Ba's defaults: β = (0.9, 0.999), ε = 1e-8.
    fn default() -> AdamSettings {
        AdamSettings {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            sparse: false,
        }
    }
}

/// The `optimizer` setting: `adam(beta1: 0.9, beta2: 0.99, eps: 1e-15, sparse: true)` (every argument
/// optional, the default Adam when the setting is absent).
pub fn optimizer(v: Option<Spanned>) -> Result<AdamSettings, Diagnostic> {
    let defaults = AdamSettings::default();
    let Some(v) = v else {
        return Ok(defaults);
    };
    let hint = "write adam(beta1: 0.9, beta2: 0.99, eps: 1e-15, sparse: true)";
    match &v.value {
        Value::Call(name, _) if name == "adam" => {}
        Value::Name(name) if name == "adam" => return Ok(defaults),
        _ => {
            return Err(
                Diagnostic::new(v.span, format!("expected an optimizer, found {}", v.describe()))
                    .with_hint(hint),
            )
        }
    }
    let a = CallArgs::new(&v, &["beta1", "beta2", "eps", "sparse"])?;
    let decay = |slot: &str, default: f32| -> Result<f32, Diagnostic> {
        match a.raw(slot) {
            None => Ok(default),
            Some(x) => Ok(crate::settings::primitives::ranged(x, 0.0, 0.999_999)? as f32),
        }
    };
    let eps = match a.raw("eps") {
        None => defaults.eps,
        Some(x) => crate::settings::primitives::ranged(x, 1e-30, 1.0)? as f32,
    };
    Ok(AdamSettings {
        beta1: decay("beta1", defaults.beta1)?,
        beta2: decay("beta2", defaults.beta2)?,
        eps,
        sparse: a.choice("sparse", &["true", "false"], "false")? == "true",
    })
}

/// The `schedule` setting: `constant` (the default), `exponential(gamma: 0.1, every: 1000)`,
/// `exponential(gamma: 0.01, over: run)` (by `gamma` over the whole run, see
/// [`Schedule::ExponentialOverRun`]) or `step(factor: 0.8, every: 50)`, starting from the rate `lr`.
pub fn schedule(v: Option<Spanned>, lr: f32) -> Result<Schedule, Diagnostic> {
    const FORMS: &str =
        "write constant, exponential(gamma: 0.1, every: 1000), exponential(gamma: 0.01, over: run) or \
         step(factor: 0.8, every: 50)";
    let Some(v) = v else {
        return Ok(Schedule::Constant { lr });
    };
    if let Value::Name(n) = &v.value {
        if n == "constant" {
            return Ok(Schedule::Constant { lr });
        }
    }
    let Value::Call(name, _) = &v.value else {
        return Err(
            Diagnostic::new(v.span, format!("expected a schedule, found {}", v.describe())).with_hint(FORMS),
        );
    };
    let a = CallArgs::new(&v, &["gamma", "factor", "every", "over"])?;
    if name == "exponential" && a.raw("over").is_some() {
        if a.raw("every").is_some() {
            return Err(Diagnostic::new(
                v.span,
                "an exponential schedule decays 'every' so many steps or 'over' the run, not both",
            )
            .with_hint(FORMS));
        }
        a.choice("over", &["run"], "run")?;
        return Ok(Schedule::ExponentialOverRun {
            lr,
            gamma: a.number("gamma", None)? as f32,
        });
    }
    let every = a.number("every", None)?;
    if every < 1.0 || every.fract() != 0.0 {
        return Err(Diagnostic::new(
            v.span,
            "'every' must be a whole number of steps ≥ 1",
        ));
    }
    match name.as_str() {
        "exponential" => Ok(Schedule::Exponential {
            lr,
            gamma: a.number("gamma", None)? as f32,
            steps_per_decay: every as u32,
        }),
        "step" => Ok(Schedule::Step {
            lr,
            factor: a.number("factor", None)? as f32,
            every: every as u32,
        }),
        other => Err(Diagnostic::new(v.span, format!("unknown schedule '{other}'")).with_hint(FORMS)),
    }
}

// The settings of `render sphere_trace`.

/// The `bounds` setting of sphere tracing: `sphere(center: [x, y, z], radius: r)`.
pub fn bounding_sphere(v: &Spanned) -> Result<(Vec3, f32), Diagnostic> {
    let a = CallArgs::new(v, &["center", "radius"])?;
    let center = a.raw("center").map(triple).transpose()?.unwrap_or([0.0; 3]);
    let radius = a.number("radius", None)?;
    if !(radius > 0.0 && radius < 1e9) {
        return Err(Diagnostic::new(
            v.span,
            format!("radius {radius} must be positive"),
        ));
    }
    Ok((Vec3::from_array(center), radius as f32))
}
