//! `nerfjit import`: f-rep models in the text format of fidget and MPR (`.vm` files) as `.sdf` scripts.
//!
//! A model is one operation per line, `name opcode args…`, each argument the name of an earlier line;
//! `#` starts a comment line. The last line is the shape's value. Opcodes: `var-x`, `var-y`, `var-z`,
//! `const c`, the unary `neg abs sqrt square recip exp ln sin cos tan`, and the binary
//! `add sub mul div min max`. The script defines `fn sdf(p: vec3) -> f32` as one `let` per operation (a
//! model without `var-z` is a 2D shape, extruded along z) and a turntable render of it.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::Path;

use crate::diagnostics::steepness;
use crate::failure::{Failure, Result};
use nerfjit_field::{Compiler, Kind};

/// The model in `text` (the `.vm` format); `source` names it in messages and in the script's header.
pub fn parse(text: &str, source: &str) -> std::result::Result<Model, String> {
    let mut names: HashMap<&str, usize> = HashMap::new();
    let mut body = String::new();
    let mut count = 0usize;
    let mut uses_z = false;
    for (line_index, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let at = |message: String| format!("{source}:{}: {message}\n  {line}", line_index + 1);
        let mut tokens = line.split_whitespace();
        let name = tokens.next().unwrap_or_default();
        let opcode = tokens
            .next()
            .ok_or_else(|| at(format!("'{name}' has no opcode")))?;
        let args: Vec<&str> = tokens.collect();
        let arity = |n: usize| {
            if args.len() == n {
                Ok(())
            } else {
                Err(at(format!(
                    "'{opcode}' takes {n} argument{}, not {}",
                    if n == 1 { "" } else { "s" },
                    args.len()
                )))
            }
        };
        let operand = |k: usize| -> std::result::Result<String, String> {
            names
                .get(args[k])
                .map(|&i| format!("v{i}"))
                .ok_or_else(|| at(format!("'{}' is not defined on an earlier line", args[k])))
        };
        let expression = match opcode {
            "var-x" | "var-y" | "var-z" => {
                arity(0)?;
                uses_z |= opcode == "var-z";
                format!("p.{}", &opcode[4..])
            }
            "const" => {
                arity(1)?;
                let value: f32 = args[0]
                    .parse()
                    .map_err(|_| at(format!("'{}' is not a number", args[0])))?;
                if !value.is_finite() {
                    return Err(at(format!("the constant {} is not finite", args[0])));
                }
                format!("{value:?}")
            }
            "neg" | "abs" | "sqrt" | "square" | "recip" | "exp" | "ln" | "sin" | "cos" | "tan" => {
                arity(1)?;
                let a = operand(0)?;
                match opcode {
                    "neg" => format!("-{a}"),
                    "square" => format!("{a} * {a}"),
                    "recip" => format!("1.0 / {a}"),
                    "ln" => format!("log({a})"),
                    _ => format!("{opcode}({a})"),
                }
            }
            "add" | "sub" | "mul" | "div" | "min" | "max" => {
                arity(2)?;
                let (a, b) = (operand(0)?, operand(1)?);
                match opcode {
                    "add" => format!("{a} + {b}"),
                    "sub" => format!("{a} - {b}"),
                    "mul" => format!("{a} * {b}"),
                    "div" => format!("{a} / {b}"),
                    _ => format!("{opcode}({a}, {b})"),
                }
            }
            _ => return Err(at(format!("unknown opcode '{opcode}'"))),
        };
        if names.insert(name, count).is_some() {
            return Err(at(format!("'{name}' is defined twice")));
        }
        writeln!(body, "    let v{count} = {expression};").expect("writing to a String");
        count += 1;
    }
    if count == 0 {
        return Err(format!("{source}: the model has no operations"));
    }
    let kind = if uses_z {
        "3D"
    } else {
        "2D (no var-z: extruded along z)"
    };
    Ok(Model {
        source: source.to_string(),
        body,
        count,
        kind,
    })
}

/// A model parsed by [`parse`]: the body of its `sdf` function.
pub struct Model {
    source: String,
    body: String,
    count: usize,
    kind: &'static str,
}

impl Model {
    /// The script: the model's `sdf` and a turntable render of it, traced as `trace` says where the field
    /// is not a distance.
    pub fn script(&self, trace: Option<&Trace>) -> String {
        let Model {
            source,
            body,
            count,
            kind,
        } = self;
        let (max_steps, lipschitz) = trace.map_or((128, String::new()), |t| {
            let line = format!("    // {}\n    lipschitz: {},\n", t.why, t.lipschitz);
            (t.max_steps, line)
        });
        format!(
            "// Imported from {source} by `nerfjit import`: {count} operations, a {kind} model.\n\
         // Mesh it with `nerfjit mesh SCRIPT --bounds 1 --res 512 --out model.ply`.\n\
         \n\
         fn sdf(p: vec3) -> f32 {{\n{body}    v{last}\n}}\n\
         \n\
         render sphere_trace {{\n    \
             camera: orbit(radius: 3.5, elevation: 25, frames: 36, up: y, focal: 1.2),\n    \
             size: 256,\n    \
             near: 0.0,\n    \
             far: 7.0,\n    \
             // fidget's and MPR's models live in [-1, 1]³.\n    \
             bounds: sphere(center: [0, 0, 0], radius: 1.75),\n    \
             max_steps: {max_steps},\n{lipschitz}    \
             eps: 1e-4,\n    \
             shading: lambert,\n    \
             albedo: [0.85, 0.75, 0.6],\n    \
             light: [-0.5, 1.0, -0.8],\n    \
             background: [0.08, 0.09, 0.12],\n    \
             out: \"{stem}.gif\",\n\
         }}\n",
            last = count - 1,
            stem = Path::new(source)
                .file_stem()
                .and_then(|s| s.to_str())
                .unwrap_or("model"),
        )
    }
}

/// The script for the model in `text` (see [`Model::script`]), traced as a distance field.
pub fn convert(text: &str, source: &str) -> std::result::Result<String, String> {
    parse(text, source).map(|model| model.script(None))
}

/// The script for the model file `input` (read with a cap on its size), and the model's name. Where the
/// model's field is not a distance (its gradient's norm exceeds 1.05 at more than 0.1% of the centers of
/// 32³ cells of [-1, 1]³), the render block divides it by 1.1 times the norm that 99.9% of those points
/// stay under, and takes proportionally more steps ([`gradient_norms`]).
pub fn script_of(input: &Path) -> Result<Imported> {
    let text = nerfjit_runtime::input::read_text_capped(input)
        .map_err(|e| Failure::Message(format!("cannot read '{}': {e}", input.display())))?;
    let name = input.file_name().and_then(|n| n.to_str()).unwrap_or("model.vm");
    let model = parse(&text, name).map_err(Failure::Message)?;
    let script = model.script(None);
    // The script must compile: a model whose numbers overflow or whose ops the language refuses is
    // reported here, not at the first run.
    let program = nerfjit_dsl::compile(&format!("{name} (imported)"), &script).map_err(Failure::Script)?;
    let norms = gradient_norms(&program, GRADIENT_SAMPLES)?;
    let typical = steepness::typical_largest(&norms).unwrap_or(0.0);
    let largest = norms.iter().copied().filter(|g| !g.is_nan()).fold(0.0, f32::max);
    let name = name.to_string();
    if typical <= 1.05 {
        return Ok(Imported {
            script,
            name,
            lipschitz: None,
        });
    }
    let bound = steepness::bound_for(typical);
    let trace = Trace {
        lipschitz: bound,
        max_steps: (STEPS_PER_UNIT_BOUND * bound).ceil().max(128.0) as u32,
        why: format!(
            "|∇sdf| is under {typical:.3} at 99.9% of {GRADIENT_SAMPLES}³ points of [-1, 1]³ (largest {largest:.3}):\n    \
             // not a distance. Steps are sdf / {bound}; raise it (and max_steps) if a render shows holes."
        ),
    };
    Ok(Imported {
        script: model.script(Some(&trace)),
        name,
        lipschitz: Some(bound),
    })
}

/// A model file converted by [`script_of`].
pub struct Imported {
    /// The script.
    pub script: String,
    /// The model file's name.
    pub name: String,
    /// The bound on the gradient's norm its render block divides the field by, if not 1.
    pub lipschitz: Option<f32>,
}

/// How the render block of a model that is not a distance field traces it.
pub struct Trace {
    /// The field is divided by this.
    lipschitz: f32,
    /// Steps before a ray misses: smaller steps need more.
    max_steps: u32,
    /// Why, as a comment.
    why: String,
}

/// Points per axis of the grid on which [`script_of`] measures the gradient.
const GRADIENT_SAMPLES: usize = 32;

/// Steps a ray may take per unit of the bound on the gradient (16 for a bound of 8, as the default 128).
const STEPS_PER_UNIT_BOUND: f32 = 16.0;

/// The norms of the gradient of `sdf` at the centers of `n`³ cells of [-1, 1]³.
pub fn gradient_norms(program: &nerfjit_dsl::Program, n: usize) -> Result<Vec<f32>> {
    let cache = nerfjit_jit::KernelCache::new();
    let compiler = Compiler {
        program,
        params: &program.param_values,
        cache: &cache,
    };
    let vec3 = [nerfjit_dsl::Type::Vec(3)];
    let gradient = compiler.function("sdf", &vec3, &nerfjit_dsl::Type::F32, Kind::Gradient)?;
    let center = |i: usize| -1.0 + 2.0 * (i as f32 + 0.5) / n as f32;
    // Cell k of axis a: the x index varies fastest, then y, then z.
    let axis = |a: u32| -> Vec<f32> { (0..n * n * n).map(|i| center(i / n.pow(a) % n)).collect() };
    let (x, y, z) = (axis(0), axis(1), axis(2));
    Ok(steepness::gradient_norms(&gradient, &[&x, &y, &z]))
}

/// The number of operations of a script written by [`convert`].
pub fn operations(script: &str) -> usize {
    script.matches("    let v").count()
}

/// Converts the model file `input` and writes the script to `out` (default: the input with `.sdf`);
/// returns a summary.
pub fn run(input: &Path, out: Option<&Path>) -> Result<String> {
    let imported = script_of(input)?;
    let out = out.map_or_else(|| input.with_extension("sdf"), Path::to_path_buf);
    nerfjit_runtime::write_whole(&out, imported.script.as_bytes())?;
    let traced = imported.lipschitz.map_or(String::new(), |bound| {
        format!(" (not a distance: traced as sdf / {bound})")
    });
    Ok(format!(
        "imported {} operations from '{}' → {}{traced}",
        operations(&imported.script),
        input.display(),
        out.display()
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    const SPHERE: &str = "# a unit sphere\n_x var-x\n_x2 square _x\n_y var-y\n_y2 square _y\n_z var-z\n\
                          _z2 square _z\n_a add _x2 _y2\n_b add _a _z2\n_r sqrt _b\n_1 const 1\n_d sub _r _1\n";

    #[test]
    fn a_sphere_becomes_a_script_with_the_same_distances() {
        let script = convert(SPHERE, "sphere.vm").unwrap();
        let program = nerfjit_dsl::compile("sphere.sdf", &script).unwrap();
        let f = program.lower("sdf").unwrap();
        for (p, want) in [
            ([0.0, 0.0, 0.0], -1.0),
            ([2.0, 0.0, 0.0], 1.0),
            ([0.6, 0.0, 0.8], 0.0),
        ] {
            let d = nerfjit_dsl::interp::eval_point(&f.graph, &p, &[]).outputs[0];
            assert!((d - want).abs() < 1e-6, "{p:?}: {d}");
        }
        assert!(script.contains("11 operations, a 3D model"), "{script}");
        assert!(script.contains("render sphere_trace"));
    }

    #[test]
    fn every_opcode_converts() {
        let model = "x var-x\ny var-y\nc const -2.5\n\
                     a neg x\nb abs a\nd sqrt b\ne square d\nf recip e\ng exp f\nh ln g\ni sin h\nj cos i\nk tan j\n\
                     l add k y\nm sub l c\nn mul m m\no div n c\np min o x\nq max p y\n";
        let script = convert(model, "all.vm").unwrap();
        assert!(script.contains("2D (no var-z"), "{script}");
        let program = nerfjit_dsl::compile("all.sdf", &script).unwrap();
        let f = program.lower("sdf").unwrap();
        let (x, y) = (0.3f64, -0.2f64);
        let a = -x;
        let d = a.abs().sqrt();
        let h = (1.0 / (d * d)).exp().ln();
        let m = h.sin().cos().tan() + y + 2.5;
        let want = ((m * m / -2.5).min(x)).max(y);
        let got = nerfjit_dsl::interp::eval_point(&f.graph, &[x, y, 0.0], &[]).outputs[0];
        assert!((got - want).abs() < 1e-9 * want.abs().max(1.0), "{got} vs {want}");
    }

    /// A model file in a scratch folder.
    fn model_file(name: &str, text: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("nerfjit-import-unit-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    }

    #[test]
    fn a_field_that_is_not_a_distance_is_traced_divided_by_its_gradient_bound() {
        // The unit sphere is a distance: traced as it is.
        let sphere = script_of(&model_file("sphere.vm", SPHERE)).unwrap();
        assert_eq!(sphere.lipschitz, None);
        assert!(sphere.script.contains("max_steps: 128,") && !sphere.script.contains("lipschitz"));
        // The same sphere in coordinates 10 times larger: |∇sdf| = 10 everywhere, so the tracer divides by
        // 11 and takes 16 steps per unit of the bound.
        let scaled = SPHERE.replace("_d sub _r _1", "_ten const 10\n_s mul _r _ten\n_d sub _s _1");
        let scaled = script_of(&model_file("scaled.vm", &scaled)).unwrap();
        assert_eq!(scaled.lipschitz, Some(11.0));
        for line in [
            "lipschitz: 11,",
            "max_steps: 176,",
            "|∇sdf| is under 10.000 at 99.9%",
        ] {
            assert!(scaled.script.contains(line), "{line}: {}", scaled.script);
        }
        // The script checks, with the bound in its render block.
        nerfjit_dsl::compile("scaled.sdf", &scaled.script).unwrap();
    }

    #[test]
    fn mistakes_name_the_line() {
        let error = |model: &str| convert(model, "m.vm").unwrap_err();
        assert!(error("a var-x\nb add a c\n").contains("m.vm:2: 'c' is not defined"));
        assert!(error("a var-x\na var-y\n").contains("m.vm:2: 'a' is defined twice"));
        assert!(error("a var-w\n").contains("m.vm:1: unknown opcode 'var-w'"));
        assert!(error("a const x\n").contains("'x' is not a number"));
        assert!(error("a const 1e60\n").contains("not finite"));
        assert!(error("a var-x\nb neg a a\n").contains("'neg' takes 1 argument, not 2"));
        assert!(error("a\n").contains("'a' has no opcode"));
        assert!(error("# only a comment\n").contains("no operations"));
    }
}
