//! Coordinate frames of a graph's positions: the one rule for `coordinates=`
//! (Python) and `--coordinates` (command line).
//!
//! A run gives positions in physical units along the array axes: voxel `(i, j, k)`
//! is at `(i*s0, j*s1, k*s2)` (`"array"`). `"xyz"` reverses the columns, so that x
//! is the last array axis, the order of SWC, VTK, Neuroglancer and ImageJ for a
//! `(z, y, x)` stack; the spacing is reversed with them, so that `spacing[c]`
//! still belongs to column `c`. `"world"` maps each position through the image's
//! 4 × 4 voxel-to-world affine `A`: `A · (p / s, 1)` (the continuous voxel index
//! `p / s`, then the affine); the spacing keeps array axis order. Radii are never
//! changed: they are in the physical units of the spacing, which are the world's
//! when the affine's column lengths equal the spacing (NIfTI's qform, and every
//! format with a spacing only). [`to_frame`] says when they do not.

use std::fmt;
use std::str::FromStr;

/// The coordinate frame of a graph's positions.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Coordinates {
    /// Physical units along array axes 0, 1, 2 (the default).
    #[default]
    Array,
    /// Physical units with x = the last array axis (columns reversed).
    Xyz,
    /// The image's world frame, through its voxel-to-world affine.
    World,
}

impl Coordinates {
    /// The names, as `coordinates=` and `--coordinates` take them.
    pub const NAMES: [&'static str; 3] = ["array", "xyz", "world"];

    /// The name of the frame (`"array"`, `"xyz"`, `"world"`).
    pub fn name(self) -> &'static str {
        match self {
            Coordinates::Array => "array",
            Coordinates::Xyz => "xyz",
            Coordinates::World => "world",
        }
    }
}

impl fmt::Display for Coordinates {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Coordinates {
    type Err = String;

    fn from_str(s: &str) -> Result<Coordinates, String> {
        match s {
            "array" => Ok(Coordinates::Array),
            "xyz" => Ok(Coordinates::Xyz),
            "world" => Ok(Coordinates::World),
            other => Err(format!("coordinates {other:?} must be one of 'array', 'xyz', 'world'")),
        }
    }
}

/// Check a voxel-to-world affine: finite, last row `0 0 0 1`, and an invertible
/// 3 × 3 part (a flat map would put the whole graph on a plane).
pub fn check_affine(affine: &[[f64; 4]; 4]) -> Result<(), String> {
    if affine.iter().flatten().any(|x| !x.is_finite()) {
        return Err(format!("affine {affine:?} must be finite numbers"));
    }
    if affine[3] != [0.0, 0.0, 0.0, 1.0] {
        return Err(format!("affine's last row {:?} must be [0, 0, 0, 1]", affine[3]));
    }
    let m = |r: usize, c: usize| affine[r][c];
    let det = m(0, 0) * (m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1)) - m(0, 1) * (m(1, 0) * m(2, 2) - m(1, 2) * m(2, 0))
        + m(0, 2) * (m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0));
    let scale: f64 = (0..3).map(|c| (0..3).map(|r| m(r, c).abs()).sum::<f64>()).product();
    // Also refuses a NaN determinant (finite entries cannot give one, but say so anyway).
    if det.abs().partial_cmp(&(1e-12 * scale)) != Some(std::cmp::Ordering::Greater) {
        return Err("affine's 3 x 3 part is singular (it maps the volume onto a plane or a line)".to_string());
    }
    Ok(())
}

/// What [`to_frame`] did besides moving the positions.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// The spacing to store with the graph: reversed for [`Coordinates::Xyz`].
    pub spacing: [f64; 3],
    /// A warning for the user, if the radii's units differ from the world's: the
    /// affine's column lengths (its voxel size) are not the spacing.
    pub warning: Option<String>,
}

/// Move `positions` (physical units along array axes, as a run gives them) into
/// the frame `coordinates`, with the run's `spacing` and, for
/// [`Coordinates::World`], the voxel-to-world `affine` (checked by
/// [`check_affine`]; unused by the other frames).
pub fn to_frame(
    positions: &mut [[f64; 3]],
    spacing: [f64; 3],
    coordinates: Coordinates,
    affine: &[[f64; 4]; 4],
) -> Result<Frame, String> {
    match coordinates {
        Coordinates::Array => Ok(Frame { spacing, warning: None }),
        Coordinates::Xyz => {
            for p in positions.iter_mut() {
                p.reverse();
            }
            Ok(Frame { spacing: [spacing[2], spacing[1], spacing[0]], warning: None })
        }
        Coordinates::World => {
            check_affine(affine)?;
            if spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
                return Err(format!("spacing {spacing:?} must be three finite numbers > 0"));
            }
            for p in positions.iter_mut() {
                let voxel = [p[0] / spacing[0], p[1] / spacing[1], p[2] / spacing[2]];
                *p = [0, 1, 2].map(|r| {
                    affine[r][0] * voxel[0] + affine[r][1] * voxel[1] + affine[r][2] * voxel[2] + affine[r][3]
                });
            }
            let lengths = [0, 1, 2].map(|c| (0..3).map(|r| affine[r][c] * affine[r][c]).sum::<f64>().sqrt());
            let off = lengths.iter().zip(spacing).any(|(l, s)| (l - s).abs() > 1e-3 * s);
            let warning = off.then(|| {
                format!(
                    "the affine's voxel size {lengths:?} differs from the spacing {spacing:?}: positions are in \
                     world units, but radii stay in the spacing's units"
                )
            });
            Ok(Frame { spacing, warning })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_move_positions_as_documented() {
        let affine = [[0.0, 0.0, 2.0, 10.0], [0.0, -3.0, 0.0, 20.0], [0.5, 0.0, 0.0, -5.0], [0.0, 0.0, 0.0, 1.0]];
        let spacing = [0.5, 3.0, 2.0];
        let start = [[1.0, 6.0, 8.0]]; // voxel (2, 2, 4)
        let mut p = start;
        assert_eq!(to_frame(&mut p, spacing, Coordinates::Array, &affine).unwrap().spacing, spacing);
        assert_eq!(p, start);
        let frame = to_frame(&mut p, spacing, Coordinates::Xyz, &affine).unwrap();
        assert_eq!((p, frame.spacing), ([[8.0, 6.0, 1.0]], [2.0, 3.0, 0.5]));
        let mut p = start;
        let frame = to_frame(&mut p, spacing, Coordinates::World, &affine).unwrap();
        assert_eq!(p, [[2.0 * 4.0 + 10.0, -3.0 * 2.0 + 20.0, 0.5 * 2.0 - 5.0]]);
        assert_eq!(frame, Frame { spacing, warning: None });
        let mut p = start;
        let warned = to_frame(&mut p, [1.0; 3], Coordinates::World, &affine).unwrap();
        assert!(warned.warning.unwrap().contains("radii"));
    }

    #[test]
    fn bad_affines_and_names_are_refused() {
        let mut flat = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
        assert!(check_affine(&flat).unwrap_err().contains("singular"));
        flat[2][2] = 1.0;
        assert!(check_affine(&flat).is_ok());
        flat[3][0] = 1.0;
        assert!(check_affine(&flat).unwrap_err().contains("last row"));
        flat[3][0] = 0.0;
        flat[0][3] = f64::NAN;
        assert!(check_affine(&flat).unwrap_err().contains("finite"));
        assert!("XYZ".parse::<Coordinates>().unwrap_err().contains("'array', 'xyz', 'world'"));
        assert_eq!("world".parse::<Coordinates>(), Ok(Coordinates::World));
    }
}
