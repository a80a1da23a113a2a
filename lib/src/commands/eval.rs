//! `nerfjit eval`: evaluates a function at points read as CSV, with the JIT or the f64 interpreter.

use std::io::{BufRead, Read, Write};

use nerfjit_dsl::{budget, interp, kernel_graphs};
use nerfjit_jit::{Kernel, Options};

use crate::failure::{Failure, Result};
use crate::script;

/// Where the points come from and what to print.
pub struct EvalArgs<'a> {
    /// The script.
    pub script: &'a str,
    /// The function.
    pub function: &'a str,
    /// A CSV file of points, or `-` for standard input.
    pub points: &'a str,
    /// Append the gradient of each output with respect to the inputs.
    pub grad: bool,
    /// Use the f64 reference interpreter instead of the JIT.
    pub interp: bool,
}

/// The longest line of a points file: far more than any row of numbers needs, so that a stream without
/// line breaks (`/dev/zero`) ends in a message instead of one endless line.
const MAX_LINE_BYTES: usize = 1 << 20;

/// Bytes a point of `width` inputs and `outputs` outputs takes while evaluated: its row (`width` f64 and
/// a vector's header), its input columns (f32), its output columns (f32) and its printed row (f64 and a
/// vector's header).
fn bytes_per_point(width: usize, outputs: usize) -> u64 {
    (24 + 8 * width + 4 * width + 4 * outputs + 24 + 8 * outputs) as u64
}

/// Parses CSV rows of `width` numbers (blank lines and `#` comments skipped), each point taking
/// `point_bytes` of the memory limit, and refusing lines longer than `MAX_LINE_BYTES` and more bytes than
/// an input file may hold.
fn read_points(reader: impl BufRead, source: &str, width: usize, point_bytes: u64) -> Result<Vec<Vec<f64>>> {
    let cap = nerfjit_runtime::input::MAX_INPUT_BYTES;
    let mut reader = reader.take(cap + 1);
    let mut rows = Vec::new();
    let mut bytes = Vec::new();
    for i in 0.. {
        let io = |e: std::io::Error| Failure::Message(format!("cannot read {source}: {e}"));
        bytes.clear();
        let read = (&mut reader)
            .take(MAX_LINE_BYTES as u64 + 1)
            .read_until(b'\n', &mut bytes)
            .map_err(io)?;
        if read == 0 {
            break;
        }
        if bytes.len() > MAX_LINE_BYTES {
            return Err(Failure::Message(format!(
                "{source}:{}: the line is longer than {MAX_LINE_BYTES} bytes: not CSV rows of numbers",
                i + 1
            )));
        }
        if reader.limit() == 0 {
            return Err(Failure::Message(format!(
                "{source} is longer than the {cap} bytes an input file may hold"
            )));
        }
        if rows.len() % 4096 == 0 {
            let what = || format!("the points of {source} (more than {})", rows.len());
            budget::check(what, budget::bytes_of(rows.len() as u64 + 4096, point_bytes))?;
        }
        let line = std::str::from_utf8(&bytes)
            .map_err(|_| Failure::Message(format!("{source}:{}: not UTF-8 text", i + 1)))?;
        let text = line.trim();
        if text.is_empty() || text.starts_with('#') {
            continue;
        }
        let row = text
            .split(',')
            .map(|f| f.trim().parse::<f64>())
            .collect::<std::result::Result<Vec<_>, _>>()
            .map_err(|e| Failure::Message(format!("{source}:{}: {e} in '{text}'", i + 1)))?;
        if row.len() != width {
            return Err(Failure::Message(format!(
                "{source}:{}: expected {width} numbers per row (one per input scalar), found {}",
                i + 1,
                row.len()
            )));
        }
        rows.push(row);
    }
    Ok(rows)
}

/// Runs the command, writing CSV to `out`.
pub fn run(args: &EvalArgs, out: &mut dyn Write) -> Result<()> {
    let program = script::load(args.script)?;
    let lowered = program.lower(args.function)?;
    let graph = if args.grad {
        kernel_graphs::with_gradient(&lowered)
    } else {
        kernel_graphs::value(&lowered)
    };
    let width = graph.n_inputs as usize;
    let point_bytes = bytes_per_point(width, graph.outputs.len());
    let points = if args.points == "-" {
        read_points(std::io::stdin().lock(), "<stdin>", width, point_bytes)?
    } else {
        let file = std::fs::File::open(args.points)
            .map_err(|e| Failure::Message(format!("cannot read points file '{}': {e}", args.points)))?;
        read_points(std::io::BufReader::new(file), args.points, width, point_bytes)?
    };
    let rows: Vec<Vec<f64>> = if args.interp {
        let params = program.param_values_f64();
        points
            .iter()
            .map(|p| interp::eval_point(&graph, p, &params).outputs)
            .collect()
    } else {
        let kernel = Kernel::compile(&graph, Options::default())?;
        let n = points.len();
        let cols: Vec<Vec<f32>> = (0..width)
            .map(|c| points.iter().map(|p| p[c] as f32).collect())
            .collect();
        let ins: Vec<&[f32]> = cols.iter().map(Vec::as_slice).collect();
        let mut outs = vec![vec![0.0f32; n]; graph.outputs.len()];
        let mut refs: Vec<&mut [f32]> = outs.iter_mut().map(Vec::as_mut_slice).collect();
        kernel.eval(n, &ins, &mut refs, &program.param_values, &mut []);
        (0..n)
            .map(|i| outs.iter().map(|o| f64::from(o[i])).collect())
            .collect()
    };
    let io = |e: std::io::Error| Failure::Message(format!("cannot write output: {e}"));
    for row in rows {
        let text: Vec<String> = row.iter().map(|x| format!("{x}")).collect();
        writeln!(out, "{}", text.join(",")).map_err(io)?;
    }
    Ok(())
}
