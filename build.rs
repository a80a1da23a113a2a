//! Embeds every `examples/*.sdf` into the binary and checks each at build time (parse, names, types,
//! params), so that a broken example fails the build with its diagnostics.

use std::fs;
use std::path::Path;

fn main() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples");
    println!("cargo:rerun-if-changed={}", dir.display());
    println!("cargo:rerun-if-changed=../dsl/prelude.sdf");
    let mut entries: Vec<_> = fs::read_dir(&dir)
        .expect("examples/ exists")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "sdf"))
        .collect();
    entries.sort();
    let mut code = String::from("/// The example scripts shipped with nerfjit: (file name, source).\n");
    code += "pub const EXAMPLES: &[(&str, &str)] = &[\n";
    for path in &entries {
        println!("cargo:rerun-if-changed={}", path.display());
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .expect("UTF-8 file name");
        let source = fs::read_to_string(path).expect("readable example");
        if let Err(report) = nerfjit_dsl::compile(&format!("examples/{name}"), &source) {
            panic!("example {name} does not check:\n{report}");
        }
        code += &format!(
            "    ({name:?}, include_str!({:?})),\n",
            path.display().to_string()
        );
    }
    code += "];\n";
    let out = Path::new(&std::env::var("OUT_DIR").expect("OUT_DIR")).join("examples.rs");
    fs::write(out, code).expect("write examples.rs");
}
