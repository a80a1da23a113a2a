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

use crate::failure::{Failure, Result};

/// The script for the model in `text`; `source` names the model in the script's header.
pub fn convert(text: &str, source: &str) -> std::result::Result<String, String> {
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
    Ok(format!(
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
             max_steps: 128,\n    \
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
    ))
}

/// The script for the model file `input` (read with a cap on its size), and the model's name.
pub fn script_of(input: &Path) -> Result<(String, String)> {
    let text = nerfjit_runtime::data::input::read_text_capped(input)
        .map_err(|e| Failure::Message(format!("cannot read '{}': {e}", input.display())))?;
    let name = input.file_name().and_then(|n| n.to_str()).unwrap_or("model.vm");
    let script = convert(&text, name).map_err(Failure::Message)?;
    Ok((script, name.to_string()))
}

/// The number of operations of a script written by [`convert`].
pub fn operations(script: &str) -> usize {
    script.matches("    let v").count()
}

/// Converts the model file `input` and writes the script to `out` (default: the input with `.sdf`);
/// returns a summary.
pub fn run(input: &Path, out: Option<&Path>) -> Result<String> {
    let (script, _) = script_of(input)?;
    let out = out.map_or_else(|| input.with_extension("sdf"), Path::to_path_buf);
    // The script must compile: a model whose numbers overflow or whose ops the language refuses is
    // reported here, not at the first run.
    nerfjit_dsl::compile(&out.display().to_string(), &script).map_err(Failure::Script)?;
    std::fs::write(&out, &script)
        .map_err(|e| Failure::Message(format!("cannot write '{}': {e}", out.display())))?;
    Ok(format!(
        "imported {} operations from '{}' → {}",
        operations(&script),
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
