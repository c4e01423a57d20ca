//! Training curves as PNG without a plotting dependency: line series on a white canvas with
//! axes, grid lines at round values, and tick labels in a built-in 3x5 pixel font.

use std::path::Path;

use crate::error::Result;
use crate::io;

/// One curve: its colour and (x, y) points.
#[derive(Clone, Debug)]
pub struct Series {
    pub color: [f32; 3],
    pub points: Vec<(f64, f64)>,
}

/// Glyphs of the 3x5 font, rows top to bottom, bit 2 = left column.
fn glyph(c: char) -> Option<[u8; 5]> {
    Some(match c {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 1, 1],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        '-' => [0, 0, 7, 0, 0],
        'e' => [0, 7, 7, 4, 7],
        'k' => [4, 5, 6, 5, 5],
        _ => return None,
    })
}

struct Canvas {
    w: usize,
    h: usize,
    rgb: Vec<f32>,
}

impl Canvas {
    fn set(&mut self, x: i64, y: i64, c: [f32; 3]) {
        if x >= 0 && y >= 0 && (x as usize) < self.w && (y as usize) < self.h {
            let o = (y as usize * self.w + x as usize) * 3;
            self.rgb[o..o + 3].copy_from_slice(&c);
        }
    }

    fn line(&mut self, (x0, y0): (f64, f64), (x1, y1): (f64, f64), c: [f32; 3]) {
        let n = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as usize).max(1);
        for i in 0..=n {
            let t = i as f64 / n as f64;
            self.set(
                (x0 + t * (x1 - x0)).round() as i64,
                (y0 + t * (y1 - y0)).round() as i64,
                c,
            );
        }
    }

    /// Text with its top-left corner at (x, y), 2x scaled glyphs.
    fn text(&mut self, x: i64, y: i64, s: &str, c: [f32; 3]) {
        for (k, ch) in s.chars().enumerate() {
            let Some(g) = glyph(ch) else { continue };
            for (row, bits) in g.iter().enumerate() {
                for col in 0..3 {
                    if bits & (4 >> col) != 0 {
                        for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                            self.set(x + k as i64 * 8 + col * 2 + dx, y + row as i64 * 2 + dy, c);
                        }
                    }
                }
            }
        }
    }
}

/// A "nice" tick step for a range (1, 2 or 5 times a power of ten), about 5 ticks.
fn tick_step(range: f64) -> f64 {
    let raw = (range / 5.0).max(f64::MIN_POSITIVE);
    let p = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * p)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * p)
}

fn label(v: f64, step: f64) -> String {
    if v.abs() >= 1000.0 && (v / 1000.0).fract() == 0.0 {
        format!("{}k", v / 1000.0)
    } else if step >= 1.0 {
        format!("{v:.0}")
    } else {
        let digits = (-step.log10().floor()) as usize;
        format!("{v:.digits$}")
    }
}

/// Draws `series` into a `width x height` PNG at `path`. Non-finite points are skipped.
pub fn line_plot(path: &Path, width: usize, height: usize, series: &[Series]) -> Result<()> {
    let mut cv = Canvas {
        w: width,
        h: height,
        rgb: vec![1.0; width * height * 3],
    };
    let pts = || {
        series
            .iter()
            .flat_map(|s| &s.points)
            .filter(|(x, y)| x.is_finite() && y.is_finite())
    };
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in pts() {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if x0 > x1 {
        (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
    }
    if x1 - x0 < 1e-12 {
        x1 = x0 + 1.0;
    }
    if y1 - y0 < 1e-12 {
        y1 = y0 + 1.0;
    }
    let (left, right, top, bottom) = (60.0, 12.0, 12.0, 30.0);
    let pw = width as f64 - left - right;
    let ph = height as f64 - top - bottom;
    let sx = |x: f64| left + (x - x0) / (x1 - x0) * pw;
    let sy = |y: f64| top + (1.0 - (y - y0) / (y1 - y0)) * ph;
    let grid = [0.9f32; 3];
    let ink = [0.2f32; 3];
    let ys = tick_step(y1 - y0);
    let mut t = (y0 / ys).ceil() * ys;
    while t <= y1 + 1e-9 {
        cv.line((left, sy(t)), (left + pw, sy(t)), grid);
        cv.text(4, sy(t) as i64 - 5, &label(t, ys), ink);
        t += ys;
    }
    let xs = tick_step(x1 - x0);
    let mut t = (x0 / xs).ceil() * xs;
    while t <= x1 + 1e-9 {
        cv.line((sx(t), top), (sx(t), top + ph), grid);
        cv.text(
            sx(t) as i64 - 8,
            (top + ph + 8.0) as i64,
            &label(t, xs),
            ink,
        );
        t += xs;
    }
    cv.line((left, top), (left, top + ph), ink);
    cv.line((left, top + ph), (left + pw, top + ph), ink);
    for s in series {
        let mut prev: Option<(f64, f64)> = None;
        for &(x, y) in s
            .points
            .iter()
            .filter(|(x, y)| x.is_finite() && y.is_finite())
        {
            let p = (sx(x), sy(y));
            if let Some(q) = prev {
                cv.line(q, p, s.color);
            } else {
                cv.set(p.0 as i64, p.1 as i64, s.color);
            }
            prev = Some(p);
        }
    }
    io::image::write_png(path, width, height, &cv.rgb)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round() {
        assert_eq!(tick_step(10.0), 2.0);
        assert_eq!(tick_step(0.3), 0.1);
        assert_eq!(tick_step(7000.0), 2000.0);
        assert_eq!(label(2000.0, 1000.0), "2k");
        assert_eq!(label(0.25, 0.05), "0.25");
    }

    #[test]
    fn plot_draws_the_series() {
        let p = std::env::temp_dir().join(format!("texavatars-plot-{}.png", std::process::id()));
        let s = Series {
            color: [1.0, 0.0, 0.0],
            points: (0..50).map(|i| (i as f64, (i as f64).sqrt())).collect(),
        };
        line_plot(&p, 200, 120, &[s]).expect("plot");
        let img = io::image::read_rgb(&p).expect("read");
        let red = img
            .rgb
            .chunks(3)
            .filter(|c| c[0] > 0.9 && c[1] < 0.1 && c[2] < 0.1)
            .count();
        assert!(red > 100, "{red} red pixels");
        let _ = std::fs::remove_file(&p);
    }
}
