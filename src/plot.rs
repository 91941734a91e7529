//! Labelled line and scatter charts (title, axis labels with units, a legend), drawn with
//! `plotters` as PNG (its bitmap backend into a buffer, encoded by `image`) or SVG.
//!
//! Text is drawn with DejaVu Sans compiled into the binary (assets/fonts/, its licence
//! beside it) through plotters' `ab_glyph` engine: no fontconfig, no system font, so the
//! default build needs no system package. The SVG keeps its text as `<text>` elements.

use plotters::coord::Shift;
use plotters::prelude::*;
use std::sync::Once;

/// DejaVu Sans 2.37 (the Bitstream Vera licence: assets/fonts/LICENSE-DejaVu.txt).
static FONT: &[u8] = include_bytes!("../assets/fonts/DejaVuSans.ttf");
/// The family every text of a chart asks for.
const FAMILY: &str = "sans-serif";

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Style {
    /// Points joined by lines, each point marked.
    Lines,
    /// Marks only (many points, or values that are not a sequence).
    Points,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// The legend's text.
    pub label: String,
    pub points: Vec<(f64, f64)>,
    pub style: Style,
    /// Each point's standard uncertainty in y, drawn as an error bar ±u (empty: none).
    pub y_u: Vec<f64>,
}

/// A chart to draw: everything a reader needs is in its text.
#[derive(Debug, Clone, PartialEq)]
pub struct Chart {
    pub title: String,
    /// Axis labels, with their units.
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
    /// Names for x = 1, 2, … instead of numbers (Figure 5's cases).
    pub x_names: Option<Vec<String>>,
    /// Size in pixels (PNG) or user units (SVG).
    pub size: (u32, u32),
}

/// Tableau's ten colours, then black and a blue: lines A–F read as in the paper's figure.
const COLOURS: [RGBColor; 12] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
    RGBColor(0, 0, 0),
    RGBColor(100, 100, 255),
];

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font is compiled in: it parses, or no chart could ever have text.
        let registered = plotters::style::register_font(FAMILY, FontStyle::Normal, FONT);
        assert!(registered.is_ok(), "the bundled DejaVu Sans does not parse");
    });
}

impl Chart {
    /// The chart as a PNG file's bytes.
    pub fn png(&self) -> Result<Vec<u8>, String> {
        register_font();
        let (w, h) = self.size;
        let mut rgb = vec![0u8; w as usize * h as usize * 3];
        {
            let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
            self.draw(&root).map_err(|e| e.to_string())?;
        }
        let img = image::RgbImage::from_raw(w, h, rgb).expect("a buffer of the chart's size");
        let mut png = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .map_err(|e| e.to_string())?;
        Ok(png)
    }

    /// The chart as an SVG document.
    pub fn svg(&self) -> Result<String, String> {
        register_font();
        let mut svg = String::new();
        {
            let root = SVGBackend::with_string(&mut svg, self.size).into_drawing_area();
            self.draw(&root).map_err(|e| e.to_string())?;
        }
        Ok(svg)
    }

    /// The data's extent, a little wider so marks at the ends are whole; (0, 1) on an axis
    /// with no finite value, one unit either side of a single value.
    fn bounds(&self) -> ((f64, f64), (f64, f64)) {
        // Error bars' ends count, so a bar is never cut off.
        let ends: Vec<(f64, f64)> = self
            .series
            .iter()
            .flat_map(|s| s.points.iter().zip(&s.y_u))
            .flat_map(|(&(x, y), &u)| [(x, y - u), (x, y + u)])
            .collect();
        let pts = || {
            self.series
                .iter()
                .flat_map(|s| &s.points)
                .chain(&ends)
                .filter(finite)
        };
        let range = |v: &mut dyn Iterator<Item = f64>| {
            let (lo, hi) = v.fold((f64::MAX, f64::MIN), |(lo, hi), x| (lo.min(x), hi.max(x)));
            let d = hi - lo;
            if lo > hi {
                (0.0, 1.0)
            } else if d == 0.0 {
                (lo - 1.0, hi + 1.0)
            } else {
                (lo - 0.05 * d, hi + 0.05 * d)
            }
        };
        let x = match &self.x_names {
            // Categories: 1..=n, half a step of room either side.
            Some(n) => (0.5, n.len().max(1) as f64 + 0.5),
            None => range(&mut pts().map(|p| p.0)),
        };
        (x, range(&mut pts().map(|p| p.1)))
    }

    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
    ) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
        root.fill(&WHITE)?;
        let ((x0, x1), (y0, y1)) = self.bounds();
        let mut chart = ChartBuilder::on(root)
            .caption(&self.title, (FAMILY, 18))
            .margin(14)
            .x_label_area_size(44)
            .y_label_area_size(70)
            .build_cartesian_2d(x0..x1, y0..y1)?;
        let names = self.x_names.clone().unwrap_or_default();
        let name_of = |x: &f64| {
            let i = x.round();
            match (i - x).abs() < 1e-6 && i >= 1.0 {
                true => names.get(i as usize - 1).cloned().unwrap_or_default(),
                false => String::new(),
            }
        };
        let mut mesh = chart.configure_mesh();
        mesh.x_desc(&self.x_label)
            .y_desc(&self.y_label)
            .label_style((FAMILY, 13))
            .axis_desc_style((FAMILY, 15))
            .x_label_formatter(&tick)
            .y_label_formatter(&tick);
        if self.x_names.is_some() {
            mesh.x_labels(names.len() * 2 + 1)
                .x_label_formatter(&name_of);
        }
        mesh.draw()?;
        for (i, s) in self.series.iter().enumerate() {
            draw_series(&mut chart, s, COLOURS[i % COLOURS.len()])?;
        }
        if !self.series.is_empty() {
            chart
                .configure_series_labels()
                .label_font((FAMILY, 13))
                // See-through: a legend of many targets may lie over data.
                .background_style(WHITE.mix(0.6))
                .border_style(BLACK)
                .position(SeriesLabelPosition::UpperRight)
                .draw()?;
        }
        root.present()
    }
}

/// A tick's number without the noise of its float: `2`, `0.5`, `-12.5`.
fn tick(v: &f64) -> String {
    let r = (v * 1e6).round() / 1e6;
    format!("{}", if r == 0.0 { 0.0 } else { r })
}

fn finite(p: &&(f64, f64)) -> bool {
    p.0.is_finite() && p.1.is_finite()
}

type Cartesian =
    Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>;

/// One series and its legend entry: a line for [`Style::Lines`], a mark for points.
fn draw_series<DB: DrawingBackend>(
    chart: &mut ChartContext<'_, DB, Cartesian>,
    s: &Series,
    colour: RGBColor,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let pts: Vec<(f64, f64)> = s.points.iter().filter(finite).copied().collect();
    let radius = if s.style == Style::Lines { 3 } else { 2 };
    let bars = s
        .points
        .iter()
        .zip(&s.y_u)
        .filter(|(p, u)| finite(p) && u.is_finite());
    chart.draw_series(bars.map(|(&(x, y), &u)| {
        PathElement::new(vec![(x, y - u), (x, y + u)], colour.stroke_width(1))
    }))?;
    let marks = chart.draw_series(pts.iter().map(|&p| Circle::new(p, radius, colour.filled())))?;
    match s.style {
        Style::Points => {
            marks
                .label(&s.label)
                .legend(move |(x, y)| Circle::new((x + 10, y), 3, colour.filled()));
        }
        Style::Lines => {
            chart
                .draw_series(LineSeries::new(pts, colour.stroke_width(2)))?
                .label(&s.label)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chart() -> Chart {
        Chart {
            title: "A title".into(),
            x_label: "repeat".into(),
            y_label: "offset − nominal (µm)".into(),
            series: vec![
                Series {
                    label: "A (100 µm)".into(),
                    points: vec![(1.0, 3.0), (2.0, -1.0), (3.0, f64::NAN), (4.0, 2.0)],
                    style: Style::Lines,
                    y_u: Vec::new(),
                },
                Series {
                    label: "scatter".into(),
                    points: vec![(1.5, 0.0)],
                    style: Style::Points,
                    y_u: Vec::new(),
                },
            ],
            x_names: None,
            size: (320, 240),
        }
    }

    #[test]
    fn a_png_of_the_asked_size_with_its_series_colour_and_text() {
        let png = chart().png().unwrap();
        let img = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (320, 240));
        let count = |c: [u8; 3]| img.pixels().filter(|p| p.0 == c).count();
        // The first series' colour: its line and marks.
        assert!(count([31, 119, 180]) > 50);
        // Text and axes: many dark pixels, and more than the axes alone would give.
        let dark = img
            .pixels()
            .filter(|p| p.0.iter().all(|&v| v < 100))
            .count();
        assert!(dark > 1000, "{dark} dark pixels");
    }

    #[test]
    fn error_bars_are_drawn_whole() {
        let mut c = chart();
        c.series = vec![Series {
            label: "with u".into(),
            points: vec![(1.0, 0.0), (2.0, 1.0)],
            style: Style::Points,
            y_u: vec![5.0, f64::NAN],
        }];
        // The axes reach the bar's ends (±5 about 0), not only the points.
        let (_, (y0, y1)) = c.bounds();
        assert!(y0 <= -5.0 && y1 >= 5.0, "{y0}..{y1}");
        // One bar where u is finite; the points alone span the axes, so nothing else moves.
        c.series[0].points = vec![(1.0, -5.0), (2.0, 5.0), (3.0, 0.0)];
        c.series[0].y_u = vec![f64::NAN, f64::NAN, 1.0];
        let bars = c.svg().unwrap().matches("<polyline").count();
        c.series[0].y_u.clear();
        assert_eq!(c.svg().unwrap().matches("<polyline").count() + 1, bars);
    }

    #[test]
    fn an_svg_keeps_its_text_and_named_categories() {
        let mut c = chart();
        c.x_names = Some(vec!["case1".into(), "case2".into()]);
        let svg = c.svg().unwrap();
        for text in [
            "A title",
            "repeat",
            "offset − nominal (µm)",
            "A (100 µm)",
            "scatter",
            "case1",
            "case2",
        ] {
            assert!(svg.contains(text), "{text} missing");
        }
        // A chart without data still draws its axes.
        c.series.clear();
        assert!(c.svg().unwrap().contains("repeat"));
    }
}
