//! Deterministic maths shared by the simulator ([`crate::sim`]) and the fits
//! ([`crate::fit`]): bit-reproducible transcendental functions, Gaussian
//! sampling, and constants of the model shapes both use.
//!
//! Why it exists: the same tuning run must give bit-identical results
//! natively (server, benchmarks, tests) and in wasm (the browser's local
//! mode); the golden hashes in `shared/tests/wasm.rs` and
//! `shared/tests/sim_determinism.rs` hold both targets to that.
//! `f64::exp`, `ln` and `tanh` call the platform's libm: glibc natively,
//! a Rust port of FreeBSD's msun on `wasm32-unknown-unknown`. Both are
//! accurate to < 1 ulp but do not always round the same way, so simulated
//! traces and fitted values built on them would differ in the last bit
//! between native and wasm. Everything here uses only IEEE-754
//! `+ − × ÷ sqrt` and exact bit manipulation, which are identical on every
//! target, so the same seed gives bit-identical data and fits everywhere.
//!
//! For the same reason Gaussian noise is drawn with [`StandardNormal`]
//! (Marsaglia's polar method on [`ln`]) instead of
//! `rand_distr::StandardNormal`, whose ziggurat calls the platform's `exp`
//! and `ln` in its wedge and tail.
//!
//! This module depends on nothing else in the crate, so `fit` can use it
//! without depending on `sim`.

// The polynomial coefficients below are the published FreeBSD/musl values,
// kept verbatim (they round to the intended f64s) so they can be checked
// against the source.
#![allow(clippy::excessive_precision)]

use rand::Rng;
use rand_distr::Distribution;

const LN2_HI: f64 = 6.931_471_803_691_238_164_90e-1;
const LN2_LO: f64 = 1.908_214_929_270_587_700_02e-10;
const INV_LN2: f64 = std::f64::consts::LOG2_E;

/// 2^k as an `f64`, for `-1022 ≤ k ≤ 1023`.
fn pow2(k: i32) -> f64 {
    f64::from_bits(((0x3ff + k) as u64) << 52)
}

/// `e^x`, < 1 ulp (FreeBSD `e_exp.c` algorithm), identical on all targets.
///
/// ```
/// use spintune::detmath::exp;
/// assert!((exp(1.0) - std::f64::consts::E).abs() < 1e-15);
/// assert_eq!(exp(0.0), 1.0);
/// ```
pub fn exp(x: f64) -> f64 {
    const P1: f64 = 1.666_666_666_666_660_190_37e-1;
    const P2: f64 = -2.777_777_777_701_559_338_42e-3;
    const P3: f64 = 6.613_756_321_437_934_361_17e-5;
    const P4: f64 = -1.653_390_220_546_525_153_90e-6;
    const P5: f64 = 4.138_136_797_057_238_460_39e-8;
    if x.is_nan() {
        return x;
    }
    if x > 709.782_712_893_384 {
        return f64::INFINITY;
    }
    if x < -745.133_219_101_941_1 {
        return 0.0;
    }
    if x.abs() < 1.0 / (1u64 << 28) as f64 {
        return 1.0 + x;
    }
    let k = (x * INV_LN2).round();
    let hi = x - k * LN2_HI;
    let lo = k * LN2_LO;
    let r = hi - lo;
    let t = r * r;
    let c = r - t * (P1 + t * (P2 + t * (P3 + t * (P4 + t * P5))));
    let y = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi);
    let k = k as i32;
    if k > 1023 {
        y * pow2(1023) * pow2(k - 1023)
    } else if k < -1022 {
        y * pow2(-1022) * pow2(k + 1022)
    } else {
        y * pow2(k)
    }
}

/// Natural logarithm, < 1 ulp (FreeBSD/musl `log` algorithm), identical on
/// all targets. `ln(0) = −∞`, `ln(x<0) = NaN`.
///
/// ```
/// use spintune::detmath::ln;
/// assert!((ln(10.0) - std::f64::consts::LN_10).abs() < 1e-15);
/// assert_eq!(ln(1.0), 0.0);
/// ```
pub fn ln(x: f64) -> f64 {
    const LG1: f64 = 6.666_666_666_666_735_130e-1;
    const LG2: f64 = 3.999_999_999_940_941_908e-1;
    const LG3: f64 = 2.857_142_874_366_239_149e-1;
    const LG4: f64 = 2.222_219_843_214_978_396e-1;
    const LG5: f64 = 1.818_357_216_161_805_012e-1;
    const LG6: f64 = 1.531_383_769_920_937_332e-1;
    const LG7: f64 = 1.479_819_860_511_658_591e-1;
    let mut x = x;
    let mut ix = x.to_bits();
    let mut hx = (ix >> 32) as u32;
    let mut k: i32 = 0;
    if hx < 0x0010_0000 || (hx >> 31) != 0 {
        if ix << 1 == 0 {
            return f64::NEG_INFINITY;
        }
        if hx >> 31 != 0 {
            return f64::NAN;
        }
        // Subnormal: scale up.
        k -= 54;
        x *= pow2(54);
        ix = x.to_bits();
        hx = (ix >> 32) as u32;
    } else if hx >= 0x7ff0_0000 {
        return x;
    } else if hx == 0x3ff0_0000 && ix << 32 == 0 {
        return 0.0;
    }
    hx = hx.wrapping_add(0x3ff0_0000 - 0x3fe6_a09e);
    k += (hx >> 20) as i32 - 0x3ff;
    hx = (hx & 0x000f_ffff) + 0x3fe6_a09e;
    ix = ((hx as u64) << 32) | (ix & 0xffff_ffff);
    let m = f64::from_bits(ix);
    let f = m - 1.0;
    let hfsq = 0.5 * f * f;
    let s = f / (2.0 + f);
    let z = s * s;
    let w = z * z;
    let t1 = w * (LG2 + w * (LG4 + w * LG6));
    let t2 = z * (LG1 + w * (LG3 + w * (LG5 + w * LG7)));
    let r = t2 + t1;
    let dk = k as f64;
    s * (hfsq + r) + dk * LN2_LO - hfsq + f + dk * LN2_HI
}

/// Hyperbolic tangent (absolute error ≲ 2e-16), identical on all targets.
///
/// ```
/// use spintune::detmath::tanh;
/// assert!((tanh(0.5) - 0.5f64.tanh()).abs() < 1e-15);
/// assert_eq!(tanh(-30.0), -1.0);
/// ```
pub fn tanh(x: f64) -> f64 {
    let a = x.abs();
    if x.is_nan() {
        return x;
    }
    let t = if a > 22.0 {
        1.0
    } else if a < 1e-9 {
        a
    } else if a < 0.5 {
        // tanh(a) = m / (m + 2) with m = e^{2a} − 1 from its Taylor series
        // (|2a| < 1: 19 terms are below 1e-17 relative).
        let u = 2.0 * a;
        let mut term = u;
        let mut m = u;
        for n in 2..=19 {
            term *= u / n as f64;
            m += term;
        }
        m / (m + 2.0)
    } else {
        1.0 - 2.0 / (exp(2.0 * a) + 1.0)
    };
    if x < 0.0 {
        -t
    } else {
        t
    }
}

/// `sech²(x) = 1 − tanh²(x)`, computed without cancellation, identical on all targets.
///
/// ```
/// use spintune::detmath::sech2;
/// assert_eq!(sech2(0.0), 1.0);
/// assert!((sech2(1.0) - 1.0 / 1f64.cosh().powi(2)).abs() < 1e-15);
/// ```
pub fn sech2(x: f64) -> f64 {
    let e = exp(-2.0 * x.abs());
    4.0 * e / ((1.0 + e) * (1.0 + e))
}

/// `atanh(1/√3)`: position of the steepest point of `sech²(x/γ)` relative to
/// its centre, in units of its width `γ` (where the second derivative
/// vanishes: `tanh²(x/γ) = 1/3`). Used by the simulated sensing dot and by
/// the sensing-dot peak fit.
///
/// ```
/// use spintune::detmath::STEEPEST_SECH2_OFFSET;
/// assert!((STEEPEST_SECH2_OFFSET - (1.0 / 3f64.sqrt()).atanh()).abs() < 1e-15);
/// ```
pub const STEEPEST_SECH2_OFFSET: f64 = 0.658_478_948_462_408_4;

/// `max |d/dz sech²(z)| = 4/(3√3)`, reached at `z = ±`[`STEEPEST_SECH2_OFFSET`].
/// Used by the simulated sensing dot and by the sensing-dot peak fit.
///
/// ```
/// use spintune::detmath::{sech2, tanh, MAX_SECH2_SLOPE, STEEPEST_SECH2_OFFSET};
/// assert!((MAX_SECH2_SLOPE - 4.0 / (3.0 * 3f64.sqrt())).abs() < 1e-15);
/// // d/dz sech²(z) = −2 sech²(z) tanh(z)
/// let z = STEEPEST_SECH2_OFFSET;
/// assert!((2.0 * sech2(z) * tanh(z) - MAX_SECH2_SLOPE).abs() < 1e-15);
/// ```
pub const MAX_SECH2_SLOPE: f64 = 0.769_800_358_919_501;

/// The standard normal distribution N(0, 1), sampled with Marsaglia's polar
/// method using only [`ln`] and `sqrt`, so that samples are bit-identical on
/// every target for the same RNG state.
///
/// ```
/// use rand::SeedableRng;
/// use rand_distr::Distribution;
/// use spintune::detmath::StandardNormal;
/// let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
/// let x: f64 = StandardNormal.sample(&mut rng);
/// assert!(x.is_finite());
/// ```
#[derive(Debug, Clone, Copy, Default)]
pub struct StandardNormal;

impl Distribution<f64> for StandardNormal {
    fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> f64 {
        loop {
            let u = 2.0 * rng.gen::<f64>() - 1.0;
            let v = 2.0 * rng.gen::<f64>() - 1.0;
            let s = u * u + v * v;
            if s > 0.0 && s < 1.0 {
                return u * (-2.0 * ln(s) / s).sqrt();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_matches_std_to_an_ulp() {
        let mut x = -700.0;
        while x < 700.0 {
            let (a, b) = (exp(x), x.exp());
            assert!(((a - b) / b).abs() <= 2.3e-16, "exp({x}): {a} vs {b}");
            x += 0.123_456_7;
        }
        assert_eq!(exp(f64::NEG_INFINITY), 0.0);
        assert_eq!(exp(1000.0), f64::INFINITY);
        assert!(exp(-740.0) > 0.0);
    }

    #[test]
    fn ln_matches_std_to_an_ulp() {
        let mut x = 1e-300;
        while x < 1e300 {
            let (a, b) = (ln(x), x.ln());
            assert!(
                (a - b).abs() <= 2.3e-16 * b.abs().max(1.0),
                "ln({x}): {a} vs {b}"
            );
            x *= 1.37;
        }
        for x in [0.5, 0.999_999, 1.000_001, 2.0, 5e-320] {
            assert!((ln(x) - x.ln()).abs() <= 2.3e-16 * x.ln().abs().max(1e-6));
        }
        assert!(ln(-1.0).is_nan());
    }

    #[test]
    fn tanh_and_sech2_match_std() {
        let mut x = -25.0;
        while x < 25.0 {
            assert!((tanh(x) - x.tanh()).abs() < 3e-16, "tanh({x})");
            let s = 1.0 / x.cosh().powi(2);
            assert!(
                (sech2(x) - s).abs() < 1e-15 * s.max(1e-300) + 1e-300,
                "sech2({x})"
            );
            x += 0.0137;
        }
        assert!((tanh(1e-5) - 1e-5f64.tanh()).abs() < 1e-20);
    }

    #[test]
    fn normal_moments() {
        use rand::SeedableRng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let n = 20_000;
        let xs: Vec<f64> = (0..n).map(|_| StandardNormal.sample(&mut rng)).collect();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 0.03, "{mean}");
        assert!((var - 1.0).abs() < 0.04, "{var}");
    }
}
