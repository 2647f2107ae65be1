//! Charts: line and scatter plots written as SVG and PNG with `plotters`.
//!
//! One call draws one chart twice, `base.svg` (vector, for documents) and `base.png`
//! (raster, for READMEs and quick looks), each through [`super::write_atomic`]. Axes can be
//! logarithmic; on a log axis points with a non-positive (or non-finite) coordinate cannot
//! be drawn and are left out (the caller sees them in its own tables).
//!
//! Text in the PNG is rasterized by `ab_glyph` from DejaVu Sans, which the crate carries
//! (`assets/fonts/DejaVuSans.ttf`, Bitstream Vera licence, from Debian's
//! `fonts-dejavu-core`; licence file alongside), so charts look the same on a machine with
//! no system fonts. The SVG names the family `sans-serif` and leaves rendering to the
//! viewer.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Once;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};

use crate::error::{Error, Result};

/// A named sequence of `(x, y)` points: one line (or one set of marks) of a chart.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Series {
    /// Legend entry.
    pub name: String,
    /// Points in drawing order.
    pub points: Vec<(f64, f64)>,
}

impl Series {
    /// A series from a name and points.
    pub fn new(name: impl Into<String>, points: Vec<(f64, f64)>) -> Series {
        Series {
            name: name.into(),
            points,
        }
    }
}

/// How the points of a series are drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mark {
    /// Points joined by a line, each marked by a dot.
    Line,
    /// Unjoined markers only.
    Scatter,
}

/// Pixel size of both files.
const SIZE: (u32, u32) = (900, 600);

/// The bundled font (see the module docs).
static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

/// Registers the bundled font as `sans-serif` once per process.
fn fonts() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font is a compile-time constant: failing to parse it is a build defect,
        // and text then falls back to nothing rather than stopping the program.
        for style in [FontStyle::Normal, FontStyle::Bold] {
            let _ = register_font("sans-serif", style, FONT);
        }
    });
}

/// A line chart of `series` written to `base.svg` and `base.png`; returns both paths.
///
/// `log_x` / `log_y` select logarithmic axes. Series keep their order in the legend and
/// take colours from a fixed palette, so reruns give identical files.
pub fn line_chart(
    base: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    log_x: bool,
    log_y: bool,
    series: &[Series],
) -> Result<Vec<PathBuf>> {
    chart(
        base,
        &Spec {
            title,
            x_label,
            y_label,
            log_x,
            log_y,
            mark: Mark::Line,
        },
        series,
    )
}

/// Like [`line_chart`], with unjoined markers.
pub fn scatter_chart(
    base: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    log_x: bool,
    log_y: bool,
    series: &[Series],
) -> Result<Vec<PathBuf>> {
    chart(
        base,
        &Spec {
            title,
            x_label,
            y_label,
            log_x,
            log_y,
            mark: Mark::Scatter,
        },
        series,
    )
}

/// Everything about a chart but its data.
#[derive(Clone, Copy, Debug)]
pub struct Spec<'a> {
    /// Caption.
    pub title: &'a str,
    /// X axis description.
    pub x_label: &'a str,
    /// Y axis description.
    pub y_label: &'a str,
    /// Logarithmic x axis.
    pub log_x: bool,
    /// Logarithmic y axis.
    pub log_y: bool,
    /// Line or scatter.
    pub mark: Mark,
}

/// Draws `series` as described by `spec` into `base.svg` and `base.png`.
pub fn chart(base: &Path, spec: &Spec, series: &[Series]) -> Result<Vec<PathBuf>> {
    fonts();
    let svg_path = with_ext(base, "svg");
    let png_path = with_ext(base, "png");
    let plot = |e: String, path: &Path| Error::Output {
        path: path.to_path_buf(),
        msg: format!("chart: {e}"),
    };

    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        draw(&root, spec, series).map_err(|e| plot(e, &svg_path))?;
        root.present().map_err(|e| plot(e.to_string(), &svg_path))?;
    }
    super::write_atomic(&svg_path, |tmp| {
        std::fs::write(tmp, svg.as_bytes()).map_err(|e| Error::io(tmp, e))
    })?;

    let mut rgb = vec![0u8; (SIZE.0 * SIZE.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, SIZE).into_drawing_area();
        draw(&root, spec, series).map_err(|e| plot(e, &png_path))?;
        root.present().map_err(|e| plot(e.to_string(), &png_path))?;
    }
    super::write_atomic(&png_path, |tmp| write_rgb_png(tmp, &rgb, SIZE))?;
    Ok(vec![svg_path, png_path])
}

/// `base` with `.ext` appended (keeps dots already in the file name).
fn with_ext(base: &Path, ext: &str) -> PathBuf {
    let mut s = base.as_os_str().to_os_string();
    s.push(".");
    s.push(ext);
    PathBuf::from(s)
}

/// Writes 8-bit RGB pixels as a PNG.
fn write_rgb_png(path: &Path, rgb: &[u8], (w, h): (u32, u32)) -> Result<()> {
    let file = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let out = |e: png::EncodingError| Error::Output {
        path: path.to_path_buf(),
        msg: e.to_string(),
    };
    let mut writer = enc.write_header().map_err(out)?;
    writer.write_image_data(rgb).map_err(out)?;
    writer.finish().map_err(out)
}

/// A colour-blind-safe palette (Okabe and Ito 2008), then plotters' 99-colour palette.
fn colour(k: usize) -> RGBColor {
    const OKABE_ITO: [RGBColor; 8] = [
        RGBColor(0, 114, 178),
        RGBColor(213, 94, 0),
        RGBColor(0, 158, 115),
        RGBColor(204, 121, 167),
        RGBColor(230, 159, 0),
        RGBColor(86, 180, 233),
        RGBColor(0, 0, 0),
        RGBColor(240, 228, 66),
    ];
    if k < OKABE_ITO.len() {
        OKABE_ITO[k]
    } else {
        let (r, g, b) = Palette99::pick(k).rgb();
        RGBColor(r, g, b)
    }
}

/// Data range of one axis with a margin (multiplicative on a log axis).
fn range(values: impl Iterator<Item = f64>, log: bool) -> Range<f64> {
    let (mut lo, mut hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if !lo.is_finite() || !hi.is_finite() {
        return if log { 0.1..10.0 } else { 0.0..1.0 };
    }
    if log {
        if hi <= lo {
            lo /= 2.0;
            hi *= 2.0;
        }
        let pad = (hi / lo).powf(0.04);
        lo / pad..hi * pad
    } else {
        if hi <= lo {
            let d = if lo == 0.0 { 1.0 } else { lo.abs() * 0.1 };
            lo -= d;
            hi += d;
        }
        let pad = 0.04 * (hi - lo);
        lo - pad..hi + pad
    }
}

/// True when `v` can be placed on the axis.
fn drawable(v: f64, log: bool) -> bool {
    v.is_finite() && (!log || v > 0.0)
}

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    spec: &Spec,
    series: &[Series],
) -> std::result::Result<(), String> {
    root.fill(&WHITE).map_err(|e| e.to_string())?;
    let keep: Vec<Vec<(f64, f64)>> = series
        .iter()
        .map(|s| {
            s.points
                .iter()
                .copied()
                .filter(|&(x, y)| drawable(x, spec.log_x) && drawable(y, spec.log_y))
                .collect()
        })
        .collect();
    let xr = range(keep.iter().flatten().map(|p| p.0), spec.log_x);
    let yr = range(keep.iter().flatten().map(|p| p.1), spec.log_y);
    let corner = emptiest_corner(&keep, (&xr, spec.log_x), (&yr, spec.log_y));
    // The four axis combinations have four coordinate types.
    match (spec.log_x, spec.log_y) {
        (false, false) => plot(root, spec, series, &keep, corner, xr, yr),
        (true, false) => plot(root, spec, series, &keep, corner, xr.log_scale(), yr),
        (false, true) => plot(root, spec, series, &keep, corner, xr, yr.log_scale()),
        (true, true) => plot(
            root,
            spec,
            series,
            &keep,
            corner,
            xr.log_scale(),
            yr.log_scale(),
        ),
    }
}

/// Share of the plot's width and height a legend is taken to cover in its corner.
const LEGEND_BOX: (f64, f64) = (0.55, 0.4);

/// The corner of the plot whose legend-sized box covers the fewest points (upper right
/// first on ties), so that the legend hides as little data as it can.
fn emptiest_corner(
    points: &[Vec<(f64, f64)>],
    (xr, log_x): (&Range<f64>, bool),
    (yr, log_y): (&Range<f64>, bool),
) -> SeriesLabelPosition {
    let unit = |v: f64, r: &Range<f64>, log: bool| {
        if log {
            (v.ln() - r.start.ln()) / (r.end.ln() - r.start.ln())
        } else {
            (v - r.start) / (r.end - r.start)
        }
    };
    let (w, h) = LEGEND_BOX;
    let corners = [
        (SeriesLabelPosition::UpperRight, true, true),
        (SeriesLabelPosition::UpperLeft, false, true),
        (SeriesLabelPosition::LowerRight, true, false),
        (SeriesLabelPosition::LowerLeft, false, false),
    ];
    let covered = |right: bool, upper: bool| {
        points
            .iter()
            .flatten()
            .filter(|&&(x, y)| {
                let (u, v) = (unit(x, xr, log_x), unit(y, yr, log_y));
                (if right { u >= 1.0 - w } else { u <= w })
                    && (if upper { v >= 1.0 - h } else { v <= h })
            })
            .count()
    };
    let mut best = (usize::MAX, SeriesLabelPosition::UpperRight);
    for (pos, right, upper) in corners {
        let n = covered(right, upper);
        if n < best.0 {
            best = (n, pos);
        }
    }
    best.1
}

/// Tick label: plain for moderate magnitudes, `1e-5` style otherwise.
fn tick(v: &f64) -> String {
    let a = v.abs();
    if *v == 0.0 {
        "0".into()
    } else if (1e-3..1e5).contains(&a) {
        let s = format!("{v:.3}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        format!("{v:.0e}")
    }
}

/// A log axis's tick label: only at 1, 2 and 5 times a power of ten (blank elsewhere), so
/// that the labels of a range crossing a decade do not run into each other.
fn log_tick(v: &f64) -> String {
    let a = v.abs();
    if !(a > 0.0 && a.is_finite()) {
        return tick(v);
    }
    let m = a / 10f64.powf(a.log10().floor());
    if [1.0, 2.0, 5.0, 10.0]
        .iter()
        .any(|&k| (m - k).abs() < 1e-6 * k)
    {
        tick(v)
    } else {
        String::new()
    }
}

fn plot<DB, X, Y>(
    root: &DrawingArea<DB, Shift>,
    spec: &Spec,
    series: &[Series],
    keep: &[Vec<(f64, f64)>],
    corner: SeriesLabelPosition,
    xr: X,
    yr: Y,
) -> std::result::Result<(), String>
where
    DB: DrawingBackend,
    X: plotters::coord::ranged1d::AsRangedCoord<Value = f64>,
    Y: plotters::coord::ranged1d::AsRangedCoord<Value = f64>,
    X::CoordDescType: plotters::coord::ranged1d::ValueFormatter<f64>,
    Y::CoordDescType: plotters::coord::ranged1d::ValueFormatter<f64>,
{
    let err = |e: &dyn std::fmt::Display| e.to_string();
    let mut ch = ChartBuilder::on(root)
        .caption(spec.title, ("sans-serif", 24))
        .margin(16)
        .x_label_area_size(50)
        .y_label_area_size(80)
        .build_cartesian_2d(xr, yr)
        .map_err(|e| err(&e))?;
    // A linear axis's ticks are multiples of a step computed in floating point, so the
    // one at zero can come out as 2e-18: a tick within 1e-9 of the axis's span of zero is
    // labelled 0.
    let span = |log: bool, v: fn(&(f64, f64)) -> f64| {
        let r = range(keep.iter().flatten().map(v), log);
        r.end - r.start
    };
    let (sx, sy) = (span(spec.log_x, |p| p.0), span(spec.log_y, |p| p.1));
    // A log axis's key points hold each power of ten twice (ten times the decade below, and
    // the decade's own): a value equal to the one labelled just before gets no label, or
    // the two would print over each other. Plotters formats the key points once, in order.
    let labeller = |log: bool, span: f64| {
        let last = std::cell::Cell::new(f64::NAN);
        move |v: &f64| {
            if last.replace(*v) == *v {
                String::new()
            } else if log {
                log_tick(v)
            } else {
                tick(&if v.abs() < 1e-9 * span { 0.0 } else { *v })
            }
        }
    };
    let (lx, ly) = (labeller(spec.log_x, sx), labeller(spec.log_y, sy));
    ch.configure_mesh()
        .x_label_formatter(&lx)
        .y_label_formatter(&ly)
        .x_desc(spec.x_label)
        .y_desc(spec.y_label)
        .label_style(("sans-serif", 15))
        .axis_desc_style(("sans-serif", 17))
        .light_line_style(RGBColor(235, 235, 235))
        .bold_line_style(RGBColor(205, 205, 205))
        .draw()
        .map_err(|e| err(&e))?;
    for (k, (s, pts)) in series.iter().zip(keep).enumerate() {
        let c = colour(k);
        let style = ShapeStyle::from(c).stroke_width(2);
        let anno = match spec.mark {
            Mark::Line => {
                ch.draw_series(LineSeries::new(pts.iter().copied(), style))
                    .map_err(|e| err(&e))?;
                ch.draw_series(pts.iter().map(|&p| Circle::new(p, 3, c.filled())))
                    .map_err(|e| err(&e))?
            }
            Mark::Scatter => ch
                .draw_series(pts.iter().map(|&p| Circle::new(p, 3, c.filled())))
                .map_err(|e| err(&e))?,
        };
        anno.label(s.name.clone()).legend(move |(x, y)| {
            PathElement::new(
                vec![(x, y), (x + 20, y)],
                ShapeStyle::from(c).stroke_width(3),
            )
        });
    }
    if series.iter().any(|s| !s.name.is_empty()) {
        ch.configure_series_labels()
            .position(corner)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 15))
            .draw()
            .map_err(|e| err(&e))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_svg_and_png() {
        let dir = super::super::test_dir("chart");
        let s = vec![
            Series::new(
                "1/sqrt(n)",
                (1..6)
                    .map(|k| (10f64.powi(k), 10f64.powf(-0.5 * k as f64)))
                    .collect(),
            ),
            Series::new(
                "1/n",
                (1..6).map(|k| (10f64.powi(k), 10f64.powi(-k))).collect(),
            ),
            // A zero cannot go on a log axis: dropped, not an error.
            Series::new("with zero", vec![(10.0, 0.0), (100.0, 1e-3)]),
        ];
        let files =
            line_chart(&dir.join("err"), "Error", "rays", "|error|", true, true, &s).unwrap();
        assert_eq!(files, vec![dir.join("err.svg"), dir.join("err.png")]);
        let svg = std::fs::read_to_string(&files[0]).unwrap();
        assert!(
            svg.starts_with("<svg") && svg.contains("1/sqrt(n)"),
            "{svg:.200}"
        );
        let png = std::fs::read(&files[1]).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        let decoder = png::Decoder::new(std::io::Cursor::new(png));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), SIZE);
        // Something other than the white background was drawn (axes, text, lines).
        let dark = buf.chunks(3).filter(|p| p.iter().all(|&c| c < 100)).count();
        assert!(dark > 1000, "{dark} dark pixels");
        let blue = buf.chunks(3).filter(|p| p == &[0, 114, 178]).count();
        assert!(blue > 100, "first series not drawn: {blue}");

        let files = scatter_chart(&dir.join("sc"), "S", "x", "y", false, false, &s).unwrap();
        assert!(files.iter().all(|f| f.exists()));
        // Empty input still gives a (blank) chart.
        line_chart(&dir.join("empty"), "E", "x", "y", true, true, &[]).unwrap();
    }

    #[test]
    fn axes_label_zero_0_and_each_power_of_ten_once() {
        // The worst face errors of a bake study: the axis's range starts just below 0, and
        // the tick there came out as 2e-18.
        let dir = super::super::test_dir("chart-zero");
        let s = vec![
            Series::new(
                "uniform",
                vec![
                    (1.45, 0.0853),
                    (4.93, 0.0724),
                    (19.9, 0.0465),
                    (76.9, 0.0344),
                ],
            ),
            Series::new(
                "hierarchical",
                vec![
                    (11.8, 0.0091),
                    (21.6, 0.0045),
                    (47.6, 0.0022),
                    (103.4, 0.0023),
                    (236.6, 0.0012),
                ],
            ),
        ];
        let files = line_chart(&dir.join("f"), "F", "cpu", "error", true, false, &s).unwrap();
        let svg = std::fs::read_to_string(&files[0]).unwrap();
        let labels: Vec<&str> = svg
            .split("</text>")
            .filter_map(|t| t.rsplit('>').next().map(str::trim))
            .collect();
        assert!(labels.contains(&"0"), "no tick labelled 0: {labels:?}");
        assert!(
            !labels.iter().any(|l| l.contains("e-")),
            "a tick labelled like 2e-18: {labels:?}"
        );
        // Against rays, the log axis crosses 1e8 once: one label (it came out twice).
        let by_rays = vec![
            Series::new(
                "uniform",
                vec![
                    (8.7e6, 0.085),
                    (3.45e7, 0.072),
                    (1.45e8, 0.047),
                    (5.53e8, 0.034),
                ],
            ),
            Series::new(
                "hierarchical",
                vec![
                    (1.1e7, 0.009),
                    (1.96e7, 0.0045),
                    (5.25e7, 0.0022),
                    (1.35e8, 0.0023),
                    (4.03e8, 0.0012),
                ],
            ),
        ];
        let files = line_chart(&dir.join("r"), "R", "rays", "e", true, true, &by_rays).unwrap();
        let svg = std::fs::read_to_string(&files[0]).unwrap();
        let n = svg
            .split("</text>")
            .filter(|t| t.rsplit('>').next().map(str::trim) == Some("1e8"))
            .count();
        assert_eq!(n, 1, "1e8 labelled {n} times");
    }
}
