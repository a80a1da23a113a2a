//! `nerfjit transmittance`: the transmittance of a piecewise-constant medium between boundaries.

use nerfjit_runtime::Medium;

use crate::failure::Result;

/// Prints T between boundaries `from` and `to`, or a table of every pair.
pub fn run(segments: &str, pair: Option<(usize, usize)>) -> Result<String> {
    let medium = Medium::parse(segments)?;
    let boundaries = medium.segments().len() + 1;
    let pairs: Vec<(usize, usize)> = match pair {
        Some(p) => vec![p],
        None => (0..boundaries)
            .flat_map(|a| (a + 1..boundaries).map(move |b| (a, b)))
            .collect(),
    };
    let mut out = String::new();
    for (a, b) in pairs {
        let t = medium.transmittance(a, b)?;
        out += &format!("T({a} → {b}) = {t}\n");
    }
    Ok(out)
}
