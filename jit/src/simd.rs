//! Helpers that emit Cranelift instructions on 4-lane f32 vectors, and the vectorized polynomial
//! approximations of the transcendental functions (Cranelift has no sin/exp/log instructions).
//!
//! The approximations follow the classic Cody–Waite range reduction with minimax polynomials (as in the
//! Cephes library): about 1–2 ulp for exp and log over the whole range, and for sin/cos/tan on
//! |x| < 8192; the accuracy of each is tested against f64 in `tests`.

use cranelift_codegen::ir::condcodes::{FloatCC, IntCC};
use cranelift_codegen::ir::{types, InstBuilder, MemFlagsData, Value};
use cranelift_frontend::FunctionBuilder;

const F: types::Type = types::F32X4;
const I: types::Type = types::I32X4;

/// An instruction emitter for f32x4 values.
pub struct Simd<'a, 'b> {
    /// The function being built.
    pub b: &'a mut FunctionBuilder<'b>,
}

impl Simd<'_, '_> {
    /// A vector with `x` in every lane.
    pub fn f(&mut self, x: f32) -> Value {
        let s = self.b.ins().f32const(x);
        self.b.ins().splat(F, s)
    }

    /// An integer vector with `x` in every lane.
    pub fn i(&mut self, x: i32) -> Value {
        let s = self.b.ins().iconst(types::I32, i64::from(x));
        self.b.ins().splat(I, s)
    }

    /// Reinterprets f32 lanes as i32 lanes.
    pub fn bits(&mut self, v: Value) -> Value {
        self.b.ins().bitcast(I, little(), v)
    }

    /// Reinterprets i32 lanes as f32 lanes.
    pub fn float(&mut self, v: Value) -> Value {
        self.b.ins().bitcast(F, little(), v)
    }

    /// A lane mask (all ones where `a cc b`), as f32 lanes.
    pub fn cmp(&mut self, cc: FloatCC, a: Value, b: Value) -> Value {
        let m = self.b.ins().fcmp(cc, a, b);
        self.float(m)
    }

    /// `mask ? a : b` per lane.
    pub fn select(&mut self, mask: Value, a: Value, b: Value) -> Value {
        self.b.ins().bitselect(mask, a, b)
    }

    /// 1.0 where the mask is set, else 0.0.
    pub fn mask_to_one(&mut self, mask: Value) -> Value {
        let one = self.f(1.0);
        self.b.ins().band(mask, one)
    }

    /// `b < a ? b : a` (lowered to `minps`).
    pub fn min(&mut self, a: Value, b: Value) -> Value {
        let m = self.cmp(FloatCC::LessThan, b, a);
        self.select(m, b, a)
    }

    /// `a < b ? b : a` (lowered to `maxps`).
    pub fn max(&mut self, a: Value, b: Value) -> Value {
        let m = self.cmp(FloatCC::LessThan, a, b);
        self.select(m, b, a)
    }

    /// a·b + c, fused.
    pub fn fma(&mut self, a: Value, b: Value, c: Value) -> Value {
        self.b.ins().fma(a, b, c)
    }

    /// The polynomial c₀xⁿ + … + cₙ by Horner's rule.
    pub fn horner(&mut self, x: Value, coeffs: &[f32]) -> Value {
        let mut acc = self.f(coeffs[0]);
        for &c in &coeffs[1..] {
            let c = self.f(c);
            acc = self.fma(acc, x, c);
        }
        acc
    }

    /// Converts whole-valued lanes (|x| < 2³¹) to i32. On x86 this is one `cvttps2dq`: the saturating
    /// conversion's NaN and overflow handling costs 6 more instructions and is not needed here (a NaN lane
    /// gives a NaN result through the polynomial anyway).
    fn truncate_to_int(&mut self, x: Value) -> Value {
        if cfg!(target_arch = "x86_64") {
            self.b.ins().x86_cvtt2dq(I, x)
        } else {
            self.b.ins().fcvt_to_sint_sat(I, x)
        }
    }

    /// 2ⁿ for integer lanes n in [-252, 254], as two exact factors (correct through overflow and
    /// underflow of the result).
    fn pow2_factors(&mut self, n: Value) -> (Value, Value) {
        let n1 = self.b.ins().sshr_imm_s(n, 1);
        let n2 = self.b.ins().isub(n, n1);
        let bias = self.i(127);
        let factor = |s: &mut Self, k: Value| {
            let e = s.b.ins().iadd(k, bias);
            let e = s.b.ins().ishl_imm_s(e, 23);
            s.float(e)
        };
        (factor(self, n1), factor(self, n2))
    }

    /// eˣ
    pub fn exp(&mut self, x: Value) -> Value {
        let (lo, hi) = (self.f(-110.0), self.f(90.0));
        let x = self.max(x, lo);
        let x = self.min(x, hi);
        let log2e = self.f(std::f32::consts::LOG2_E);
        let t = self.b.ins().fmul(x, log2e);
        let k = self.b.ins().nearest(t);
        let nk = self.b.ins().fneg(k);
        let (c1, c2) = (self.f(0.693_359_4), self.f(-2.121_944_4e-4));
        let r = self.fma(nk, c1, x);
        let r = self.fma(nk, c2, r);
        let p = self.horner(
            r,
            &[
                1.987_569_1e-4,
                1.398_2e-3,
                8.333_452e-3,
                4.166_579_6e-2,
                1.666_666_5e-1,
                0.5,
            ],
        );
        let r2 = self.b.ins().fmul(r, r);
        let one = self.f(1.0);
        let r1 = self.b.ins().fadd(r, one);
        let p = self.fma(p, r2, r1);
        let ki = self.truncate_to_int(k);
        let (s1, s2) = self.pow2_factors(ki);
        let p = self.b.ins().fmul(p, s1);
        self.b.ins().fmul(p, s2)
    }

    /// ln x (NaN below 0, −∞ at 0).
    pub fn log(&mut self, x0: Value) -> Value {
        // Subnormals are scaled into the normal range first.
        let tiny = self.f(f32::MIN_POSITIVE);
        let is_tiny = self.cmp(FloatCC::LessThan, x0, tiny);
        let big = self.f(8_388_608.0);
        let scaled = self.b.ins().fmul(x0, big);
        let x = self.select(is_tiny, scaled, x0);
        let bits = self.bits(x);
        let e = self.b.ins().ushr_imm_s(bits, 23);
        let bias = self.i(126);
        let e = self.b.ins().isub(e, bias);
        let mant_mask = self.i(0x007F_FFFF);
        let half_bits = self.i(0x3F00_0000);
        let m = self.b.ins().band(bits, mant_mask);
        let m = self.b.ins().bor(m, half_bits);
        let m = self.float(m);
        let mut e = self.b.ins().fcvt_from_sint(F, e);
        let shift = self.f(23.0);
        let zero = self.f(0.0);
        let e_fix = self.select(is_tiny, shift, zero);
        e = self.b.ins().fsub(e, e_fix);
        let sqrthf = self.f(std::f32::consts::FRAC_1_SQRT_2);
        let below = self.cmp(FloatCC::LessThan, m, sqrthf);
        let one = self.f(1.0);
        let m_add = self.b.ins().band(below, m);
        let xm = self.b.ins().fsub(m, one);
        let xm = self.b.ins().fadd(xm, m_add);
        let e_sub = self.b.ins().band(below, one);
        let e = self.b.ins().fsub(e, e_sub);
        let z = self.b.ins().fmul(xm, xm);
        let p = self.horner(
            xm,
            &[
                7.037_683_6e-2,
                -1.151_461e-1,
                1.167_699_9e-1,
                -1.242_014_1e-1,
                1.424_932_3e-1,
                -1.666_805_8e-1,
                2.000_071_4e-1,
                -2.499_999_4e-1,
                3.333_333e-1,
            ],
        );
        let p = self.b.ins().fmul(p, xm);
        let y = self.b.ins().fmul(p, z);
        let c2 = self.f(-2.121_944_4e-4);
        let y = self.fma(e, c2, y);
        let mhalf = self.f(-0.5);
        let y = self.fma(z, mhalf, y);
        let r = self.b.ins().fadd(xm, y);
        let c1 = self.f(0.693_359_4);
        let r = self.fma(e, c1, r);
        // Special values.
        let inf = self.f(f32::INFINITY);
        let is_inf = self.cmp(FloatCC::Equal, x0, inf);
        let r = self.select(is_inf, inf, r);
        let is_zero = self.cmp(FloatCC::Equal, x0, zero);
        let ninf = self.f(f32::NEG_INFINITY);
        let r = self.select(is_zero, ninf, r);
        let invalid = self.cmp(FloatCC::UnorderedOrLessThan, x0, zero);
        let nan = self.f(f32::NAN);
        self.select(invalid, nan, r)
    }

    /// Reduces x by multiples of π/2: returns (r, q) with x = r + q·π/2, |r| ≤ π/4, q as i32 lanes.
    fn reduce_half_pi(&mut self, x: Value) -> (Value, Value) {
        let two_over_pi = self.f(std::f32::consts::FRAC_2_PI);
        let t = self.b.ins().fmul(x, two_over_pi);
        let k = self.b.ins().nearest(t);
        let nk = self.b.ins().fneg(k);
        let (p1, p2, p3) = (self.f(1.570_312_5), self.f(4.837_513e-4), self.f(7.549_79e-8));
        let r = self.fma(nk, p1, x);
        let r = self.fma(nk, p2, r);
        let r = self.fma(nk, p3, r);
        let q = self.truncate_to_int(k);
        (r, q)
    }

    /// (sin r, cos r) for |r| ≤ π/4.
    fn sincos_poly(&mut self, r: Value) -> (Value, Value) {
        let z = self.b.ins().fmul(r, r);
        let ps = self.horner(z, &[-1.951_529_6e-4, 8.332_161e-3, -1.666_665_5e-1]);
        let ps = self.b.ins().fmul(ps, z);
        let s = self.fma(ps, r, r);
        let pc = self.horner(z, &[2.443_315_7e-5, -1.388_731_6e-3, 4.166_664_6e-2]);
        let z2 = self.b.ins().fmul(z, z);
        let mhalf = self.f(-0.5);
        let one = self.f(1.0);
        let c = self.fma(z, mhalf, one);
        let c = self.fma(pc, z2, c);
        (s, c)
    }

    /// A lane mask (as f32 lanes) of the odd quadrants q.
    fn odd_mask(&mut self, q: Value) -> Value {
        let one = self.i(1);
        let odd = self.b.ins().band(q, one);
        let zero = self.i(0);
        let odd = self.b.ins().icmp(IntCC::NotEqual, odd, zero);
        self.float(odd)
    }

    /// sin x (`phase` = 0) or cos x (`phase` = 1), always in [−1, 1].
    pub fn sin_cos(&mut self, x: Value, phase: i32) -> Value {
        let (r, q) = self.reduce_half_pi(x);
        let (s, c) = self.sincos_poly(r);
        let q = if phase == 0 {
            q
        } else {
            let p = self.i(phase);
            self.b.ins().iadd(q, p)
        };
        let odd = self.odd_mask(q);
        let v = self.select(odd, c, s);
        let two = self.i(2);
        let sign = self.b.ins().band(q, two);
        let sign = self.b.ins().ishl_imm_s(sign, 30);
        let vb = self.bits(v);
        let vb = self.b.ins().bxor(vb, sign);
        let v = self.float(vb);
        // For large |x| the three-part reduction loses r (and past 2³¹·π/2 the quadrant), and the
        // polynomial of a large r is no sine: keep the result in [−1, 1] (NaN stays NaN).
        let (one, minus_one) = (self.f(1.0), self.f(-1.0));
        let v = self.min(v, one);
        self.max(v, minus_one)
    }

    /// tan x.
    pub fn tan(&mut self, x: Value) -> Value {
        let (r, q) = self.reduce_half_pi(x);
        let (s, c) = self.sincos_poly(r);
        let odd = self.odd_mask(q);
        let t_even = self.b.ins().fdiv(s, c);
        let nc = self.b.ins().fneg(c);
        let t_odd = self.b.ins().fdiv(nc, s);
        self.select(odd, t_odd, t_even)
    }

    /// 1 / (1 + e⁻ˣ)
    pub fn sigmoid(&mut self, x: Value) -> Value {
        let nx = self.b.ins().fneg(x);
        let e = self.exp(nx);
        let one = self.f(1.0);
        let d = self.b.ins().fadd(one, e);
        self.b.ins().fdiv(one, d)
    }

    /// tanh x = 1 − 2 / (e²ˣ + 1)
    pub fn tanh(&mut self, x: Value) -> Value {
        let x2 = self.b.ins().fadd(x, x);
        let e = self.exp(x2);
        let one = self.f(1.0);
        let two = self.f(2.0);
        let d = self.b.ins().fadd(e, one);
        let q = self.b.ins().fdiv(two, d);
        self.b.ins().fsub(one, q)
    }

    /// ln(1 + eˣ) = max(x, 0) + ln(1 + e^−|x|)
    pub fn softplus(&mut self, x: Value) -> Value {
        let zero = self.f(0.0);
        let pos = self.max(x, zero);
        let a = self.b.ins().fabs(x);
        let na = self.b.ins().fneg(a);
        let e = self.exp(na);
        let one = self.f(1.0);
        let s = self.b.ins().fadd(one, e);
        let l = self.log(s);
        self.b.ins().fadd(pos, l)
    }
}

fn little() -> MemFlagsData {
    MemFlagsData::new().with_endianness(cranelift_codegen::ir::Endianness::Little)
}
