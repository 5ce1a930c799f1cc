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

/// A decimated series: the line's points and the band envelope.
pub type Decimated = (Vec<(f64, f64)>, Vec<Band>);

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

/// Branching factor of a [`Pyramid`]: a block of level 0 summarises `FAN`
/// points, a block of level `l` summarises `FAN` blocks of level `l − 1`.
const FAN: usize = 8;

/// Points per pixel column from which [`Pyramid::decimate`] aligns column
/// ends to blocks (below it the columns are exact).
pub const ALIGN_BELOW: usize = 8 * FAN;

/// Summary of consecutive points: the smallest and largest value with their
/// (first) index, the band envelope (smallest `y − σ`, largest `y + σ`) and
/// how many points had a finite value. Non-finite values are not counted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Block {
    /// Smallest value (+∞ if none).
    pub min: f64,
    /// Index of the first point with the smallest value.
    pub min_i: u32,
    /// Largest value (−∞ if none).
    pub max: f64,
    /// Index of the first point with the largest value.
    pub max_i: u32,
    /// Smallest `y − σ`.
    pub lo: f64,
    /// Largest `y + σ`.
    pub hi: f64,
    /// Points with a finite value.
    pub n: u32,
}

impl Block {
    /// No points.
    pub const EMPTY: Block = Block {
        min: f64::INFINITY,
        min_i: u32::MAX,
        max: f64::NEG_INFINITY,
        max_i: u32::MAX,
        lo: f64::INFINITY,
        hi: f64::NEG_INFINITY,
        n: 0,
    };

    /// Add point `i` with value `y` and σ `s` (a non-finite σ counts as 0;
    /// a non-finite `y` is ignored).
    #[inline]
    fn add_point(&mut self, i: usize, (y, s): (f64, f64)) {
        if !y.is_finite() {
            return;
        }
        let s = if s.is_finite() { s } else { 0.0 };
        self.add(&Block {
            min: y,
            min_i: i as u32,
            max: y,
            max_i: i as u32,
            lo: y - s,
            hi: y + s,
            n: 1,
        });
    }

    /// Merge another block (ties keep the smaller index, whatever the order).
    #[inline]
    fn add(&mut self, b: &Block) {
        if b.n == 0 {
            return;
        }
        if b.min < self.min || (b.min == self.min && b.min_i < self.min_i) {
            self.min = b.min;
            self.min_i = b.min_i;
        }
        if b.max > self.max || (b.max == self.max && b.max_i < self.max_i) {
            self.max = b.max;
            self.max_i = b.max_i;
        }
        self.lo = self.lo.min(b.lo);
        self.hi = self.hi.max(b.hi);
        self.n += b.n;
    }
}

/// A min/max pyramid over one series (values with an optional σ, indexed
/// like the history's rows): per block of [`FAN`] points, then per
/// [`FAN`] blocks and so on, the [`Block`] summary. The summary of any index
/// range takes O([`FAN`] × levels) steps instead of one per point, so
/// decimating a series to pixel columns ([`Pyramid::decimate`]) costs
/// O(columns × log n) whatever the number of points. Points appended at the
/// end update O(levels) blocks ([`Pyramid::update`]); about n / 7 blocks
/// (48 B each) are held.
///
/// The pyramid holds no values: every call takes the series as an accessor
/// `y(i) -> (value, σ)`, which must be the one the pyramid was built with.
#[derive(Debug, Clone, Default)]
pub struct Pyramid {
    /// `levels[l][b]`: block `b` of level `l` (`FAN^(l+1)` points).
    levels: Vec<Vec<Block>>,
    /// Points covered.
    len: usize,
}

impl Pyramid {
    /// The pyramid of points `0..n`.
    pub fn build(n: usize, y: impl Fn(usize) -> (f64, f64)) -> Self {
        let mut p = Self::default();
        p.update(n, 0, y);
        p
    }

    /// Points covered.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether no point is covered.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The series now has `n` points of which `from..n` are new or changed
    /// (points before `from` unchanged): recompute the blocks above them.
    pub fn update(&mut self, n: usize, from: usize, y: impl Fn(usize) -> (f64, f64)) {
        let from = from.min(self.len).min(n);
        self.len = n;
        let mut first = from / FAN;
        let mut count = n.div_ceil(FAN);
        let mut level = 0;
        loop {
            if self.levels.len() <= level {
                self.levels.push(Vec::new());
            }
            let (below, here) = self.levels.split_at_mut(level);
            let here = &mut here[0];
            here.truncate(first);
            for b in first..count {
                let mut blk = Block::EMPTY;
                if level == 0 {
                    for i in b * FAN..((b + 1) * FAN).min(n) {
                        blk.add_point(i, y(i));
                    }
                } else {
                    let prev = &below[level - 1];
                    for c in &prev[b * FAN..((b + 1) * FAN).min(prev.len())] {
                        blk.add(c);
                    }
                }
                here.push(blk);
            }
            if count <= 1 {
                self.levels.truncate(level + 1);
                break;
            }
            first /= FAN;
            count = count.div_ceil(FAN);
            level += 1;
        }
    }

    /// Summary of the points `a..b`.
    pub fn range(&self, a: usize, b: usize, y: impl Fn(usize) -> (f64, f64)) -> Block {
        let mut acc = Block::EMPTY;
        let (mut a, mut b) = (a, b.min(self.len));
        while a < b && a % FAN != 0 {
            acc.add_point(a, y(a));
            a += 1;
        }
        while b > a && b % FAN != 0 {
            b -= 1;
            acc.add_point(b, y(b));
        }
        let (mut a, mut b) = (a / FAN, b / FAN);
        for level in &self.levels {
            if a >= b {
                break;
            }
            while a < b && a % FAN != 0 {
                acc.add(&level[a]);
                a += 1;
            }
            while b > a && b % FAN != 0 {
                b -= 1;
                acc.add(&level[b]);
            }
            a /= FAN;
            b /= FAN;
        }
        acc
    }

    /// Decimate the points `rows` (their x, from `x(i)`, non-decreasing in
    /// `i`) over `[x0, x1]` into `columns` pixel columns: per column the
    /// first, smallest, largest and last point (M4, as [`Columns`]) and the
    /// band envelope at the middle of the column's first and last point.
    /// O(columns × log n).
    ///
    /// With fewer than [`ALIGN_BELOW`] points per column the columns are
    /// exactly those of [`Columns`]. With more, each column's end is moved
    /// back to a block boundary of the pyramid less than 1/8 of a column
    /// before it (so the summary is read from whole blocks, about three
    /// times fewer steps): a point may be counted in the column left of its
    /// own by under 1/8 pixel; every drawn point is still a real point and
    /// every extreme is kept.
    #[allow(clippy::too_many_arguments)]
    pub fn decimate(
        &self,
        rows: std::ops::Range<usize>,
        x: impl Fn(usize) -> f64,
        y: impl Fn(usize) -> (f64, f64),
        x0: f64,
        x1: f64,
        columns: usize,
    ) -> Decimated {
        let columns = columns.max(1);
        let mut line = Vec::with_capacity(4 * columns);
        let mut bands = Vec::with_capacity(columns);
        let end = rows.end.min(self.len);
        let part = |from: usize, pred: &dyn Fn(f64) -> bool| {
            // First index in from..end whose x fails `pred` (x non-decreasing).
            let (mut lo, mut hi) = (from, end);
            while lo < hi {
                let mid = lo + (hi - lo) / 2;
                if pred(x(mid)) {
                    lo = mid + 1;
                } else {
                    hi = mid;
                }
            }
            lo
        };
        let start = part(rows.start.min(end), &|v| v < x0);
        let stop = part(start, &|v| v <= x1);
        let per_column = (stop - start) / columns;
        // The largest block size (a power of FAN) under 1/8 of a column.
        let mut align = 1;
        if per_column >= ALIGN_BELOW {
            while align * FAN <= per_column / 8 {
                align *= FAN;
            }
        }
        // `cur`: first row of this chunk; `lead`: first row of this column
        // by x (later than `cur` when the previous chunk ended early at a
        // block boundary).
        let (mut cur, mut lead) = (start, start);
        while cur < stop {
            let Some(c) = column(x(lead), x0, x1, columns) else {
                lead += 1;
                if lead >= stop {
                    break;
                }
                continue;
            };
            let exact = {
                let (mut lo, mut hi) = (lead + 1, stop);
                while lo < hi {
                    let mid = lo + (hi - lo) / 2;
                    if column(x(mid), x0, x1, columns).is_some_and(|m| m <= c) {
                        lo = mid + 1;
                    } else {
                        hi = mid;
                    }
                }
                lo
            };
            // Block-aligned column end (see above).
            let next = if align > 1 && exact < stop {
                let a = exact / align * align;
                if a > cur {
                    a
                } else {
                    exact
                }
            } else {
                exact
            };
            let blk = self.range(cur, next, &y);
            if blk.n > 0 {
                let finite = |i: &usize| y(*i).0.is_finite();
                let f = (cur..next).find(finite).unwrap_or(cur);
                let l = (cur..next).rev().find(finite).unwrap_or(f);
                let (mi, ma) = (blk.min_i as usize, blk.max_i as usize);
                let mut pts = [
                    (x(f), y(f).0),
                    (x(mi), blk.min),
                    (x(ma), blk.max),
                    (x(l), y(l).0),
                ];
                pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                for p in pts {
                    if line.last() != Some(&p) {
                        line.push(p);
                    }
                }
                if blk.lo.is_finite() && blk.hi.is_finite() {
                    bands.push(((x(f) + x(l)) / 2.0, blk.lo, blk.hi));
                }
            }
            cur = next;
            lead = exact;
        }
        (line, bands)
    }
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

    /// A series with NaN stretches and σ: `(x, y, σ)`, x non-decreasing with
    /// repeats (like lab time).
    fn series(n: usize) -> Vec<(f64, f64, f64)> {
        noisy(n)
            .into_iter()
            .enumerate()
            .map(|(i, (_, y))| {
                let x = (i / 3) as f64 * 0.7 + (i % 3) as f64 * 0.2;
                let y = if i % 97 < 5 || (2_000..2_300).contains(&i) {
                    f64::NAN
                } else {
                    y
                };
                let s = if i % 13 == 0 {
                    f64::NAN
                } else {
                    0.1 + (i % 7) as f64 * 0.01
                };
                (x, y, s)
            })
            .collect()
    }

    fn by_columns(
        pts: &[(f64, f64, f64)],
        x0: f64,
        x1: f64,
        cols: usize,
    ) -> (Vec<(f64, f64)>, Vec<Band>) {
        let mut c = Columns::new(x0, x1, cols);
        for &(x, y, s) in pts {
            let s = if s.is_finite() { s } else { 0.0 };
            c.push(x, y, y - s, y + s);
        }
        c.finish()
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn pyramid_decimation_draws_the_same_line_and_band_extent_as_a_full_pass() {
        let pts = series(30_011);
        let y = |i: usize| (pts[i].1, pts[i].2);
        let x = |i: usize| pts[i].0;
        let p = Pyramid::build(pts.len(), y);
        let last = pts.last().unwrap().0;
        // Fewer than ALIGN_BELOW points per column: exactly the columns of a full pass.
        for (x0, x1, cols, rows) in [
            (-0.5, last + 0.5, 800, 0..pts.len()),
            (-0.5, last + 0.5, 480, 0..pts.len()),
            (1_000.0, 4_321.0, 333, 0..pts.len()),
            (1_000.0, 4_321.0, 333, 1_500..20_000),
            (400.0, 480.0, 800, 0..pts.len()),
        ] {
            let expect = by_columns(&pts[rows.clone()], x0, x1, cols);
            let got = p.decimate(rows.clone(), x, y, x0, x1, cols);
            assert_eq!(got.0, expect.0, "line over [{x0}, {x1}] in {cols} columns");
            assert_eq!(got.1.len(), expect.1.len());
            for (g, e) in got.1.iter().zip(&expect.1) {
                assert_eq!((g.1, g.2), (e.1, e.2), "band at {}", e.0);
                assert!((g.0 - e.0).abs() <= (x1 - x0) / cols as f64, "{g:?} {e:?}");
            }
        }
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn pyramid_columns_aligned_to_blocks_draw_real_points_and_every_columns_extent() {
        let mut pts = series(100_000);
        pts[73_219].1 = 900.0;
        pts[5].1 = -900.0;
        let y = |i: usize| (pts[i].1, pts[i].2);
        let x = |i: usize| pts[i].0;
        let p = Pyramid::build(pts.len(), y);
        let (x0, x1) = (-0.5, pts.last().unwrap().0 + 0.5);
        for cols in [97, 150, 440] {
            assert!(pts.len() / cols >= ALIGN_BELOW);
            let (line, bands) = p.decimate(0..pts.len(), x, y, x0, x1, cols);
            let (exact, exact_bands) = by_columns(&pts, x0, x1, cols);
            assert!(
                line.len() <= 4 * cols && line.len() >= cols,
                "{}",
                line.len()
            );
            assert!(line.windows(2).all(|w| w[0].0 <= w[1].0), "not in x order");
            assert!(line.contains(&(pts[73_219].0, 900.0)), "spike lost");
            assert!(line.contains(&(pts[5].0, -900.0)), "dip lost");
            // Every drawn point is a real point.
            for q in &line {
                assert!(
                    pts.iter().any(|r| r.0 == q.0 && r.1 == q.1),
                    "{q:?} is not a point"
                );
            }
            // Per pixel column: what is drawn there comes from that column or
            // its left neighbour, and its extent is drawn within one column.
            let ext = |s: &[(f64, f64)], c: std::ops::RangeInclusive<usize>| {
                s.iter()
                    .filter(|q| column(q.0, x0, x1, cols).is_some_and(|k| c.contains(&k)))
                    .fold((f64::MAX, f64::MIN), |(lo, hi), q| {
                        (lo.min(q.1), hi.max(q.1))
                    })
            };
            for c in 1..cols - 1 {
                let (lo, hi) = ext(&line, c..=c);
                let (elo, ehi) = ext(&exact, c - 1..=c);
                assert!(
                    lo >= elo && hi <= ehi,
                    "column {c}: {lo}..{hi} outside {elo}..{ehi}"
                );
                let (tlo, thi) = ext(&exact, c..=c);
                let (dlo, dhi) = ext(&line, c - 1..=c + 1);
                assert!(
                    dlo <= tlo && dhi >= thi,
                    "column {c}: extent {tlo}..{thi} not drawn"
                );
            }
            // The band's overall envelope is the same.
            let env = |b: &[Band]| {
                b.iter().fold((f64::MAX, f64::MIN), |(lo, hi), q| {
                    (lo.min(q.1), hi.max(q.2))
                })
            };
            assert_eq!(env(&bands), env(&exact_bands));
        }
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn pyramid_appended_point_by_point_equals_one_built_at_once_and_keeps_a_spike() {
        let mut pts = series(5_000);
        pts[4_321].1 = 900.0;
        let y = |i: usize| (pts[i].1, pts[i].2);
        let mut p = Pyramid::default();
        let mut n = 0;
        for step in [1, 1, 15, 16, 17, 255, 256, 257, 4_000, 182] {
            p.update(n + step, n, y);
            n += step;
        }
        assert_eq!(n, pts.len());
        let whole = Pyramid::build(pts.len(), y);
        assert_eq!(p.levels, whole.levels);
        let all = p.range(0, n, y);
        assert_eq!((all.max, all.max_i), (900.0, 4_321));
        // One point changed in the middle (a merge rebuilds from there).
        pts[10].1 = -50.0;
        let y = |i: usize| (pts[i].1, pts[i].2);
        p.update(n, 10, y);
        assert_eq!(p.levels, Pyramid::build(n, y).levels);
        assert_eq!(p.range(0, n, y).min, -50.0);
        // A one-point spike in 100,000 points decimated to 800 columns.
        let mut big = noisy(100_000);
        big[73_219].1 = 900.0;
        let p = Pyramid::build(big.len(), |i| (big[i].1, 0.0));
        let (line, _) = p.decimate(
            0..big.len(),
            |i| big[i].0,
            |i| (big[i].1, 0.0),
            -0.5,
            99_999.5,
            800,
        );
        assert!(line.contains(&(73_219.0, 900.0)));
        assert!(line.len() <= 4 * 800 && line.len() > 800, "{}", line.len());
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
