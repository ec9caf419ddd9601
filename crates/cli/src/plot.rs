//! The `--plot` picture: a quick look at a run without leaving the terminal. The
//! mask's maximum-intensity projection along axis 0 (axis 1 down, axis 2 across,
//! in physical proportions) in grey on black, every graph edge drawn over it in
//! the viridis colour of its radius, and a colour bar with ticks and the label
//! "radius (physical units)" at the right. The picture grows with the volume (a few
//! pixels per voxel, within bounds), and its lines and text grow with the picture.

use crate::Failure;
use ab_glyph::{point, Font, FontRef, PxScale, ScaleFont};
use image::codecs::png::PngEncoder;
use image::{imageops, ImageEncoder, Rgb, RgbImage};
use imageproc::drawing::{
    draw_antialiased_line_segment_mut, draw_antialiased_polygon_mut, draw_filled_circle_mut, draw_filled_rect_mut,
    draw_text_mut, text_size,
};
use imageproc::pixelops::interpolate;
use imageproc::point::Point;
use imageproc::rect::Rect;
use ndarray::{ArrayView3, Axis};
use std::io;
use std::path::Path;
use vesselflow::Skeleton;

/// Pixels per voxel (of the finer in-plane spacing) along the longer side of the
/// projection, before [`MIN_LONG_SIDE_PX`] and [`MAX_LONG_SIDE_PX`] bound it.
pub(crate) const PX_PER_VOXEL: f64 = 4.0;
/// The longer side of the projection is at least this many pixels (small volumes)...
pub(crate) const MIN_LONG_SIDE_PX: f64 = 600.0;
/// ...and at most this many (large volumes: the PNG stays a few megabytes).
pub(crate) const MAX_LONG_SIDE_PX: f64 = 2400.0;
/// The colour bar's label.
pub(crate) const BAR_LABEL: &str = "radius (physical units)";
/// Foreground of the projection: a mid grey, so that every viridis colour stands out.
const FOREGROUND: Rgb<u8> = Rgb([110, 110, 110]);
const BACKGROUND: Rgb<u8> = Rgb([0, 0, 0]);
const TEXT: Rgb<u8> = Rgb([235, 235, 235]);

/// The picture, the radii at the bottom and top of its colour bar, and where the
/// bar and its ticks are (for the tests).
pub(crate) struct Plot {
    pub image: RgbImage,
    pub radius_range: Option<[f64; 2]>,
    /// Sizes in pixels the picture was drawn with.
    #[cfg_attr(not(test), allow(dead_code))]
    pub layout: Layout,
    /// Left, top, right (exclusive) and bottom (exclusive) pixel of the colour bar.
    #[cfg_attr(not(test), allow(dead_code))]
    pub bar: [u32; 4],
    /// The ticks of the colour bar: radius and pixel row, smallest radius first.
    #[cfg_attr(not(test), allow(dead_code))]
    pub ticks: Vec<(f64, u32)>,
}

/// Sizes of the picture, in pixels: all derived from the projection's longer side,
/// so a picture twice as large has lines, text and colour bar twice as large.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Layout {
    /// Pixels per voxel along axes 1 and 2.
    pub per_voxel: [f64; 2],
    /// The projection's `(width, height)`.
    pub map: (u32, u32),
    /// Width of the graph's edges.
    pub line_px: f64,
    /// Height of the text.
    pub font_px: f32,
}

/// Refuse a plot path before the run: not `.png` is a usage error; a directory
/// that is missing or refuses a new file is an I/O error.
pub(crate) fn check_output(path: &Path) -> Result<(), Failure> {
    let is_png = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if !is_png {
        return Err(Failure::Usage(format!("cannot write {}: unsupported plot format (use .png)", path.display())));
    }
    vesselflow_io::check_writable(path).map_err(|e| Failure::Run(e.to_string()))
}

/// The picture's sizes for a mask of `shape` with voxel size `spacing`. One physical
/// unit is as long on both axes; the longer side has [`PX_PER_VOXEL`] pixels per
/// voxel of the finer in-plane spacing, within [`MIN_LONG_SIDE_PX`] and
/// [`MAX_LONG_SIDE_PX`]; lines are 1/300 and text 1/40 of that side (at least 2 and 14 px).
pub(crate) fn layout(shape: [usize; 3], spacing: [f64; 3]) -> Layout {
    let (height_units, width_units) = (shape[1] as f64 * spacing[1], shape[2] as f64 * spacing[2]);
    let long_units = height_units.max(width_units);
    let long_voxels = long_units / spacing[1].min(spacing[2]);
    let long_px = (PX_PER_VOXEL * long_voxels).clamp(MIN_LONG_SIDE_PX, MAX_LONG_SIDE_PX);
    let px_per_unit = long_px / long_units;
    let height = (height_units * px_per_unit).round().max(1.0) as u32;
    let width = (width_units * px_per_unit).round().max(1.0) as u32;
    let per_voxel = [f64::from(height) / shape[1].max(1) as f64, f64::from(width) / shape[2].max(1) as f64];
    Layout {
        per_voxel,
        map: (width, height),
        line_px: (long_px / 300.0).max(2.0),
        font_px: (long_px / 40.0).max(14.0) as f32,
    }
}

/// Draw `skel` (positions in physical units, array axis order) over the
/// projection of `mask` (voxel size `spacing`).
pub(crate) fn render(mask: ArrayView3<'_, u8>, spacing: [f64; 3], skel: &Skeleton) -> Plot {
    let shape = [mask.len_of(Axis(0)), mask.len_of(Axis(1)), mask.len_of(Axis(2))];
    let layout = layout(shape, spacing);
    let (width, height) = layout.map;
    let per_voxel = layout.per_voxel;
    let font = FontRef::try_from_slice(epaint_default_fonts::HACK_REGULAR).expect("the bundled font parses");
    let scale = PxScale::from(layout.font_px);

    let edge_radius = |&[a, b]: &[usize; 2]| 0.5 * (skel.radii[a] + skel.radii[b]);
    let radius_range = skel
        .edges
        .iter()
        .map(edge_radius)
        .fold(None, |range: Option<[f64; 2]>, r| Some(range.map_or([r, r], |[lo, hi]| [lo.min(r), hi.max(r)])));
    let [lo, hi] = radius_range.unwrap_or([0.0, 1.0]);
    let ticks = radius_range.map_or_else(Vec::new, |[lo, hi]| nice_ticks(lo, hi));
    let labels: Vec<String> = ticks.iter().map(|&t| format_tick(t, &ticks)).collect();

    // The colour bar panel: gap, bar, tick marks, tick labels, the rotated label.
    let font_px = f64::from(layout.font_px);
    let gap = (font_px * 0.8).round() as u32;
    let bar_width = (font_px * 1.2).round() as u32;
    let tick_len = (font_px * 0.4).round() as u32;
    let label_width = labels.iter().map(|l| text_size(scale, &font, l).0).max().unwrap_or(0);
    let title_width = text_size(scale, &font, BAR_LABEL).0;
    let line_height = (font_px * 1.4).ceil() as u32;
    let bar_left = width + gap;
    let labels_left = bar_left + bar_width + tick_len + tick_len / 2;
    let title_left = labels_left + label_width + gap;
    let total_width = title_left + line_height + gap;
    // The bar is at least as tall as its label; half a line of text above and below
    // it leaves room for the end ticks' labels.
    let margin = (font_px * 0.75).round() as u32;
    let total_height = height.max(title_width + 2 * gap).max(6 * (layout.font_px as u32));
    let bar = [bar_left, margin, bar_left + bar_width, total_height - margin];
    let mut image = RgbImage::from_pixel(total_width, total_height, BACKGROUND);

    let projection = mask.map_axis(Axis(0), |column| column.iter().any(|&v| v != 0));
    for y in 0..height {
        let j = ((f64::from(y) + 0.5) / per_voxel[0]) as usize;
        for x in 0..width {
            let k = ((f64::from(x) + 0.5) / per_voxel[1]) as usize;
            if projection.get((j.min(shape[1] - 1), k.min(shape[2] - 1))) == Some(&true) {
                image.put_pixel(x, y, FOREGROUND);
            }
        }
    }

    // Pixel (x, y) has its centre at voxel coordinate ((y + 0.5) / per_voxel, ...).
    let pixel = |p: &[f64; 3]| -> [f64; 2] {
        let y = (p[1] / spacing[1] + 0.5) * per_voxel[0] - 0.5;
        let x = (p[2] / spacing[2] + 0.5) * per_voxel[1] - 0.5;
        [x.clamp(0.0, f64::from(width - 1)), y.clamp(0.0, f64::from(height - 1))]
    };
    let colour_of = |r: f64| {
        let t = if hi > lo { (r - lo) / (hi - lo) } else { 0.5 };
        let c = colorous::VIRIDIS.eval_continuous(t.clamp(0.0, 1.0));
        Rgb([c.r, c.g, c.b])
    };
    // Thin vessels last, so a small branch is not hidden under its trunk.
    let mut edges: Vec<&[usize; 2]> = skel.edges.iter().collect();
    edges.sort_by(|a, b| edge_radius(b).total_cmp(&edge_radius(a)));
    for edge in edges {
        let (start, end) = (pixel(&skel.positions[edge[0]]), pixel(&skel.positions[edge[1]]));
        draw_thick_segment(&mut image, start, end, layout.line_px, colour_of(edge_radius(edge)));
    }

    // The colour bar: the smallest radius at the bottom, the largest at the top.
    let [left, top, right, bottom] = bar;
    let row_of = |r: f64| {
        let t = if hi > lo { (r - lo) / (hi - lo) } else { 0.5 };
        (f64::from(bottom - 1) - t * f64::from(bottom - 1 - top)).round() as u32
    };
    for y in top..bottom {
        let t = f64::from(bottom - 1 - y) / f64::from((bottom - 1 - top).max(1));
        draw_filled_rect_mut(
            &mut image,
            Rect::at(left as i32, y as i32).of_size(right - left, 1),
            colour_of(lo + t * (hi - lo)),
        );
    }
    let tick_rows: Vec<(f64, u32)> = ticks.iter().map(|&t| (t, row_of(t))).collect();
    let tick_thickness = (layout.line_px / 2.0).round().max(1.0) as u32;
    for ((_, y), label) in tick_rows.iter().zip(&labels) {
        let mark_top = y.saturating_sub(tick_thickness / 2) as i32;
        draw_filled_rect_mut(&mut image, Rect::at(right as i32, mark_top).of_size(tick_len, tick_thickness), TEXT);
        let label_top = *y as i32 - digit_middle(&font, scale);
        draw_text_mut(&mut image, TEXT, labels_left as i32, label_top, scale, &font, label);
    }
    let mut title = RgbImage::from_pixel(title_width + 2, line_height, BACKGROUND);
    draw_text_mut(&mut title, TEXT, 0, 0, scale, &font, BAR_LABEL);
    let title = imageops::rotate270(&title); // read from bottom to top
    let title_top = (i64::from(top + bottom) - i64::from(title.height())) / 2;
    imageops::overlay(&mut image, &title, i64::from(title_left), title_top.max(0));
    Plot { image, radius_range, layout, bar, ticks: tick_rows }
}

/// How far below the `y` given to `draw_text_mut` the middle of a digit lies, to
/// centre a tick's label on its mark.
fn digit_middle(font: &FontRef<'_>, scale: PxScale) -> i32 {
    let ascent = font.as_scaled(scale).ascent();
    let glyph = font.glyph_id('0').with_scale_and_position(scale, point(0.0, ascent));
    font.outline_glyph(glyph).map_or(ascent / 2.0, |g| 0.5 * (g.px_bounds().min.y + g.px_bounds().max.y)).round() as i32
}

/// A segment `width` pixels wide with round ends, from `a` to `b` (pixel centres).
fn draw_thick_segment(image: &mut RgbImage, a: [f64; 2], b: [f64; 2], width: f64, colour: Rgb<u8>) {
    let round = |p: [f64; 2]| (p[0].round() as i32, p[1].round() as i32);
    let half = width / 2.0;
    let radius = half.round() as i32;
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let length = dx.hypot(dy);
    if length >= 1.0 {
        // The normal, half a line width long: the quad's corners lie on both sides.
        let (nx, ny) = (-dy / length * half, dx / length * half);
        let corners = [[a[0] + nx, a[1] + ny], [b[0] + nx, b[1] + ny], [b[0] - nx, b[1] - ny], [a[0] - nx, a[1] - ny]];
        let mut polygon: Vec<Point<i32>> = Vec::with_capacity(4);
        for corner in corners {
            let (x, y) = round(corner);
            if polygon.last() != Some(&Point::new(x, y)) {
                polygon.push(Point::new(x, y));
            }
        }
        while polygon.len() > 1 && polygon.first() == polygon.last() {
            polygon.pop();
        }
        if polygon.len() >= 3 {
            draw_antialiased_polygon_mut(image, &polygon, colour, interpolate);
        } else {
            draw_antialiased_line_segment_mut(image, round(a), round(b), colour, interpolate);
        }
    }
    for end in [a, b] {
        draw_filled_circle_mut(image, round(end), (radius - 1).max(0), colour);
    }
}

/// About six ticks at round values (1, 2 or 5 times a power of ten) within `[lo, hi]`;
/// just `lo` when the range is a single value.
pub(crate) fn nice_ticks(lo: f64, hi: f64) -> Vec<f64> {
    if hi <= lo || !(hi - lo).is_finite() {
        return vec![lo];
    }
    let rough = (hi - lo) / 6.0;
    let power = 10f64.powf(rough.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0].into_iter().map(|m| m * power).find(|&s| s >= rough).unwrap_or(10.0 * power);
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    let ticks: Vec<f64> = (first..=last).map(|i| i as f64 * step).filter(|t| (lo..=hi).contains(t)).collect();
    if ticks.is_empty() {
        vec![lo]
    } else {
        ticks
    }
}

/// `value` with as many decimals as the spacing of `ticks` needs (three for a single tick).
fn format_tick(value: f64, ticks: &[f64]) -> String {
    let step = if ticks.len() > 1 { ticks[1] - ticks[0] } else { 1e-3 * value.abs().max(1e-12) };
    let decimals = (-step.log10().floor()).clamp(0.0, 12.0) as usize;
    format!("{value:.decimals$}")
}

/// Write `image` as PNG to `path`, atomically: a temporary file beside it, renamed
/// over `path` only once complete.
pub(crate) fn write_png(path: &Path, image: &RgbImage) -> Result<(), Failure> {
    vesselflow_io::write_atomically(path, |writer| {
        PngEncoder::new(writer)
            .write_image(image.as_raw(), image.width(), image.height(), image::ExtendedColorType::Rgb8)
            .map_err(io::Error::other)
    })
    .map_err(|e| Failure::Run(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    fn colour(t: f64) -> Rgb<u8> {
        let c = colorous::VIRIDIS.eval_continuous(t);
        Rgb([c.r, c.g, c.b])
    }

    #[test]
    fn layout_keeps_physical_proportions() {
        // 21 voxels of 2 units down (42), 40 of 1 across (40): down is the long side,
        // 42 voxels of the finer spacing, 168 px at 4 px per voxel: the minimum applies.
        let layout_ = layout([5, 21, 40], [1.0, 2.0, 1.0]);
        assert_eq!(layout_.map, (571, 600));
        let [py, px] = layout_.per_voxel;
        assert!((py / px - 2.0).abs() < 0.01, "a voxel is twice as tall as wide: {py} {px}");
        assert_eq!(layout([5, 10, 30], [1.0, 1.0, 1.0]).map, (600, 200));
    }

    #[test]
    fn picture_lines_and_text_grow_with_the_volume() {
        let small = layout([10, 100, 100], [1.0; 3]);
        let large = layout([10, 500, 250], [1.0; 3]);
        let huge = layout([10, 5000, 100], [1.0; 3]);
        assert_eq!(small.map, (600, 600));
        assert_eq!(large.map, (1000, 2000)); // 4 px per voxel
        assert_eq!(huge.map.1, 2400); // bounded
        assert!(large.line_px > 3.0 * small.line_px, "{} vs {}", large.line_px, small.line_px);
        assert!(large.font_px > 3.0 * small.font_px);
        assert_eq!(small.line_px, 2.0);
        // Anisotropic: 15 slices of 5 µm, 512 x 512 of 0.994 µm: 4 px per in-plane voxel.
        assert_eq!(layout([15, 512, 512], [5.0, 0.994, 0.994]).map, (2048, 2048));
    }

    #[test]
    fn ticks_are_round_values_within_the_range() {
        let ticks = nice_ticks(1.5, 2.5);
        assert_eq!(ticks.len(), 5);
        assert!((ticks[0] - 1.6).abs() < 1e-12 && (ticks[4] - 2.4).abs() < 1e-12, "{ticks:?}");
        assert_eq!(nice_ticks(0.0, 10.0), [0.0, 2.0, 4.0, 6.0, 8.0, 10.0]);
        assert_eq!(nice_ticks(3.0, 3.0), [3.0]);
        let labels: Vec<String> = ticks.iter().map(|&t| format_tick(t, &ticks)).collect();
        assert_eq!(labels, ["1.6", "1.8", "2.0", "2.2", "2.4"]);
        assert_eq!(format_tick(10.0, &[0.0, 10.0]), "10");
    }

    #[test]
    fn edge_colours_follow_the_radius_and_the_bar_has_ticks_and_a_label() {
        let mut mask = Array3::<u8>::zeros((3, 10, 20));
        mask.slice_mut(ndarray::s![1, 4..7, ..]).fill(1);
        let skel = Skeleton {
            positions: vec![[1.0, 5.0, 2.0], [1.0, 5.0, 10.0], [1.0, 5.0, 17.0]],
            radii: vec![1.0, 2.0, 3.0],
            edges: vec![[0, 1], [1, 2]],
            ..Default::default()
        };
        let plot = render(mask.view(), [1.0; 3], &skel);
        assert_eq!(plot.radius_range, Some([1.5, 2.5]));
        let (w, h) = (600, 300);
        assert_eq!(plot.layout.map, (w, h));
        assert!(plot.image.width() > w + 100, "room for the bar, its ticks and its label");
        let y = 165; // row of voxel 5's centre: (5 + 0.5) * 30 - 0.5, rounded
        assert_eq!(plot.image.get_pixel(150, y), &colour(0.0));
        assert_eq!(plot.image.get_pixel(450, y), &colour(1.0));
        // Lines are `line_px` (2) wide: the rows next to the centre are coloured too, not
        // two rows away.
        assert_eq!(plot.image.get_pixel(150, y + 1), &colour(0.0));
        assert_eq!(plot.image.get_pixel(150, y + 4), &FOREGROUND);
        assert_eq!(plot.image.get_pixel(150, 30), &BACKGROUND);

        let [left, top, right, bottom] = plot.bar;
        let middle = (left + right) / 2;
        assert_eq!(plot.image.get_pixel(middle, bottom - 1), &colour(0.0));
        assert_eq!(plot.image.get_pixel(middle, top), &colour(1.0));
        // Ticks at 1.6 .. 2.4, each a light mark right of the bar at its radius's row.
        let radii: Vec<f64> = plot.ticks.iter().map(|&(r, _)| r).collect();
        assert_eq!(radii.len(), 5, "{radii:?}");
        for &(r, row) in &plot.ticks {
            let expected = f64::from(bottom - 1) - (r - 1.5) * f64::from(bottom - 1 - top);
            assert!((f64::from(row) - expected).abs() <= 1.0, "tick {r} at row {row}, not {expected}");
            assert_eq!(plot.image.get_pixel(right + 1, row), &TEXT, "tick mark of {r}");
            assert_eq!(plot.image.get_pixel(right + 1, row + 6), &BACKGROUND, "the mark of {r} is thin");
        }
        // Text (tick labels and the bar's label) fills part of the panel right of the marks.
        let light = |x0: u32, x1: u32| {
            (x0..x1)
                .flat_map(|x| (0..plot.image.height()).map(move |y| (x, y)))
                .filter(|&(x, y)| plot.image.get_pixel(x, y)[0] > 128)
                .count()
        };
        let panel_right = plot.image.width();
        assert!(light(right + 10, panel_right) > 500, "tick labels and the label are drawn");
        // The label runs vertically: its light pixels span most of the bar's height.
        let title_x0 = panel_right - 40;
        let rows: Vec<u32> = (0..plot.image.height())
            .filter(|&y| (title_x0..panel_right).any(|x| plot.image.get_pixel(x, y)[0] > 128))
            .collect();
        let span = rows.last().unwrap() - rows.first().unwrap();
        assert!(span > 150, "the label is {span} px tall");
    }

    #[test]
    fn a_graph_without_edges_gets_a_bar_without_ticks() {
        let mask = Array3::<u8>::ones((2, 5, 5));
        let plot = render(mask.view(), [1.0; 3], &Skeleton::default());
        assert_eq!(plot.radius_range, None);
        assert!(plot.ticks.is_empty());
    }
}
