//! Transmittance through a piecewise-constant medium along a ray, the first exercise of volume
//! rendering: `T = exp(−Σ density·length)` over the segments between two boundaries.

use std::fmt;

use crate::error::{Error, Result};

/// A stretch of the ray of constant density.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Segment {
    /// Length along the ray (>= 0).
    pub length: f32,
    /// Density σ (>= 0).
    pub density: f32,
}

/// Segments one after another along a ray. Boundary 0 is the start of the first segment and
/// boundary k the end of segment k (counting from 1).
#[derive(Debug, Clone, PartialEq)]
pub struct Medium {
    segments: Vec<Segment>,
}

/// The transmittance between two boundaries and the optical depth `x` with `T = e^−x`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Transmittance {
    /// The fraction of light that gets through, `e^−x`.
    pub value: f32,
    /// `x = Σ density·length`.
    pub optical_depth: f32,
}

impl fmt::Display for Transmittance {
    /// Writes e.g. `e^-2.5 = 0.082085`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "e^-{} = {}", self.optical_depth, self.value)
    }
}

/// Parses one number of a segment for [`Medium::parse`].
fn number(segment: usize, text: &str, what: &str, value: &str) -> Result<f32> {
    let x: f32 = value.trim().parse().map_err(|_| {
        Error::Invalid(format!(
            "segment {segment} '{text}': {what} '{}' is not a number",
            value.trim()
        ))
    })?;
    if !(x.is_finite() && x >= 0.0) {
        return Err(Error::Invalid(format!(
            "segment {segment} '{text}': {what} {x} must be finite and >= 0"
        )));
    }
    Ok(x)
}

impl Medium {
    /// A medium made of `segments`, each of finite length and density >= 0.
    pub fn new(segments: Vec<Segment>) -> Result<Medium> {
        for (k, s) in segments.iter().enumerate() {
            let ok = |x: f32| x.is_finite() && x >= 0.0;
            if !(ok(s.length) && ok(s.density)) {
                return Err(Error::Invalid(format!(
                    "segment {} has length {} and density {}: both must be finite and >= 0",
                    k + 1,
                    s.length,
                    s.density
                )));
            }
        }
        Ok(Medium { segments })
    }

    /// Parses comma-separated `length:density` pairs, e.g. `"2:1,1:0.5,3:10"`.
    pub fn parse(text: &str) -> Result<Medium> {
        if text.trim().is_empty() {
            return Err(Error::Invalid(
                "a medium needs at least one segment 'length:density', e.g. '2:1,1:0.5'".into(),
            ));
        }
        let mut segments = Vec::new();
        for (k, part) in text.split(',').enumerate() {
            let segment = k + 1;
            let part = part.trim();
            let Some((length, density)) = part.split_once(':') else {
                return Err(Error::Invalid(format!(
                    "segment {segment} '{part}' is not of the form 'length:density'"
                )));
            };
            segments.push(Segment {
                length: number(segment, part, "length", length)?,
                density: number(segment, part, "density", density)?,
            });
        }
        Ok(Medium { segments })
    }

    /// The segments in ray order.
    pub fn segments(&self) -> &[Segment] {
        &self.segments
    }

    /// Transmittance between boundaries `from` and `to` (in either order; both at most the
    /// number of segments): `exp(−Σ density·length)` over the segments in between.
    pub fn transmittance(&self, from: usize, to: usize) -> Result<Transmittance> {
        let n = self.segments.len();
        if from > n || to > n {
            return Err(Error::Invalid(format!(
                "boundaries {from} and {to} must be between 0 and {n} (the number of segments)"
            )));
        }
        let (a, b) = (from.min(to), from.max(to));
        let x: f32 = self.segments[a..b].iter().map(|s| s.density * s.length).sum();
        Ok(Transmittance {
            value: (-x).exp(),
            optical_depth: x,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn course_example_by_hand() {
        let m = Medium::parse("2:1,1:0.5,3:10").unwrap();
        assert_eq!(m.segments().len(), 3);
        let cases = [
            ((0, 1), 2.0),
            ((0, 2), 2.5),
            ((1, 3), 30.5),
            ((0, 3), 32.5),
            ((2, 2), 0.0),
        ];
        for ((from, to), x) in cases {
            let t = m.transmittance(from, to).unwrap();
            assert_eq!(t.optical_depth, x, "T({from},{to})");
            let expected = (-(x as f64)).exp();
            assert!(((t.value as f64) - expected).abs() <= 1e-6 * expected, "{t}");
            assert_eq!(m.transmittance(to, from).unwrap(), t);
        }
        assert_eq!(
            m.transmittance(0, 1).unwrap().to_string(),
            format!("e^-2 = {}", (-2f32).exp())
        );
    }

    #[test]
    fn transmittance_multiplies_over_consecutive_stretches() {
        let m = Medium::parse(" 0.5:0.3, 1.25:2 ,4:0, 0.1:7").unwrap();
        for mid in 0..=4 {
            let whole = m.transmittance(0, 4).unwrap().value;
            let parts = m.transmittance(0, mid).unwrap().value * m.transmittance(mid, 4).unwrap().value;
            assert!((whole - parts).abs() <= 1e-6 * whole);
        }
        assert_eq!(m.transmittance(2, 3).unwrap().value, 1.0);
    }

    #[test]
    fn bad_text_and_boundaries_are_clear_errors() {
        let cases = [
            ("", "at least one segment"),
            ("2:1,,3:1", "segment 2 '' is not of the form 'length:density'"),
            ("2:1;3:1", "segment 1 '2:1;3:1': density '1;3:1' is not a number"),
            ("2", "segment 1 '2' is not of the form"),
            ("2:1,x:1", "segment 2 'x:1': length 'x' is not a number"),
            ("2:-1", "density -1 must be finite and >= 0"),
            ("inf:1", "length inf must be finite"),
        ];
        for (text, message) in cases {
            let e = Medium::parse(text).unwrap_err().to_string();
            assert!(e.contains(message), "{text:?}: {e}");
        }
        let m = Medium::parse("1:1").unwrap();
        let e = m.transmittance(0, 2).unwrap_err().to_string();
        assert!(e.contains("between 0 and 1"), "{e}");
        let bad = Segment {
            length: 1.0,
            density: f32::NAN,
        };
        assert!(Medium::new(vec![bad]).is_err());
        assert_eq!(
            Medium::new(vec![Segment {
                length: 2.0,
                density: 0.5
            }])
            .unwrap()
            .transmittance(0, 1)
            .unwrap()
            .optical_depth,
            1.0
        );
    }
}
