//! The `--plot` picture: a quick look at a run without leaving the terminal. The
//! mask's maximum-intensity projection along axis 0 (axis 1 down, axis 2 across,
//! in physical proportions) in grey on black, every graph edge drawn over it in
//! the viridis colour of its radius, and a colour bar at the right edge.

use crate::Failure;
use image::codecs::png::PngEncoder;
use image::{ImageEncoder, Rgb, RgbImage};
use imageproc::drawing::{draw_antialiased_line_segment_mut, draw_filled_rect_mut};
use imageproc::pixelops::interpolate;
use imageproc::rect::Rect;
use ndarray::{ArrayView3, Axis};
use std::io;
use std::path::Path;
use vesselflow::Skeleton;

/// Pixels on the longer physical side of the projection.
pub(crate) const LONG_SIDE_PX: f64 = 800.0;
/// Black gap between the projection and the colour bar, in pixels.
const BAR_GAP_PX: u32 = 12;
/// Width of the colour bar, in pixels.
const BAR_WIDTH_PX: u32 = 20;
/// Foreground of the projection: a mid grey, so that every viridis colour stands out.
const FOREGROUND: Rgb<u8> = Rgb([110, 110, 110]);
const BACKGROUND: Rgb<u8> = Rgb([0, 0, 0]);

/// The picture, and the radii at the bottom and top of its colour bar.
pub(crate) struct Plot {
    pub image: RgbImage,
    pub radius_range: Option<[f64; 2]>,
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

/// Pixels per voxel along axes 1 and 2, and the projection's size in pixels
/// `(width, height)`: one physical unit is as long on both axes, and the longer
/// side is [`LONG_SIDE_PX`].
pub(crate) fn layout(shape: [usize; 3], spacing: [f64; 3]) -> ([f64; 2], (u32, u32)) {
    let (height_units, width_units) = (shape[1] as f64 * spacing[1], shape[2] as f64 * spacing[2]);
    let px_per_unit = LONG_SIDE_PX / height_units.max(width_units);
    let height = (height_units * px_per_unit).round().max(1.0) as u32;
    let width = (width_units * px_per_unit).round().max(1.0) as u32;
    let per_voxel = [f64::from(height) / shape[1].max(1) as f64, f64::from(width) / shape[2].max(1) as f64];
    (per_voxel, (width, height))
}

/// Draw `skel` (positions in physical units, array axis order) over the
/// projection of `mask` (voxel size `spacing`).
pub(crate) fn render(mask: ArrayView3<'_, u8>, spacing: [f64; 3], skel: &Skeleton) -> Plot {
    let shape = [mask.len_of(Axis(0)), mask.len_of(Axis(1)), mask.len_of(Axis(2))];
    let (per_voxel, (width, height)) = layout(shape, spacing);
    let projection = mask.map_axis(Axis(0), |column| column.iter().any(|&v| v != 0));
    let mut image = RgbImage::from_pixel(width + BAR_GAP_PX + BAR_WIDTH_PX, height, BACKGROUND);
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
    let pixel = |p: &[f64; 3]| -> (i32, i32) {
        let y = (p[1] / spacing[1] + 0.5) * per_voxel[0] - 0.5;
        let x = (p[2] / spacing[2] + 0.5) * per_voxel[1] - 0.5;
        (x.round().clamp(0.0, f64::from(width - 1)) as i32, y.round().clamp(0.0, f64::from(height - 1)) as i32)
    };
    let edge_radius = |&[a, b]: &[usize; 2]| 0.5 * (skel.radii[a] + skel.radii[b]);
    let radius_range = skel
        .edges
        .iter()
        .map(edge_radius)
        .fold(None, |range: Option<[f64; 2]>, r| Some(range.map_or([r, r], |[lo, hi]| [lo.min(r), hi.max(r)])));
    let [lo, hi] = radius_range.unwrap_or([0.0, 1.0]);
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
        let colour = colour_of(edge_radius(edge));
        if start == end {
            // Wu's algorithm divides by the length; a one-pixel edge is one pixel.
            image.put_pixel(start.0 as u32, start.1 as u32, colour);
        } else {
            draw_antialiased_line_segment_mut(&mut image, start, end, colour, interpolate);
        }
    }

    // The colour bar: the smallest radius at the bottom, the largest at the top.
    let bar_left = (width + BAR_GAP_PX) as i32;
    for y in 0..height {
        let t = 1.0 - f64::from(y) / f64::from((height - 1).max(1));
        let rect = Rect::at(bar_left, y as i32).of_size(BAR_WIDTH_PX, 1);
        draw_filled_rect_mut(&mut image, rect, colour_of(lo + t * (hi - lo)));
    }
    Plot { image, radius_range }
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

    #[test]
    fn layout_keeps_physical_proportions() {
        // 21 voxels of 2 units down (42), 40 of 1 across (40): down is the long side.
        let ([py, px], (w, h)) = layout([5, 21, 40], [1.0, 2.0, 1.0]);
        assert_eq!((w, h), (762, 800));
        assert!((py / px - 2.0).abs() < 0.01, "a voxel is twice as tall as wide: {py} {px}");
        let (_, (w, h)) = layout([5, 10, 30], [1.0, 1.0, 1.0]);
        assert_eq!((w, h), (800, 267));
    }

    #[test]
    fn edge_colours_follow_the_radius_and_the_bar_spans_the_range() {
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
        let (w, h) = (800, 400);
        assert_eq!(plot.image.dimensions(), (w + BAR_GAP_PX + BAR_WIDTH_PX, h));
        let y = 220; // row of voxel 5's centre: (5 + 0.5) * 40 - 0.5, rounded
        let low = colorous::VIRIDIS.eval_continuous(0.0);
        let high = colorous::VIRIDIS.eval_continuous(1.0);
        assert_eq!(plot.image.get_pixel(200, y), &Rgb([low.r, low.g, low.b]));
        assert_eq!(plot.image.get_pixel(600, y), &Rgb([high.r, high.g, high.b]));
        assert_eq!(plot.image.get_pixel(200, 190), &FOREGROUND);
        assert_eq!(plot.image.get_pixel(200, 50), &BACKGROUND);
        let bar = w + BAR_GAP_PX + BAR_WIDTH_PX / 2;
        assert_eq!(plot.image.get_pixel(bar, h - 1), &Rgb([low.r, low.g, low.b]));
        assert_eq!(plot.image.get_pixel(bar, 0), &Rgb([high.r, high.g, high.b]));
    }
}
