//! Golden files: each `tests/in/NAME.sdf` names on its first line the nerfjit command run on it
//! (`// nerfjit check {}`, `// nerfjit ir {} sdf --grad --graph-only`; `{}` is the script's path), and
//! `tests/out/NAME.txt` holds what that command printed: its exit status, standard output and standard
//! error — rendered diagnostics and IR dumps as users see them. A change to either shows up as a diff of
//! text in review. `NERFJIT_BLESS=1 cargo test --release --test golden` writes the outputs anew (read the
//! diff before committing it).

use std::path::{Path, PathBuf};
use std::process::Command;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The golden inputs, sorted by name.
fn inputs() -> Vec<PathBuf> {
    let mut inputs: Vec<PathBuf> = std::fs::read_dir(Path::new(ROOT).join("tests/in"))
        .expect("tests/in")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "sdf"))
        .collect();
    inputs.sort();
    inputs
}

/// What running the command on the first line of `input` prints, as stored in its golden file.
fn output_of(input: &Path) -> String {
    let relative = input.strip_prefix(ROOT).expect("inside the repository");
    let relative = relative.to_str().expect("UTF-8 path");
    let source = std::fs::read_to_string(input).expect("readable input");
    let command = source
        .lines()
        .next()
        .and_then(|l| l.strip_prefix("// nerfjit "))
        .unwrap_or_else(|| panic!("{relative}: the first line must be '// nerfjit COMMAND {{}} ...'"));
    let args: Vec<String> = command
        .split_whitespace()
        .map(|a| a.replace("{}", relative))
        .collect();
    let out = Command::new(env!("CARGO_BIN_EXE_nerfjit"))
        .args(&args)
        .current_dir(ROOT)
        .output()
        .expect("nerfjit runs");
    format!(
        "$ nerfjit {}\nexit status: {}\n--- stdout\n{}--- stderr\n{}",
        args.join(" "),
        out.status.code().map_or("killed".to_string(), |c| c.to_string()),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// The first line where `got` and `want` differ, shown with both versions.
fn first_difference(got: &str, want: &str) -> String {
    let (mut got_lines, mut want_lines) = (got.lines(), want.lines());
    for number in 1.. {
        match (got_lines.next(), want_lines.next()) {
            (Some(g), Some(w)) if g == w => continue,
            (None, None) => break,
            (g, w) => {
                return format!(
                    "line {number}:\n  golden: {}\n  now:    {}",
                    w.unwrap_or("(end)"),
                    g.unwrap_or("(end)")
                )
            }
        }
    }
    "the texts differ only in line endings".to_string()
}

#[test]
fn every_input_prints_its_golden_output() {
    let bless = std::env::var_os("NERFJIT_BLESS").is_some();
    let inputs = inputs();
    assert!(inputs.len() >= 10, "only {} golden inputs", inputs.len());
    let out_dir = Path::new(ROOT).join("tests/out");
    let mut failures = Vec::new();
    for input in &inputs {
        let name = input.file_stem().unwrap().to_str().unwrap();
        let golden = out_dir.join(format!("{name}.txt"));
        let got = output_of(input);
        if bless {
            std::fs::write(&golden, &got).expect("write golden file");
            continue;
        }
        match std::fs::read_to_string(&golden) {
            Ok(want) if want == got => {}
            Ok(want) => failures.push(format!("{name}: {}", first_difference(&got, &want))),
            Err(_) => failures.push(format!("{name}: no golden file {}", golden.display())),
        }
    }
    let stale: Vec<String> = std::fs::read_dir(&out_dir)
        .expect("tests/out")
        .map(|e| e.expect("entry").path())
        .filter(|p| {
            let stem = p.file_stem().unwrap_or_default();
            !inputs.iter().any(|i| i.file_stem() == Some(stem))
        })
        .map(|p| format!("{}: a golden file without an input", p.display()))
        .collect();
    failures.extend(stale);
    assert!(
        failures.is_empty(),
        "{}\n(NERFJIT_BLESS=1 cargo test --release --test golden writes the outputs anew)",
        failures.join("\n")
    );
}
