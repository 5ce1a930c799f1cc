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

/// One pixel column of [`min_max`]: (column, first, min, max, last point).
type Column = (usize, (f64, f64), (f64, f64), (f64, f64), (f64, f64));

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
    let n = inside().count();
    if n <= 2 * columns.max(1) {
        return inside().collect();
    }
    let mut out = Vec::with_capacity(4 * columns);
    let mut cur: Option<Column> = None;
    let flush = |c: &Column, out: &mut Vec<(f64, f64)>| {
        let (_, first, lo, hi, last) = *c;
        let mut pts = [first, lo, hi, last];
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        for p in pts {
            if out.last() != Some(&p) {
                out.push(p);
            }
        }
    };
    for p in inside() {
        let Some(col) = column(p.0, x0, x1, columns) else {
            continue;
        };
        match &mut cur {
            Some(c) if c.0 == col => {
                if p.1 < c.2 .1 {
                    c.2 = p;
                }
                if p.1 > c.3 .1 {
                    c.3 = p;
                }
                c.4 = p;
            }
            _ => {
                if let Some(c) = &cur {
                    flush(c, &mut out);
                }
                cur = Some((col, p, p, p, p));
            }
        }
    }
    if let Some(c) = &cur {
        flush(c, &mut out);
    }
    out
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
    let n = inside().count();
    if n <= 2 * columns.max(1) {
        return inside().collect();
    }
    let mut out: Vec<(f64, f64, f64)> = Vec::with_capacity(columns);
    let mut cur: Option<(usize, f64, usize, f64, f64)> = None; // col, Σx, count, lo, hi
    for (x, lo, hi) in inside() {
        let Some(col) = column(x, x0, x1, columns) else {
            continue;
        };
        match &mut cur {
            Some(c) if c.0 == col => {
                c.1 += x;
                c.2 += 1;
                c.3 = c.3.min(lo);
                c.4 = c.4.max(hi);
            }
            _ => {
                if let Some(c) = cur {
                    out.push((c.1 / c.2 as f64, c.3, c.4));
                }
                cur = Some((col, x, 1, lo, hi));
            }
        }
    }
    if let Some(c) = cur {
        out.push((c.1 / c.2 as f64, c.3, c.4));
    }
    out
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
