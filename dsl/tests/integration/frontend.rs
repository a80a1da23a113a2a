//! The front end: exact diagnostics for common mistakes (pinned as text), and robustness: any input gives
//! a program or diagnostics, never a panic or a stack overflow.

use nerfjit_dsl::compile;
use proptest::prelude::*;

fn error(src: &str) -> String {
    match compile("scene.sdf", src) {
        Ok(_) => panic!("expected an error for:\n{src}"),
        Err(report) => report.to_string(),
    }
}

#[test]
fn typo_in_a_function_name() {
    let text = error("fn sdf(p: vec3) -> f32 {\n    lenght(p) - 1.0\n}\n");
    assert_eq!(
        text,
        "error: unknown function 'lenght'\n --> scene.sdf:2:5\n  |\n2 |     lenght(p) - 1.0\n  |     ^^^^^^\n  = hint: did you mean 'length'?\n"
    );
}

#[test]
fn wrong_arity_shows_the_signature() {
    let text = error("fn sdf(p: vec3) -> f32 = clamp(p.x, 0.0)");
    assert!(
        text.contains("wrong number of arguments: 'clamp' takes 3, got 2"),
        "{text}"
    );
    assert!(text.contains("scene.sdf:1:26"), "{text}");
    assert!(
        text.contains("hint: write clamp(x: T, lo: T, hi: T) -> T"),
        "{text}"
    );
}

#[test]
fn type_mismatch_names_both_types() {
    let text = error("fn sdf(p: vec3) -> f32 {\n  let q = p.xy + p\n  q.x\n}");
    assert!(text.contains("mismatched types for '+': vec2 and vec3"), "{text}");
    assert!(text.contains("scene.sdf:2:11"), "{text}");
    let text = error("fn sdf(p: vec3) -> f32 = p * 2.0");
    assert!(
        text.contains("'sdf' declares result type f32 but its body has type vec3"),
        "{text}"
    );
    let text = error("fn sdf(p: vec3) -> f32 = sphere(p.xy, 1.0)");
    assert!(
        text.contains("argument 'p' of 'sphere' must be vec3, found vec2"),
        "{text}"
    );
}

#[test]
fn recursion_is_reported() {
    let text = error("fn a(x: f32) -> f32 = b(x)\nfn b(x: f32) -> f32 = a(x) + 1.0");
    assert!(text.contains("recursive call to 'a'"), "{text}");
    assert!(text.contains("hint: functions are inlined"), "{text}");
}

#[test]
fn unknown_swizzle_and_names() {
    let text = error("fn sdf(p: vec3) -> f32 = p.xq.x");
    assert!(
        text.contains("unknown swizzle '.xq' on a value of type vec3"),
        "{text}"
    );
    assert!(
        text.contains("scene.sdf:1:28") && text.contains("p.xq.x\n  |                            ^^\n"),
        "{text}"
    );
    let text = error("fn sdf(p: vec3) -> f32 = p.w");
    assert!(text.contains("unknown swizzle '.w'"), "{text}");
    let text = error("fn sdf(pos: vec3) -> f32 = length(po)");
    assert!(
        text.contains("unknown name 'po'") && text.contains("did you mean 'pos'?"),
        "{text}"
    );
}

#[test]
fn duplicate_names() {
    let text = error("fn f(x: f32) -> f32 = x\n\nfn f(x: f32) -> f32 = 2.0 * x");
    assert!(
        text.contains("duplicate name 'f'") && text.contains("already defined on line 1"),
        "{text}"
    );
    assert!(text.contains("scene.sdf:3:4"), "{text}");
    let text = error("fn length(x: f32) -> f32 = x");
    assert!(text.contains("'length' is the name of a builtin"), "{text}");
    let text = error("fn f(x: f32) -> f32 { let a = x; let a = 2.0; a }");
    assert!(text.contains("'a' is already defined in this block"), "{text}");
}

#[test]
fn syntax_errors() {
    assert!(error("fn f(x: f32) -> f32 { x ").contains("expected '}', found end of file"));
    assert!(error("fn f(x: f23) -> f32 = x").contains("did you mean 'f32'?"));
    assert!(error("fn f(x: float) -> f32 = x").contains("did you mean 'f32'?"));
    assert!(error("fn f(x: f32) f32 = x").contains("expected '->'"));
    assert!(error("fn f(x: f32) -> f32 = if x > 0.0 { 1.0 }").contains("'if' needs an 'else' branch"));
    assert!(error("fn f(x: f32) -> f32 = x @ 2").contains("unexpected character '@'"));
    assert!(error("fn f(x: f32) -> f32 = 1.5e").contains("malformed number '1.5e'"));
    assert!(error("rendr { size: 3 }\nfn f(x: f32) -> f32 = x").contains("unknown block 'rendr'"));
}

#[test]
fn params_need_valid_initial_values() {
    assert!(error("param w: mat<2, 3> = [1, 2]").contains("cannot start from a value of 2 components"));
    assert!(error("param b: vec<4> = xavier(seed: 1)").contains("'xavier' initializes a matrix"));
    assert!(error("param b: vec<4> = linear_init(seed: 1)").contains("needs fan_in"));
    assert!(error("fn f(x: f32) -> f32 = xavier(x)").contains("can only initialize a param"));
    // A fan-in of 0 would divide by zero (NaN weights); seeds are whole numbers, never negative.
    for init in [
        "kaiming(fan_in: 0)",
        "linear_init(fan_in: 0)",
        "kaiming(fan_in: -3)",
        "xavier(fan_in: 0.5)",
    ] {
        let text = error(&format!("param w: mat<2, 3> = {init}"));
        assert!(
            text.contains("not a whole number from 1 to 2^53"),
            "{init}: {text}"
        );
    }
    assert!(error("param w: mat<2, 3> = uniform(0, 1, seed: -1)")
        .contains("seed is -1, not a whole number from 0"));
    assert!(error("param w: mat<2, 3> = kaiming(seed: 1.5)").contains("seed is 1.5"));
    assert!(error("param n: mlp<3, 4, 2> = kaiming(seed: -2)").contains("seed is -2"));
    let text = error("param w: mat<2, 3> = uniform(0, 1, sed: 3)");
    assert!(
        text.contains("'uniform' has no argument 'sed'") && text.contains("named arguments are: seed"),
        "{text}"
    );
}

#[test]
fn limits_give_errors_not_stack_overflows() {
    let deep = format!(
        "fn f(x: f32) -> f32 = {}x{}",
        "sin(".repeat(5000),
        ")".repeat(5000)
    );
    assert!(error(&deep).contains("nested too deeply"));
    let blocks = format!(
        "fn f(x: f32) -> f32 = {}x{}",
        "{ ".repeat(5000),
        " }".repeat(5000)
    );
    assert!(error(&blocks).contains("nested too deeply"));
    // Each level calls the previous one twice: 2^40 inlined calls without the step limit.
    let mut src = String::from("fn f0(x: f32) -> f32 = x * 1.5\n");
    for i in 1..40 {
        src += &format!("fn f{i}(x: f32) -> f32 = f{}(x) + f{}(x * 2.0)\n", i - 1, i - 1);
    }
    assert!(error(&src).contains("program too large"), "{}", error(&src));
}

const VALID: &str = "// a scene\nparam c: vec3 = [0.1, 0.2, 0.3]\nconst k = 2.5e-1\n\
fn shape(p: vec3, r: f32 = 1.0) -> f32 {\n    let q = p - c;\n    let (a, b) = (length(q.xy) - r, q.z);\n    \
length(vec2(a, b)) - k\n}\nfn sdf(p: vec3) -> f32 = smooth_union(shape(p), sphere(p, 0.5), 0.2)\n\
fn color(p: vec3) -> vec3 = clamp(abs(p), 0.02, 0.98)\nrender sphere_trace { size: 64, camera: orbit(radius: 3) }\n";

#[test]
fn the_mutation_seed_is_valid() {
    compile("valid.sdf", VALID).unwrap();
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn arbitrary_text_never_panics(src in "\\PC{0,200}") {
        let _ = compile("fuzz.sdf", &src);
    }

    #[test]
    fn token_soup_never_panics(tokens in prop::collection::vec(prop::sample::select(vec![
        "fn", "let", "param", "const", "if", "else", "f(", "(", ")", "{", "}", "[", "]", ",", ":", ";", "=", "->",
        "+", "-", "*", "/", "<", ">=", "&&", "!", ".", "..", "x", "p", "vec3", "f32", "vec<3>", "mat<2,3>",
        "1", "0.5", "1e3", "\"s\"", "length(", "dense(", "harmonic(", ".xy", "[0..2]", "render", "\n",
    ]), 0..60)) {
        let src: String = tokens.join(" ");
        let _ = compile("fuzz.sdf", &src);
    }

    #[test]
    fn mutated_scripts_give_a_program_or_diagnostics(edits in prop::collection::vec(
        (any::<prop::sample::Index>(), 0u8..3, prop::sample::select(vec![
            "(", ")", "{", "}", ",", ";", "x", "p", ".", "1", "-", "*", "let ", "fn ", "vec3", "\"", "é", "\t",
        ])), 1..6)) {
        let mut src = VALID.to_string();
        for (at, kind, text) in edits {
            let mut i = at.index(src.len() + 1);
            while !src.is_char_boundary(i) {
                i -= 1;
            }
            match kind {
                0 => src.insert_str(i, text),
                1 => {
                    let mut j = (i + 1).min(src.len());
                    while !src.is_char_boundary(j) {
                        j += 1;
                    }
                    src.replace_range(i..j, "");
                }
                _ => src.replace_range(i..i, text),
            }
        }
        match compile("mutated.sdf", &src) {
            Ok(_) => {}
            Err(report) => {
                prop_assert!(!report.diagnostics.is_empty());
                let text = report.to_string();
                prop_assert!(text.contains("-->") && text.contains('^'), "{text}");
            }
        }
    }
}

#[test]
fn constants_initial_values_and_settings_must_be_finite() {
    let text = error("const bad = 0 / 0\nfn f(p: vec3) -> f32 = bad");
    assert!(
        text.contains("this value is NaN, not a finite 32-bit float"),
        "{text}"
    );
    assert!(text.contains("scene.sdf:1:13"), "points at the value: {text}");
    let text = error("param y: vec3 = [1, 1e38 * 10, 0]");
    assert!(
        text.contains("this value is 1e39 (one of its components)"),
        "{text}"
    );
    assert!(text.contains("division by zero"), "{text}");
    let text = error("param w: mat<2, 3> = uniform(0, 1 / 0, seed: 1)");
    assert!(text.contains("not a finite 32-bit float"), "{text}");
    // Settings are evaluated when a block runs: a NaN color is refused with its place.
    let program = compile("scene.sdf", "render sphere_trace { background: [0 / 0, 0, 0] }").unwrap();
    let block = program.blocks()[0];
    let Err(d) = nerfjit_dsl::config::Settings::new(&program, block) else {
        panic!("a NaN setting is refused")
    };
    assert!(d.message.contains("NaN"), "{}", d.message);
    // Large intermediate values are fine when the result is finite.
    assert!(compile(
        "s.sdf",
        "const tiny = 1 / (1e38 * 10)\nfn f(p: vec3) -> f32 = tiny"
    )
    .is_ok());
}
