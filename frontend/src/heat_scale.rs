//! The colour scale of a heat map of magnitudes (the array overview's
//! |Jacobian|, [`crate::array_view::HeatMap`]): logarithmic over
//! [`LogScale::DECADES`] decades ending at the power of ten at or above the
//! largest value, light (small) to dark blue (large); values at or below
//! its bottom (exact zeros too) get its lightest colour, missing values a
//! grey of their own.

/// A log₁₀ colour scale from `lo` to `hi` (both powers of ten).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LogScale {
    /// Bottom (lightest colour and below).
    pub lo: f64,
    /// Top (darkest colour).
    pub hi: f64,
}

/// Colour of a missing value (no estimate).
pub const MISSING: &str = "rgb(200,200,200)";

/// Sequential ramp, light to dark (ColorBrewer "Blues"): readable in grey
/// and for colour-blind readers.
const RAMP: [(u8, u8, u8); 5] = [
    (247, 251, 255),
    (198, 219, 239),
    (107, 174, 214),
    (33, 113, 181),
    (8, 48, 107),
];

impl LogScale {
    /// Decades the scale spans.
    pub const DECADES: i32 = 3;

    /// The scale for values up to `max`: top the power of ten at or above
    /// it, bottom [`Self::DECADES`] below (0.001 … 1 without a positive,
    /// finite `max`).
    pub fn for_max(max: f64) -> Self {
        let top = if max.is_finite() && max > 0.0 {
            max.log10().ceil() as i32
        } else {
            0
        };
        Self {
            lo: pow10(top - Self::DECADES),
            hi: pow10(top),
        }
    }

    /// Where `v` lies on the scale, 0 (bottom or below) to 1 (top or
    /// above); `None` for a missing value (NaN).
    pub fn fraction(&self, v: f64) -> Option<f64> {
        if v.is_nan() {
            return None;
        }
        if v <= self.lo {
            return Some(0.0);
        }
        let f = (v / self.lo).log10() / (self.hi / self.lo).log10();
        Some(f.clamp(0.0, 1.0))
    }

    /// CSS colour of `v` ([`MISSING`] for NaN).
    pub fn colour(&self, v: f64) -> String {
        match self.fraction(v) {
            None => MISSING.to_string(),
            Some(f) => {
                let (r, g, b) = ramp(f);
                format!("rgb({r},{g},{b})")
            }
        }
    }

    /// Whether text on `v`'s colour should be light (dark background).
    pub fn dark(&self, v: f64) -> bool {
        self.fraction(v).is_some_and(|f| f > 0.55)
    }

    /// The ticks: every power of ten from bottom to top.
    pub fn ticks(&self) -> Vec<f64> {
        let (a, b) = (
            self.lo.log10().round() as i32,
            self.hi.log10().round() as i32,
        );
        (a..=b).map(pow10).collect()
    }
}

/// 10^e, correctly rounded (as the literal `1e{e}`).
fn pow10(e: i32) -> f64 {
    format!("1e{e}").parse().unwrap_or(f64::NAN)
}

/// The ramp's colour at `t` ∈ [0, 1] (linear between its stops).
pub fn ramp(t: f64) -> (u8, u8, u8) {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = t * (RAMP.len() - 1) as f64;
    let i = (x.floor() as usize).min(RAMP.len() - 2);
    let f = x - i as f64;
    let (a, b) = (RAMP[i], RAMP[i + 1]);
    let m = |p: u8, q: u8| (p as f64 + (q as f64 - p as f64) * f).round() as u8;
    (m(a.0, b.0), m(a.1, b.1), m(a.2, b.2))
}

/// A power of ten as text, e.g. `0.001` → `"10⁻³"`, `1` → `"1"`, `10` → `"10"`.
pub fn power_label(v: f64) -> String {
    if !(v.is_finite() && v > 0.0) {
        return "0".to_string();
    }
    let e = v.log10().round() as i32;
    match e {
        0 => "1".to_string(),
        1 => "10".to_string(),
        _ => {
            const SUP: [char; 10] = ['⁰', '¹', '²', '³', '⁴', '⁵', '⁶', '⁷', '⁸', '⁹'];
            let digits: String = e
                .unsigned_abs()
                .to_string()
                .chars()
                .map(|d| SUP[d.to_digit(10).unwrap_or(0) as usize])
                .collect();
            format!("10{}{digits}", if e < 0 { "⁻" } else { "" })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn three_decades_up_to_the_power_of_ten_above_the_largest_value() {
        let s = LogScale::for_max(0.066);
        assert_eq!((s.lo, s.hi), (1e-4, 0.1));
        assert_eq!(s.ticks().len(), 4);
        assert_eq!(
            s.ticks()
                .iter()
                .map(|t| power_label(*t))
                .collect::<Vec<_>>(),
            ["10⁻⁴", "10⁻³", "10⁻²", "10⁻¹"]
        );
        let exact = LogScale::for_max(1.0);
        assert_eq!((exact.lo, exact.hi), (1e-3, 1.0));
        assert_eq!(LogScale::for_max(f64::NAN), exact);
        assert_eq!(LogScale::for_max(0.0), exact);
        assert_eq!(power_label(10.0), "10");
        assert_eq!(power_label(1000.0), "10³");
        assert_eq!(power_label(1e-12), "10⁻¹²");
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn colours_grow_darker_with_the_value_and_missing_is_grey() {
        let s = LogScale::for_max(0.05);
        assert_eq!(s.fraction(0.1), Some(1.0));
        assert_eq!(s.fraction(1.0), Some(1.0));
        assert_eq!(s.fraction(0.0), Some(0.0));
        assert_eq!(s.fraction(1e-9), Some(0.0));
        assert!((s.fraction(0.01).unwrap() - 2.0 / 3.0).abs() < 1e-12);
        assert_eq!(s.fraction(f64::NAN), None);
        assert_eq!(s.colour(f64::NAN), MISSING);
        assert_eq!(s.colour(0.0), "rgb(247,251,255)");
        assert_eq!(s.colour(0.1), "rgb(8,48,107)");
        let lum = |v: f64| {
            let (r, g, b) = ramp(s.fraction(v).unwrap());
            r as u32 + g as u32 + b as u32
        };
        let vs = [1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 0.1];
        assert!(vs.windows(2).all(|w| lum(w[0]) > lum(w[1])), "monotone");
        assert!(!s.dark(1e-4) && s.dark(0.1));
    }
}
