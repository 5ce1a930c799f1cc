//! The iteration window shared by all charts: zoom, pan, "last N
//! iterations", drag-to-zoom. Pure arithmetic on iteration numbers (the x
//! axis in lab-time mode is derived from the same window).
//!
//! Invariants: a resolved [`Window`] lies inside the run's extent
//! `[first, last]` (iterations), has `lo ≤ hi` and spans at least
//! [`MIN_SPAN`] iterations when the run has that many.

/// The smallest window a zoom can reach, iterations.
pub const MIN_SPAN: f64 = 4.0;

/// A closed range of iterations `[lo, hi]` (fractional while dragging).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Window {
    /// First iteration shown.
    pub lo: f64,
    /// Last iteration shown.
    pub hi: f64,
}

impl Window {
    /// Width in iterations.
    pub fn span(&self) -> f64 {
        self.hi - self.lo
    }

    /// Whether iteration `k` is inside.
    pub fn contains(&self, k: f64) -> bool {
        k >= self.lo && k <= self.hi
    }
}

/// `w` with its end moved out to `lo` plus a whole number of steps of
/// max(10, a 1-2-5 step of about a tenth of its span) iterations: a window
/// that follows a live run keeps its x axis for many iterations (≈ 10 % of
/// the run, at least 10) instead of changing with every one. `lo` and the
/// iterations inside stay the same.
pub fn grow_in_steps(w: Window) -> Window {
    let span = w.span();
    if !(span.is_finite() && span > 0.0) {
        return w;
    }
    let step = crate::axis::nice_step(span / 10.0).max(10.0);
    Window {
        lo: w.lo,
        hi: w.lo + (span / step).ceil() * step,
    }
}

/// What the user chose; resolved against the run's extent with [`View::window`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum View {
    /// The whole run (follows new iterations).
    All,
    /// The newest `n` iterations (follows new iterations).
    Last(u64),
    /// A fixed window (after zoom, pan or drag).
    Fixed(Window),
}

/// Keep `w` inside `[first, last]` preserving its span where possible, with
/// at least [`MIN_SPAN`] (or the whole extent if it is shorter).
pub fn clamp(w: Window, first: f64, last: f64) -> Window {
    let extent = (last - first).max(0.0);
    let span = w.span().max(MIN_SPAN.min(extent)).min(extent);
    let mid = (w.lo + w.hi) / 2.0;
    let mut lo = mid - span / 2.0;
    lo = lo.max(first).min(last - span);
    Window { lo, hi: lo + span }
}

impl View {
    /// The window to draw for a run spanning iterations `[first, last]`.
    pub fn window(&self, first: f64, last: f64) -> Window {
        match *self {
            View::All => Window {
                lo: first,
                hi: last,
            },
            View::Last(n) => Window {
                lo: (last - n.saturating_sub(1) as f64).max(first),
                hi: last,
            },
            View::Fixed(w) => clamp(w, first, last),
        }
    }

    /// Zoom by `factor` (< 1 zooms in, > 1 out) around `center` (an
    /// iteration; `None`: the window's middle). Zooming out to the whole
    /// extent gives [`View::All`].
    pub fn zoom(&self, factor: f64, center: Option<f64>, first: f64, last: f64) -> View {
        let w = self.window(first, last);
        let c = center.unwrap_or((w.lo + w.hi) / 2.0).clamp(w.lo, w.hi);
        let lo = c - (c - w.lo) * factor;
        let hi = c + (w.hi - c) * factor;
        if hi - lo >= last - first {
            return View::All;
        }
        View::Fixed(clamp(Window { lo, hi }, first, last))
    }

    /// Pan by `fraction` of the window's span (negative: towards older iterations).
    pub fn pan(&self, fraction: f64, first: f64, last: f64) -> View {
        let w = self.window(first, last);
        if w.span() >= last - first {
            return *self;
        }
        let d = fraction * w.span();
        View::Fixed(clamp(
            Window {
                lo: w.lo + d,
                hi: w.hi + d,
            },
            first,
            last,
        ))
    }
}

/// Pixel → data coordinate on an axis whose plot area spans pixels
/// `[px0, px1]` for data `[d0, d1]` (clamped to the area).
pub fn pixel_to_data(px: f64, px0: f64, px1: f64, d0: f64, d1: f64) -> f64 {
    if px1 <= px0 {
        return d0;
    }
    let t = ((px - px0) / (px1 - px0)).clamp(0.0, 1.0);
    d0 + t * (d1 - d0)
}

/// The window selected by dragging from pixel `a` to pixel `b` over a plot
/// area `[px0, px1]` showing iterations `w`; `None` for a drag shorter than
/// 4 px (a click).
pub fn drag_window(a: f64, b: f64, px0: f64, px1: f64, w: Window) -> Option<Window> {
    if (a - b).abs() < 4.0 {
        return None;
    }
    let (a, b) = (a.min(b), a.max(b));
    Some(Window {
        lo: pixel_to_data(a, px0, px1, w.lo, w.hi),
        hi: pixel_to_data(b, px0, px1, w.lo, w.hi),
    })
}

/// How a parameter chart chooses its y range (the x window is shared, the
/// y range is each chart's own).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum YRange {
    /// Robust (the default): the accepted values, the bands that are not
    /// much wider than the median band, the targets with their tolerance
    /// bands, the compared run; values the tuner rejected and distrusted
    /// bands do not widen it.
    #[default]
    Auto,
    /// Everything drawn: rejected values and every band too.
    Full,
    /// `[lo, hi]` as typed (finite, `lo < hi`); values outside are pinned
    /// to the nearer edge and marked.
    Manual(f64, f64),
}

impl YRange {
    /// Menu value.
    pub fn name(self) -> &'static str {
        match self {
            YRange::Auto => "auto",
            YRange::Full => "full",
            YRange::Manual(..) => "manual",
        }
    }

    /// A manual range, if `lo < hi` and both are finite.
    pub fn manual(lo: f64, hi: f64) -> Option<YRange> {
        (lo.is_finite() && hi.is_finite() && lo < hi).then_some(YRange::Manual(lo, hi))
    }

    /// Part of a chart's redraw key.
    pub fn key(self) -> [u64; 3] {
        match self {
            YRange::Auto => [0, 0, 0],
            YRange::Full => [1, 0, 0],
            YRange::Manual(lo, hi) => [2, lo.to_bits(), hi.to_bits()],
        }
    }

    /// The y range to draw: `auto` is the robust range of the data, `full`
    /// the range of everything drawn; a manual range as it is.
    pub fn resolve(self, auto: (f64, f64), full: (f64, f64)) -> (f64, f64) {
        match self {
            YRange::Auto => auto,
            YRange::Full => full,
            YRange::Manual(lo, hi) => (lo, hi),
        }
    }
}

/// `v` inside `[y0, y1]`, and whether it had to be moved there (a value
/// outside the y range is drawn pinned to the nearer edge, marked).
pub fn pin(v: f64, (y0, y1): (f64, f64)) -> (f64, bool) {
    let c = v.clamp(y0, y1);
    (c, c != v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_y_range_is_robust_full_or_typed_and_pins_what_lies_outside() {
        let (auto, full) = ((10.0, 30.0), (-200.0, 500.0));
        assert_eq!(YRange::default(), YRange::Auto);
        assert_eq!(YRange::Auto.resolve(auto, full), auto);
        assert_eq!(YRange::Full.resolve(auto, full), full);
        assert_eq!(YRange::manual(5.0, 8.0), Some(YRange::Manual(5.0, 8.0)));
        assert_eq!(YRange::Manual(5.0, 8.0).resolve(auto, full), (5.0, 8.0));
        // Empty, reversed or non-finite manual ranges are refused.
        assert_eq!(YRange::manual(8.0, 8.0), None);
        assert_eq!(YRange::manual(8.0, 5.0), None);
        assert_eq!(YRange::manual(f64::NAN, 5.0), None);
        assert_eq!(YRange::manual(0.0, f64::INFINITY), None);
        // Each choice redraws the chart (its key differs).
        let keys = [
            YRange::Auto.key(),
            YRange::Full.key(),
            YRange::Manual(5.0, 8.0).key(),
            YRange::Manual(5.0, 9.0).key(),
        ];
        for (i, a) in keys.iter().enumerate() {
            for b in &keys[i + 1..] {
                assert_ne!(a, b);
            }
        }
        assert_eq!(pin(6.0, (5.0, 8.0)), (6.0, false));
        assert_eq!(pin(8.0, (5.0, 8.0)), (8.0, false));
        assert_eq!(pin(9.5, (5.0, 8.0)), (8.0, true));
        assert_eq!(pin(-1.0, (5.0, 8.0)), (5.0, true));
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_following_window_grows_in_steps() {
        let w = |lo: f64, hi: f64| Window { lo, hi };
        // Small runs: steps of 10 iterations.
        assert_eq!(grow_in_steps(w(0.0, 4.0)), w(0.0, 10.0));
        assert_eq!(grow_in_steps(w(0.0, 10.0)), w(0.0, 10.0));
        assert_eq!(grow_in_steps(w(0.0, 11.0)), w(0.0, 20.0));
        // Long runs: about a tenth of the span.
        assert_eq!(grow_in_steps(w(0.0, 99_999.0)), w(0.0, 100_000.0));
        assert_eq!(grow_in_steps(w(500.0, 1_730.0)), w(500.0, 1_900.0));
        // Every live iteration from 1,731 to 1,900 keeps that axis.
        for hi in 1_731..=1_900 {
            assert_eq!(grow_in_steps(w(500.0, hi as f64)), w(500.0, 1_900.0));
        }
        // Never shrinks, keeps lo; a single iteration stays as it is.
        for hi in [3.0, 47.0, 1234.5, 77_777.0] {
            let g = grow_in_steps(w(2.0, hi));
            assert!(
                g.lo == 2.0 && g.hi >= hi && g.hi - hi <= 0.25 * (hi - 2.0) + 10.0,
                "{hi} -> {g:?}"
            );
        }
        assert_eq!(grow_in_steps(w(7.0, 7.0)), w(7.0, 7.0));
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn zoom_in_and_out_around_a_point() {
        let (first, last) = (0.0, 99_999.0);
        let v = View::All.zoom(0.5, Some(80_000.0), first, last);
        let w = v.window(first, last);
        // The point under the cursor stays where it was (relative position kept).
        assert!(
            (w.lo - 40_000.0).abs() < 1e-6 && (w.hi - 89_999.5).abs() < 1e-6,
            "{w:?}"
        );
        assert!(w.contains(80_000.0));
        // Zooming back out reaches the whole run.
        assert_eq!(v.zoom(2.5, None, first, last), View::All);
        // Zoom in repeatedly: never below MIN_SPAN, always inside the run.
        let mut v = View::All;
        for _ in 0..60 {
            v = v.zoom(0.5, Some(99_999.0), first, last);
        }
        let w = v.window(first, last);
        assert!((w.span() - MIN_SPAN).abs() < 1e-9, "{w:?}");
        assert_eq!(w.hi, last);
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn pan_stays_inside_the_run() {
        let v = View::Fixed(Window {
            lo: 100.0,
            hi: 200.0,
        });
        let left = v.pan(-0.25, 0.0, 1000.0).window(0.0, 1000.0);
        assert_eq!(
            left,
            Window {
                lo: 75.0,
                hi: 175.0
            }
        );
        let far = v.pan(-50.0, 0.0, 1000.0).window(0.0, 1000.0);
        assert_eq!(far, Window { lo: 0.0, hi: 100.0 });
        let right = v.pan(50.0, 0.0, 1000.0).window(0.0, 1000.0);
        assert_eq!(
            right,
            Window {
                lo: 900.0,
                hi: 1000.0
            }
        );
        // The whole run cannot pan.
        assert_eq!(View::All.pan(0.5, 0.0, 1000.0), View::All);
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn last_n_follows_the_newest_iteration() {
        assert_eq!(
            View::Last(100).window(0.0, 999.0),
            Window {
                lo: 900.0,
                hi: 999.0
            }
        );
        assert_eq!(
            View::Last(100).window(0.0, 1999.0),
            Window {
                lo: 1900.0,
                hi: 1999.0
            }
        );
        // Fewer iterations than N: all of them.
        assert_eq!(
            View::Last(100).window(0.0, 9.0),
            Window { lo: 0.0, hi: 9.0 }
        );
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn drag_selects_the_pixels_between_press_and_release() {
        let w = Window {
            lo: 0.0,
            hi: 1000.0,
        };
        // Plot area from pixel 60 to 560: 2 iterations per pixel.
        let sel = drag_window(310.0, 160.0, 60.0, 560.0, w).unwrap();
        assert_eq!(
            sel,
            Window {
                lo: 200.0,
                hi: 500.0
            }
        );
        assert_eq!(drag_window(100.0, 102.0, 60.0, 560.0, w), None);
        // Outside the area: clamped to its edges.
        let sel = drag_window(0.0, 900.0, 60.0, 560.0, w).unwrap();
        assert_eq!(sel, w);
        let clamped = clamp(Window { lo: 5.0, hi: 5.5 }, 0.0, 1000.0);
        assert_eq!(clamped.span(), MIN_SPAN);
    }
}
