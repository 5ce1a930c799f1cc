//! Decimation of long series for drawing: at most a few points per pixel
//! column, **preserving extremes** (a one-point spike in 100,000 stays
//! visible).
//!
//! [`min_max`] is the M4 scheme: for every pixel column it keeps the first,
//! the smallest, the largest and the last point (in x order), so the drawn
//! polyline covers exactly the same vertical extent in every column as the
//! full series. [`envelope`] does the same for bands (lower/upper bound per
//! point, e.g. value ∓ 1σ): per column the smallest lower and the largest
//! upper bound.
//!
//! Both are pure and O(n) in the number of input points; the output has at
//! most `4 × columns` points ([`min_max`]) or `columns` ([`envelope`]).

/// Column of x in `[x0, x1)` split into `columns` equal columns (`None`
/// outside the range or for a non-finite x).
fn column(x: f64, x0: f64, x1: f64, columns: usize) -> Option<usize> {
    if !x.is_finite() || x < x0 || x > x1 || columns == 0 {
        return None;
    }
    let span = x1 - x0;
    if span <= 0.0 {
        return Some(0);
    }
    Some((((x - x0) / span * columns as f64) as usize).min(columns - 1))
}

/// A band column: (x, lower, upper).
pub type Band = (f64, f64, f64);

/// Streaming decimation in one pass, without intermediate vectors: push
/// points (sorted by x) with an optional band `[lo, hi]`; per pixel column it
/// keeps the M4 points of the values (first, min, max, last) and the band's
/// envelope (mean x, smallest lo, largest hi). [`min_max`] and [`envelope`]
/// are this with all points at once.
#[derive(Debug, Clone)]
pub struct Columns {
    x0: f64,
    x1: f64,
    columns: usize,
    line: Vec<(f64, f64)>,
    bands: Vec<(f64, f64, f64)>,
    cur: Option<Col>,
}

#[derive(Debug, Clone, Copy)]
struct Col {
    index: usize,
    first: (f64, f64),
    min: (f64, f64),
    max: (f64, f64),
    last: (f64, f64),
    sum_x: f64,
    n: usize,
    lo: f64,
    hi: f64,
}

impl Columns {
    /// Decimate over `[x0, x1]` into `columns` pixel columns.
    pub fn new(x0: f64, x1: f64, columns: usize) -> Self {
        Self {
            x0,
            x1,
            columns: columns.max(1),
            line: Vec::with_capacity(4 * columns),
            bands: Vec::with_capacity(columns),
            cur: None,
        }
    }

    fn flush(&mut self) {
        let Some(c) = self.cur.take() else { return };
        let mut pts = [c.first, c.min, c.max, c.last];
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        for p in pts {
            if self.line.last() != Some(&p) {
                self.line.push(p);
            }
        }
        if c.lo.is_finite() && c.hi.is_finite() {
            self.bands.push((c.sum_x / c.n as f64, c.lo, c.hi));
        }
    }

    /// Add a point `(x, y)` with band `[lo, hi]` (NaN: no band). Points with
    /// a non-finite x or y, or outside the range, are ignored.
    #[inline]
    pub fn push(&mut self, x: f64, y: f64, lo: f64, hi: f64) {
        if !y.is_finite() {
            return;
        }
        let Some(index) = column(x, self.x0, self.x1, self.columns) else {
            return;
        };
        let p = (x, y);
        match &mut self.cur {
            Some(c) if c.index == index => {
                if y < c.min.1 {
                    c.min = p;
                }
                if y > c.max.1 {
                    c.max = p;
                }
                c.last = p;
                c.sum_x += x;
                c.n += 1;
                c.lo = c.lo.min(lo);
                c.hi = c.hi.max(hi);
            }
            _ => {
                self.flush();
                self.cur = Some(Col {
                    index,
                    first: p,
                    min: p,
                    max: p,
                    last: p,
                    sum_x: x,
                    n: 1,
                    lo,
                    hi,
                });
            }
        }
    }

    /// The decimated line (at most 4 points per column, in x order) and the
    /// band envelope (one per column with a finite band).
    pub fn finish(mut self) -> (Vec<(f64, f64)>, Vec<Band>) {
        self.flush();
        (self.line, self.bands)
    }
}

/// M4 decimation of `points` (sorted by x; non-finite y are skipped) to at
/// most 4 points per pixel column over the x range `[x0, x1]` (points outside
/// are dropped). Within each column the output is in x order and contains
/// the column's first, minimum, maximum and last point (duplicates merged).
///
/// If the range holds no more than `2 × columns` points they are returned
/// unchanged (nothing to gain).
pub fn min_max(points: &[(f64, f64)], x0: f64, x1: f64, columns: usize) -> Vec<(f64, f64)> {
    let inside = || {
        points
            .iter()
            .copied()
            .filter(|&(x, y)| y.is_finite() && x.is_finite() && x >= x0 && x <= x1)
    };
    if inside().count() <= 2 * columns.max(1) {
        return inside().collect();
    }
    let mut c = Columns::new(x0, x1, columns);
    for (x, y) in points {
        c.push(*x, *y, f64::NAN, f64::NAN);
    }
    c.finish().0
}

/// Band decimation: `points` are `(x, lower, upper)` sorted by x. Per pixel
/// column over `[x0, x1]`: the column's mean x, the smallest lower and the
/// largest upper bound. Fewer than `2 × columns` points in range are returned
/// unchanged.
pub fn envelope(
    points: &[(f64, f64, f64)],
    x0: f64,
    x1: f64,
    columns: usize,
) -> Vec<(f64, f64, f64)> {
    let inside = || {
        points.iter().copied().filter(|&(x, lo, hi)| {
            x.is_finite() && lo.is_finite() && hi.is_finite() && x >= x0 && x <= x1
        })
    };
    if inside().count() <= 2 * columns.max(1) {
        return inside().collect();
    }
    let mut c = Columns::new(x0, x1, columns);
    for (x, lo, hi) in inside() {
        c.push(x, (lo + hi) / 2.0, lo, hi);
    }
    c.finish().1
}

#[cfg(test)]
mod tests {
    use super::*;

    fn noisy(n: usize) -> Vec<(f64, f64)> {
        (0..n)
            .map(|i| {
                let x = i as f64;
                (
                    x,
                    (x * 0.37).sin() + 0.1 * ((x * 12.9898).sin() * 43758.5453).fract(),
                )
            })
            .collect()
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_one_point_spike_in_100000_survives() {
        let mut pts = noisy(100_000);
        pts[73_219].1 = 50.0;
        pts[12_345].1 = -40.0;
        let out = min_max(&pts, 0.0, 99_999.0, 800);
        assert!(out.len() <= 4 * 800, "{} points", out.len());
        assert!(out.len() > 800, "too few: {}", out.len());
        assert!(out.contains(&(73_219.0, 50.0)), "spike lost");
        assert!(out.contains(&(12_345.0, -40.0)), "dip lost");
        // Sorted by x and the same extremes as the input.
        assert!(out.windows(2).all(|w| w[0].0 <= w[1].0));
        let max = out.iter().map(|p| p.1).fold(f64::MIN, f64::max);
        let min = out.iter().map(|p| p.1).fold(f64::MAX, f64::min);
        assert_eq!((min, max), (-40.0, 50.0));
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn every_column_keeps_its_vertical_extent() {
        let pts = noisy(10_000);
        let cols = 97;
        let out = min_max(&pts, 0.0, 9_999.0, cols);
        for c in 0..cols {
            let ext = |s: &[(f64, f64)]| {
                s.iter()
                    .filter(|p| column(p.0, 0.0, 9_999.0, cols) == Some(c))
                    .fold((f64::MAX, f64::MIN), |(lo, hi), p| {
                        (lo.min(p.1), hi.max(p.1))
                    })
            };
            assert_eq!(ext(&pts), ext(&out), "column {c}");
        }
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn range_selects_and_short_series_pass_through() {
        let pts = noisy(1_000);
        // A zoomed window: only points inside it.
        let out = min_max(&pts, 100.0, 199.0, 800);
        assert_eq!(out.len(), 100);
        assert_eq!(out.first().unwrap().0, 100.0);
        assert_eq!(out.last().unwrap().0, 199.0);
        // NaN values are skipped, not drawn.
        let mut with_nan = noisy(10);
        with_nan[3].1 = f64::NAN;
        assert_eq!(min_max(&with_nan, 0.0, 9.0, 800).len(), 9);
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn envelope_keeps_the_widest_band() {
        let mut band: Vec<(f64, f64, f64)> = (0..100_000).map(|i| (i as f64, -1.0, 1.0)).collect();
        band[55_555] = (55_555.0, -9.0, 30.0);
        let out = envelope(&band, 0.0, 99_999.0, 500);
        assert_eq!(out.len(), 500);
        assert!(out.iter().any(|p| p.1 == -9.0 && p.2 == 30.0));
        assert_eq!(out.iter().filter(|p| p.2 > 1.0).count(), 1);
    }
}
