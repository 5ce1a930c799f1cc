//! The colours every CLI figure uses (matplotlib's "tab10", first six), so a
//! parameter or a scan kind looks the same across `bench`, `drift-day` and
//! `bench --plot-time`.

use plotters::style::RGBColor;

/// Blue, orange, green, red, purple, grey.
pub const TAB10: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(127, 127, 127),
];
