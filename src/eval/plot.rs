//! Report figures: line plots (training curves) and the text headers of the image panels.
//!
//! Drawn with [plotters](https://crates.io/crates/plotters) 0.3 (MIT), the maintained Rust
//! plotting crate: axes with round ticks, axis descriptions, log axes, legends. Only its
//! bitmap backend is enabled (`default-features = false`), rendering into a memory buffer that
//! [`io::image::write_png`] writes; no native libraries.
//!
//! Text goes through plotters' `ab_glyph` feature with a font embedded in the binary: DejaVu
//! Sans 2.37 from the [`dejavu`](https://crates.io/crates/dejavu) crate (the crate MIT /
//! Apache-2.0; the font under the Bitstream Vera licence, DejaVu's changes in the public
//! domain: free to use, embed and redistribute). No system font, no fontconfig: the figures
//! look the same on a bare machine.

use std::error::Error as _;
use std::ops::Range;
use std::path::Path;
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::coord::ranged1d::{AsRangedCoord, Ranged, ValueFormatter};
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::error::{Error, Result};
use crate::io;

/// The font family every text here uses (DejaVu Sans, registered on first use).
const FONT: &str = "sans-serif";

/// Registers the embedded font with plotters once.
fn fonts() -> Result<()> {
    static DONE: OnceLock<bool> = OnceLock::new();
    let ok = *DONE.get_or_init(|| {
        plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular()).is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(Error::invalid(
            "plot",
            "font",
            "the embedded DejaVu Sans does not parse",
        ))
    }
}

fn plot_error(what: &str, e: impl std::fmt::Display) -> Error {
    Error::invalid(what, "plot", e.to_string())
}

/// One curve of a [`line_plot`].
#[derive(Clone, Debug)]
pub struct Series {
    /// Its legend entry (no entry when empty).
    pub label: String,
    /// sRGB colour.
    pub color: [u8; 3],
    /// Line width in pixels (at the 800x500 reference size); 0 draws no line.
    pub width: u32,
    /// Marks each point with a dot.
    pub markers: bool,
    /// (x, y) points; non-finite ones (and on a log axis those <= 0) are skipped.
    pub points: Vec<(f64, f64)>,
    /// Per point, a half-width drawn as a vertical error bar `y ± e` with caps (none where it
    /// is missing, zero or not finite; empty: no error bars).
    pub errors: Vec<f64>,
}

/// Titles and axes of a [`line_plot`].
#[derive(Clone, Debug)]
pub struct Figure {
    pub title: String,
    /// The x axis' description, with its unit.
    pub x_label: String,
    /// The y axis' description, with its unit.
    pub y_label: String,
    /// A logarithmic x axis.
    pub log_x: bool,
    /// A logarithmic y axis.
    pub log_y: bool,
    /// Image size in pixels.
    pub width: usize,
    pub height: usize,
}

/// A tick label: at most 3 significant digits, no trailing zeros, exponent form for very
/// large or small magnitudes.
fn tick_label(v: f64) -> String {
    let a = v.abs();
    // Below 1e-12: zero reached by adding up float steps (-5.55e-17).
    if a < 1e-12 || !v.is_finite() {
        return "0".into();
    }
    let trim = |s: String| {
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        }
    };
    if !(1e-3..1e5).contains(&a) {
        let s = format!("{v:.2e}");
        let (m, e) = s.split_once('e').unwrap_or((&s, "0"));
        return format!("{}e{e}", trim(m.to_string()));
    }
    let digits = (2 - a.log10().floor() as i32).clamp(0, 6) as usize;
    trim(format!("{v:.digits$}"))
}

/// The points of `s` that the axes can show, with their error bars' half-widths (0: none).
fn shown(s: &Series, log: (bool, bool)) -> impl Iterator<Item = ((f64, f64), f64)> + '_ {
    s.points
        .iter()
        .copied()
        .enumerate()
        .filter(move |&(_, (x, y))| {
            x.is_finite() && y.is_finite() && (!log.0 || x > 0.0) && (!log.1 || y > 0.0)
        })
        .map(|(i, p)| {
            let e = s
                .errors
                .get(i)
                .copied()
                .filter(|e| e.is_finite())
                .unwrap_or(0.0);
            (p, e.abs())
        })
}

/// The lower end of a point's error bar: on a log axis a bar reaching zero or below is cut
/// at the point.
fn bar_bottom(y: f64, e: f64, log_y: bool) -> f64 {
    if log_y && y - e <= 0.0 { y } else { y - e }
}

/// Data ranges (x, y) over the shown points and their error bars, padded; defaults when
/// there are none.
fn ranges(series: &[Series], (log_x, log_y): (bool, bool)) -> (Range<f64>, Range<f64>) {
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for ((x, y), e) in series.iter().flat_map(|s| shown(s, (log_x, log_y))) {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(bar_bottom(y, e, log_y));
        y1 = y1.max(y + e);
    }
    if x0 > x1 {
        let unit = |log| if log { 0.1..1.0 } else { 0.0..1.0 };
        return (unit(log_x), unit(log_y));
    }
    if log_x {
        // A tenth of the data's span in decades beyond it on each side (at least 0.05).
        let pad = (0.1 * (x1 / x0).log10()).max(0.05);
        (x0, x1) = (x0 / 10f64.powf(pad), x1 * 10f64.powf(pad));
    } else if x1 - x0 < 1e-12 {
        (x0, x1) = (x0 - 0.5, x1 + 0.5);
    } else if x0 > 0.0 && x0 < 0.05 * (x1 - x0) {
        // Iterations from 1: the axis from 0.
        x0 = 0.0;
    }
    let y = if log_y {
        // A fifth of a decade beyond the data; at least one decade in all.
        let (mut lo, mut hi) = (y0.log10() - 0.2, y1.log10() + 0.2);
        if hi - lo < 1.0 {
            let mid = 0.5 * (lo + hi);
            (lo, hi) = (mid - 0.5, mid + 0.5);
        }
        10f64.powf(lo)..10f64.powf(hi)
    } else {
        let pad = if y1 - y0 < 1e-12 {
            0.5 * y0.abs().max(1.0)
        } else {
            0.05 * (y1 - y0)
        };
        y0 - pad..y1 + pad
    };
    (x0..x1, y)
}

/// Draws `series` with `fig`'s titles and axes into a PNG at `path`, with a legend of the
/// labelled series where it hides the fewest curve pixels (the upper right when free).
pub fn line_plot(path: &Path, fig: &Figure, series: &[Series]) -> Result<()> {
    let rgb = render_plot(fig, series).map_err(|e| plot_error(&path.display().to_string(), e))?;
    let floats: Vec<f32> = rgb.iter().map(|&v| v as f32 / 255.0).collect();
    io::image::write_png(path, fig.width, fig.height, &floats)
}

/// Ticks of a log axis over `r` (positive): labelled at 1, 2 and 5 times the powers of ten
/// (only the powers where the range spans more than two decades), grid lines at every
/// integer multiple of them.
fn log_ticks(r: &Range<f64>) -> (Vec<f64>, Vec<f64>) {
    let (lo, hi) = (r.start.max(f64::MIN_POSITIVE), r.end);
    let steps: &[f64] = if hi / lo > 100.0 {
        &[1.0]
    } else {
        &[1.0, 2.0, 5.0]
    };
    let (mut bold, mut light) = (Vec::new(), Vec::new());
    let mut p = 10f64.powf(lo.log10().floor());
    while p <= hi {
        for m in 1..10 {
            let v = p * m as f64;
            if (lo..=hi).contains(&v) {
                if steps.contains(&(m as f64)) {
                    bold.push(v);
                } else {
                    light.push(v);
                }
            }
        }
        p *= 10.0;
    }
    (bold, light)
}

/// [`line_plot`]'s pixels: [H, W, 3] bytes.
fn render_plot(fig: &Figure, series: &[Series]) -> std::result::Result<Vec<u8>, String> {
    fonts().map_err(|e| e.to_string())?;
    let (w, h) = (fig.width.max(1), fig.height.max(1));
    let mut buf = vec![255u8; w * h * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w as u32, h as u32)).into_drawing_area();
        let (x, y) = ranges(series, (fig.log_x, fig.log_y));
        let res = match (fig.log_x, fig.log_y) {
            (false, false) => draw_chart(&root, fig, series, x, y),
            (false, true) => draw_chart(&root, fig, series, x, y.log_scale()),
            (true, log_y) => {
                let (bold, light) = log_ticks(&x);
                let x = x.log_scale().with_key_points(bold).with_light_points(light);
                if log_y {
                    draw_chart(&root, fig, series, x, y.log_scale())
                } else {
                    draw_chart(&root, fig, series, x, y)
                }
            }
        };
        res.map_err(|e| e.source().map_or(e.to_string(), |s| s.to_string()))?;
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(buf)
}

type DrawResult<'a> =
    std::result::Result<(), DrawingAreaErrorKind<<BitMapBackend<'a> as DrawingBackend>::ErrorType>>;

/// The chart frame both plots use: the title, margins and label areas for `fig`'s size
/// (800x500 sizes scaled with the image, never below 10 px text).
fn chart_builder<'a, 'b>(
    root: &'a DrawingArea<BitMapBackend<'b>, Shift>,
    fig: &Figure,
) -> ChartBuilder<'a, 'b, BitMapBackend<'b>> {
    let s = (fig.width as f64 / 800.0).min(fig.height as f64 / 500.0);
    let px = |v: f64| (v * s).max(10.0);
    let mut b = ChartBuilder::on(root);
    b.caption(
        &fig.title,
        (FONT, px(24.0)).into_font().color(&RGBColor(40, 40, 40)),
    )
    .margin((12.0 * s).max(4.0) as u32)
    .margin_right((24.0 * s).max(6.0) as u32)
    .x_label_area_size(px(48.0) as u32)
    .y_label_area_size(px(72.0) as u32);
    b
}

fn draw_chart<'a, X, Y>(
    root: &DrawingArea<BitMapBackend<'a>, Shift>,
    fig: &Figure,
    series: &[Series],
    x: X,
    y: Y,
) -> DrawResult<'a>
where
    X: AsRangedCoord<Value = f64>,
    X::CoordDescType: Ranged<ValueType = f64> + ValueFormatter<f64>,
    Y: AsRangedCoord<Value = f64>,
    Y::CoordDescType: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    // Sizes for 800x500, scaled with the image (never below 10 px text).
    let s = (fig.width as f64 / 800.0).min(fig.height as f64 / 500.0);
    let px = |v: f64| (v * s).max(10.0);
    let ink = RGBColor(40, 40, 40);
    root.fill(&WHITE)?;
    let mut chart = chart_builder(root, fig).build_cartesian_2d(x, y)?;
    let xfmt = |v: &f64| tick_label(*v);
    let yfmt = |v: &f64| tick_label(*v);
    chart
        .configure_mesh()
        .x_desc(&fig.x_label)
        .y_desc(&fig.y_label)
        .x_label_formatter(&xfmt)
        .y_label_formatter(&yfmt)
        .label_style((FONT, px(15.0)).into_font().color(&ink))
        .axis_desc_style((FONT, px(17.0)).into_font().color(&ink))
        .bold_line_style(BLACK.mix(0.12))
        .light_line_style(BLACK.mix(if fig.log_x || fig.log_y { 0.05 } else { 0.0 }))
        .axis_style(ink)
        .draw()?;
    let log = (fig.log_x, fig.log_y);
    let mut labels: Vec<&str> = Vec::new();
    // Where the curves run, in plotting-area pixels (segments sampled every 2 px), to put the
    // legend where it hides the least.
    let base = chart.plotting_area().get_base_pixel();
    let mut occupied: Vec<(i32, i32)> = Vec::new();
    for se in series {
        let shown: Vec<((f64, f64), f64)> = shown(se, log).collect();
        if shown.is_empty() {
            continue;
        }
        let pts: Vec<(f64, f64)> = shown.iter().map(|&(p, _)| p).collect();
        let pix: Vec<(i32, i32)> = pts
            .iter()
            .map(|p| {
                let (x, y) = chart.backend_coord(p);
                (x - base.0, y - base.1)
            })
            .collect();
        occupied.extend(&pix);
        let color = RGBColor(se.color[0], se.color[1], se.color[2]);
        let lw = ((se.width as f64 * s).round() as u32).max(u32::from(se.width > 0));
        let dot = (3.0 * s).max(2.0) as i32;
        if lw > 0 {
            for w in pix.windows(2) {
                let (a, b) = (w[0], w[1]);
                let (dx, dy) = (b.0 as i64 - a.0 as i64, b.1 as i64 - a.1 as i64);
                let n = (dx.abs().max(dy.abs()) / 2).clamp(1, 1 << 16);
                occupied.extend((1..n).map(|k| {
                    (
                        (a.0 as i64 + dx * k / n) as i32,
                        (a.1 as i64 + dy * k / n) as i32,
                    )
                }));
            }
            let ann = chart.draw_series(LineSeries::new(pts.clone(), color.stroke_width(lw)))?;
            if !se.label.is_empty() && !se.markers {
                labels.push(&se.label);
                ann.label(&se.label).legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(lw.max(2)))
                });
            }
        }
        let bars: Vec<_> = shown
            .iter()
            .filter(|&&(_, e)| e > 0.0)
            .map(|&((x, y), e)| {
                let lo = bar_bottom(y, e, log.1);
                let (top, bottom) = (
                    chart.backend_coord(&(x, y + e)),
                    chart.backend_coord(&(x, lo)),
                );
                occupied.extend(
                    (bottom.1.min(top.1)..=bottom.1.max(top.1))
                        .step_by(2)
                        .map(|r| (top.0 - base.0, r - base.1)),
                );
                let cap = dot + 1;
                EmptyElement::at((x, y + e))
                    + PathElement::new(vec![(-cap, 0), (cap, 0)], color.stroke_width(lw.max(1)))
                    + PathElement::new(
                        vec![(0, 0), (0, bottom.1 - top.1)],
                        color.stroke_width(lw.max(1)),
                    )
                    + PathElement::new(
                        vec![(-cap, bottom.1 - top.1), (cap, bottom.1 - top.1)],
                        color.stroke_width(lw.max(1)),
                    )
            })
            .collect();
        chart.draw_series(bars)?;
        if se.markers {
            let ann =
                chart.draw_series(pts.iter().map(|&p| Circle::new(p, dot, color.filled())))?;
            if !se.label.is_empty() {
                labels.push(&se.label);
                ann.label(&se.label).legend(move |(x, y)| {
                    EmptyElement::at((x, y))
                        + PathElement::new(vec![(0, 0), (20, 0)], color.stroke_width(lw))
                        + Circle::new((10, 0), dot, color.filled())
                });
            }
        }
    }
    if !labels.is_empty() {
        let font = (FONT, px(14.0)).into_font().color(&ink);
        let margin = px(10.0) as u32;
        let mut text = MultiLineText::<_, &str>::new((0, 0), &font);
        for l in &labels {
            text.push_line(*l);
        }
        // plotters' legend box: the text, 30 px for the samples, the margin around.
        let (tw, th) = text
            .estimate_dimension()
            .unwrap_or((200, 20 * labels.len() as i32));
        let size = (tw + 30 + 2 * margin as i32, th + 2 * margin as i32);
        let (aw, ah) = chart.plotting_area().dim_in_pixel();
        let at = legend_position(size, (aw as i32, ah as i32), &occupied);
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::Coordinate(at.0, at.1))
            .label_font(font)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.3))
            .margin(margin)
            .draw()?;
    }
    Ok(())
}

/// The top-left corner of a legend box of `size` in a plotting area of `area` pixels: the
/// corner, edge middle or centre position covering the fewest `occupied` pixels, preferring
/// the upper right, then the other corners.
fn legend_position(size: (i32, i32), area: (i32, i32), occupied: &[(i32, i32)]) -> (i32, i32) {
    let m = 8;
    let xs = [area.0 - size.0 - m, m, (area.0 - size.0) / 2];
    let ys = [m, area.1 - size.1 - m, (area.1 - size.1) / 2];
    let order = [
        (0, 0),
        (1, 0),
        (0, 1),
        (1, 1),
        (2, 0),
        (2, 1),
        (0, 2),
        (1, 2),
        (2, 2),
    ];
    let hidden = |(x, y): (i32, i32)| {
        occupied
            .iter()
            .filter(|p| {
                (x - 4..=x + size.0 + 4).contains(&p.0) && (y - 4..=y + size.1 + 4).contains(&p.1)
            })
            .count()
    };
    order
        .iter()
        .map(|&(i, j)| (xs[i].max(0), ys[j].max(0)))
        .min_by_key(|&p| hidden(p))
        .unwrap_or((m, m))
}

/// One bar per group of a [`bar_chart`]: its legend entry, colour and `(mean, error)` per
/// group (an error of 0 draws no error bar; a non-finite mean draws no bar).
#[derive(Clone, Debug)]
pub struct Bars {
    pub label: String,
    /// sRGB colour.
    pub color: [u8; 3],
    pub values: Vec<(f64, f64)>,
}

/// Grouped bars with error bars (mean ± error): one group per entry of `groups`, one bar
/// per entry of `bars` within each, a legend of the bars, into a PNG at `path`. The y axis
/// spans the bars and their errors (from 0 when every value is positive and the smallest
/// is below half the largest, else padded around them, so that small differences show).
pub fn bar_chart(path: &Path, fig: &Figure, groups: &[String], bars: &[Bars]) -> Result<()> {
    let what = path.display().to_string();
    fonts()?;
    let (w, h) = (fig.width.max(1), fig.height.max(1));
    let mut buf = vec![255u8; w * h * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w as u32, h as u32)).into_drawing_area();
        draw_bars(&root, fig, groups, bars)
            .map_err(|e| plot_error(&what, e.source().map_or(e.to_string(), |s| s.to_string())))?;
        root.present().map_err(|e| plot_error(&what, e))?;
    }
    let floats: Vec<f32> = buf.iter().map(|&v| v as f32 / 255.0).collect();
    io::image::write_png(path, w, h, &floats)
}

fn draw_bars<'a>(
    root: &DrawingArea<BitMapBackend<'a>, Shift>,
    fig: &Figure,
    groups: &[String],
    bars: &[Bars],
) -> DrawResult<'a> {
    let s = (fig.width as f64 / 800.0).min(fig.height as f64 / 500.0);
    let px = |v: f64| (v * s).max(10.0);
    let ink = RGBColor(40, 40, 40);
    root.fill(&WHITE)?;
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for b in bars {
        for &(m, e) in b.values.iter().filter(|(m, _)| m.is_finite()) {
            lo = lo.min(m - e.abs());
            hi = hi.max(m + e.abs());
        }
    }
    if !lo.is_finite() {
        (lo, hi) = (0.0, 1.0);
    }
    let y = if lo > 0.0 && lo < 0.5 * hi {
        0.0..hi * 1.05
    } else {
        let pad = 0.1 * (hi - lo).max(1e-9);
        lo - pad..hi + pad
    };
    let n = groups.len().max(1);
    let k = bars.len().max(1);
    let mut chart = chart_builder(root, fig).build_cartesian_2d(0.0..n as f64, y.clone())?;
    let names = groups.to_vec();
    let xfmt = move |v: &f64| {
        let i = v.floor() as usize;
        if (v - i as f64 - 0.5).abs() < 1e-6 {
            names.get(i).cloned().unwrap_or_default()
        } else {
            String::new()
        }
    };
    let yfmt = |v: &f64| tick_label(*v);
    chart
        .configure_mesh()
        .x_desc(&fig.x_label)
        .y_desc(&fig.y_label)
        .x_labels(2 * n + 1)
        .x_label_formatter(&xfmt)
        .y_label_formatter(&yfmt)
        .disable_x_mesh()
        .label_style((FONT, px(15.0)).into_font().color(&ink))
        .axis_desc_style((FONT, px(17.0)).into_font().color(&ink))
        .bold_line_style(BLACK.mix(0.12))
        .light_line_style(BLACK.mix(0.0))
        .axis_style(ink)
        .draw()?;
    let width = 0.8 / k as f64;
    let base = y.start.max(0.0).min(y.end);
    for (j, b) in bars.iter().enumerate() {
        let color = RGBColor(b.color[0], b.color[1], b.color[2]);
        let x0 = |g: usize| g as f64 + 0.1 + j as f64 * width;
        let rects: Vec<_> = b
            .values
            .iter()
            .enumerate()
            .filter(|(_, (m, _))| m.is_finite())
            .map(|(g, &(m, _))| Rectangle::new([(x0(g), base), (x0(g) + width, m)], color.filled()))
            .collect();
        let ann = chart.draw_series(rects)?;
        ann.label(&b.label)
            .legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 16, y + 6)], color.filled()));
        let errs: Vec<_> = b
            .values
            .iter()
            .enumerate()
            .filter(|(_, (m, e))| m.is_finite() && *e > 0.0)
            .map(|(g, &(m, e))| {
                let xc = x0(g) + 0.5 * width;
                PathElement::new(vec![(xc, m - e), (xc, m + e)], ink.stroke_width(2))
            })
            .collect();
        chart.draw_series(errs)?;
    }
    chart
        .configure_series_labels()
        .label_font((FONT, px(14.0)).into_font().color(&ink))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK.mix(0.3))
        .position(SeriesLabelPosition::UpperRight)
        .draw()?;
    Ok(())
}

/// The text size of a panel header for image columns `column_width` pixels wide: 6 % of the
/// width, at least 12 px.
pub fn header_font_px(column_width: usize) -> f64 {
    (0.06 * column_width as f64).round().max(12.0)
}

/// The height of a panel header (a line of [`header_font_px`] text with some space).
pub fn header_height(column_width: usize) -> usize {
    (1.7 * header_font_px(column_width)).round() as usize
}

/// A white header band, [`header_height`]`(column_width)` rows by `column_width *
/// labels.len()` columns, with each label centred over its column in dark text (shrunk to fit
/// the column down to 10 px, clipped below that): [H, W, 3] floats in [0, 1].
pub fn header(column_width: usize, labels: &[&str]) -> Result<Vec<f32>> {
    fonts()?;
    let h = header_height(column_width);
    let w = column_width * labels.len();
    let mut out = vec![1.0f32; h * w * 3];
    if column_width == 0 {
        return Ok(out);
    }
    let size = header_font_px(column_width);
    for (k, label) in labels.iter().enumerate() {
        let mut cell = vec![255u8; h * column_width * 3];
        {
            let area = BitMapBackend::with_buffer(&mut cell, (column_width as u32, h as u32))
                .into_drawing_area();
            let style = |px: f64| {
                (FONT, px)
                    .into_font()
                    .color(&RGBColor(20, 20, 20))
                    .pos(Pos::new(HPos::Center, VPos::Center))
            };
            let fit = area
                .estimate_text_size(label, &style(size))
                .map(|(tw, _)| {
                    let room = column_width.saturating_sub(4).max(1) as f64;
                    if tw as f64 > room {
                        (size * room / tw as f64).max(10.0)
                    } else {
                        size
                    }
                })
                .map_err(|e| plot_error("panel header", e))?;
            area.draw_text(
                label,
                &style(fit),
                ((column_width / 2) as i32, (h / 2) as i32),
            )
            .map_err(|e| plot_error("panel header", e))?;
            area.present().map_err(|e| plot_error("panel header", e))?;
        }
        for row in 0..h {
            for col in 0..column_width {
                let i = (row * column_width + col) * 3;
                let o = (row * w + k * column_width + col) * 3;
                for c in 0..3 {
                    out[o + c] = cell[i + c] as f32 / 255.0;
                }
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> std::path::PathBuf {
        std::env::temp_dir().join(format!("texavatars-plot-{name}-{}.png", std::process::id()))
    }

    /// Non-white pixels of `img` in rows `r` and columns `c`.
    fn ink(img: &io::image::RgbImage, r: Range<usize>, c: Range<usize>) -> usize {
        r.flat_map(|y| c.clone().map(move |x| (y, x)))
            .filter(|&(y, x)| {
                let o = (y * img.width + x) * 3;
                img.rgb[o..o + 3].iter().any(|&v| v < 0.6)
            })
            .count()
    }

    fn fig(log_y: bool) -> Figure {
        Figure {
            title: "Training loss".into(),
            x_label: "iteration".into(),
            y_label: "loss".into(),
            log_x: false,
            log_y,
            width: 800,
            height: 500,
        }
    }

    #[test]
    fn tick_labels_are_short() {
        assert_eq!(tick_label(2000.0), "2000");
        assert_eq!(tick_label(0.25), "0.25");
        assert_eq!(tick_label(0.1), "0.1");
        assert_eq!(tick_label(0.30000000000000004), "0.3");
        assert_eq!(tick_label(31.25), "31.2");
        assert_eq!(tick_label(1e-4), "1e-4");
        assert_eq!(tick_label(0.0), "0");
        assert_eq!(tick_label(-5.551115123125783e-17), "0");
    }

    #[test]
    fn plot_has_title_axes_and_series() {
        let p = tmp("lin");
        let s = Series {
            label: "train".into(),
            color: [220, 30, 30],
            width: 2,
            markers: false,
            points: (0..50).map(|i| (i as f64, (i as f64).sqrt())).collect(),
            errors: Vec::new(),
        };
        let mut f = fig(false);
        f.title = "PSNR".into();
        f.y_label = "PSNR (dB)".into();
        line_plot(&p, &f, &[s]).expect("plot");
        let img = io::image::read_rgb(&p).expect("read");
        assert_eq!((img.width, img.height), (800, 500));
        // the title band: text at the top centre
        assert!(ink(&img, 0..40, 300..500) > 50, "no title");
        // the plotting area holds the red curve
        let red = img
            .rgb
            .chunks(3)
            .filter(|c| c[0] > 0.8 && c[1] < 0.25 && c[2] < 0.25)
            .count();
        assert!(red > 300, "{red} red pixels");
        // tick labels left of the axis and the x description below it
        assert!(ink(&img, 60..440, 0..60) > 50, "no y labels");
        assert!(ink(&img, 460..500, 300..500) > 30, "no x description");
        let _ = std::fs::remove_file(&p);
    }

    #[test]
    fn log_plot_skips_values_it_cannot_show() {
        let p = tmp("log");
        let mut pts: Vec<(f64, f64)> = (1..300).map(|i| (i as f64, 1.0 / i as f64)).collect();
        pts.extend([
            (300.0, 0.0),
            (301.0, -1.0),
            (302.0, f64::NAN),
            (f64::INFINITY, 1.0),
        ]);
        let series = [
            Series {
                label: "total".into(),
                color: [30, 60, 200],
                width: 2,
                markers: false,
                points: pts,
                errors: Vec::new(),
            },
            // nothing to show: no line, no legend entry, no panic
            Series {
                label: "zero".into(),
                color: [0, 0, 0],
                width: 2,
                markers: true,
                points: vec![(1.0, 0.0), (2.0, -3.0), (3.0, f64::NAN)],
                errors: Vec::new(),
            },
        ];
        line_plot(&p, &fig(true), &series).expect("log plot");
        let img = io::image::read_rgb(&p).expect("read");
        assert_eq!((img.width, img.height), (800, 500));
        assert!(ink(&img, 0..40, 300..500) > 50, "no title");
        let blue = img
            .rgb
            .chunks(3)
            .filter(|c| c[2] > 0.7 && c[0] < 0.3 && c[1] < 0.4)
            .count();
        assert!(blue > 300, "{blue} blue pixels");
        // only invalid values: empty axes, still a figure
        line_plot(&p, &fig(true), &series[1..]).expect("empty log plot");
        line_plot(&p, &fig(false), &[]).expect("empty plot");
        let _ = std::fs::remove_file(&p);
    }

    #[test]
    fn legend_goes_where_the_curves_are_not() {
        let area = (600, 400);
        let size = (200, 100);
        // free: upper right
        assert_eq!(legend_position(size, area, &[]), (392, 8));
        // a curve in the upper right: upper left
        let busy: Vec<(i32, i32)> = (400..600).map(|x| (x, 50)).collect();
        assert_eq!(legend_position(size, area, &busy), (8, 8));
    }

    #[test]
    fn header_centres_labels_over_columns() {
        let w = 138;
        let h = header_height(w);
        assert_eq!(h, 20);
        assert_eq!(header_height(550), 56);
        let band = header(w, &["a long label", "", "x"]).expect("header");
        assert_eq!(band.len(), h * 3 * w * 3);
        let img = io::image::RgbImage {
            width: 3 * w,
            height: h,
            rgb: band,
        };
        assert!(ink(&img, 0..h, 0..w) > 30);
        assert_eq!(ink(&img, 0..h, w..2 * w), 0);
        // "x" sits in the middle of the third column
        assert!(ink(&img, 0..h, 2 * w + w / 2 - 8..2 * w + w / 2 + 8) > 5);
        assert_eq!(ink(&img, 0..h, 2 * w..2 * w + w / 3), 0);
    }

    #[test]
    fn error_bars_and_a_log_x_axis() {
        let point = |color: [u8; 3], x: f64, e: f64| Series {
            label: String::new(),
            color,
            width: 0,
            markers: true,
            points: vec![(x, 0.0)],
            errors: vec![e],
        };
        let (red, green, blue) = ([230, 20, 20], [20, 200, 20], [20, 20, 230]);
        let series = [
            point(red, 1.0, 0.5),
            point(green, 10.0, 2.0),
            point(blue, 100.0, 0.0),
        ];
        let mut f = fig(false);
        f.log_x = true;
        // The y range holds every bar; the log x range pads by factors around 1..100.
        let (x, y) = ranges(&series, (true, false));
        assert!(y.start < -2.0 && y.end > 2.0, "{y:?}");
        assert!(
            x.start < 1.0 && x.start > 0.5 && x.end > 100.0 && x.end < 200.0,
            "{x:?}"
        );
        let p = tmp("bars");
        line_plot(&p, &f, &series).expect("plot");
        let img = io::image::read_rgb(&p).expect("read");
        // Each colour's pixels: count, mean column, rows spanned.
        let of = |c: [u8; 3]| {
            let want = c.map(|v| v as f32 / 255.0);
            let (mut n, mut col, mut r0, mut r1) = (0usize, 0.0, usize::MAX, 0usize);
            for (i, px) in img.rgb.chunks(3).enumerate() {
                if px.iter().zip(want).all(|(a, b)| (a - b).abs() < 0.1) {
                    n += 1;
                    col += (i % img.width) as f64;
                    r0 = r0.min(i / img.width);
                    r1 = r1.max(i / img.width);
                }
            }
            (n, col / n.max(1) as f64, r1.saturating_sub(r0))
        };
        let (r, g, b) = (of(red), of(green), of(blue));
        assert!(r.0 > 0 && g.0 > 0 && b.0 > 0, "{r:?} {g:?} {b:?}");
        // 1, 10, 100 are evenly spaced on the log axis.
        assert!((g.1 - 0.5 * (r.1 + b.1)).abs() < 3.0, "{r:?} {g:?} {b:?}");
        // Its ticks: the powers of ten over two decades and more, else 1, 2, 5 times them.
        assert_eq!(log_ticks(&(0.7..150.0)).0, vec![1.0, 10.0, 100.0]);
        assert_eq!(log_ticks(&(3.5..60.0)).0, vec![5.0, 10.0, 20.0, 50.0]);
        assert_eq!(log_ticks(&(3.5..60.0)).1[..3], [4.0, 6.0, 7.0]);
        // The bars' lengths follow their errors (4x); no error, no bar: just the dot.
        assert!(g.2 > 100, "{g:?}");
        assert!((g.2 as f64 / r.2 as f64 - 4.0).abs() < 0.5, "{r:?} {g:?}");
        assert!(b.2 < 10, "{b:?}");
        let _ = std::fs::remove_file(&p);
    }
}
