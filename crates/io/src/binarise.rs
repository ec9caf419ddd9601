//! The input rule: which images are vessel masks, and how to make a mask of any
//! other image. Every entry point applies it (the command-line readers while they
//! stream a file, `vesselflow.skeletonize` and `vesselflow.load_volume` through
//! `vesselflow._core`), so a file means the same thing however it is read.
//!
//! With no choice given ([`MaskRule::Binary`]) an image is a mask if it is bool,
//! integer with at most one non-zero value (0 and v, v = vessel), or floating point
//! with every value exactly 0 or 1. Anything else (a label image with two or more
//! non-zero values, a probability map, an intensity image, NaN) is refused: the
//! caller says how to binarise it, with a threshold (mask = data > t) or a label
//! (mask = data == v).

use std::fmt::Display;

/// How an image becomes a mask.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum MaskRule {
    /// The image must already be binary (see the module documentation); non-zero = vessel.
    #[default]
    Binary,
    /// Vessel where the value is greater than this.
    Threshold(f64),
    /// Vessel where the value equals this.
    Label(f64),
}

/// What to tell a user whose image is not a mask.
pub const MASK_ADVICE: &str = "pass threshold=T (CLI: --threshold T; mask = data > T) or label=V \
     (CLI: --label V; mask = data == V) to say how to binarise it";

impl MaskRule {
    /// The rule for optional `threshold` and `label` arguments; both at once is an error.
    pub fn new(threshold: Option<f64>, label: Option<f64>) -> Result<MaskRule, String> {
        for (name, value) in [("threshold", threshold), ("label", label)] {
            if value.is_some_and(|v| !v.is_finite()) {
                return Err(format!("{name}= must be a finite number, got {}", value.unwrap_or_default()));
            }
        }
        match (threshold, label) {
            (Some(_), Some(_)) => Err("pass threshold= or label=, not both".to_string()),
            (Some(t), None) => Ok(MaskRule::Threshold(t)),
            (None, Some(v)) => Ok(MaskRule::Label(v)),
            (None, None) => Ok(MaskRule::Binary),
        }
    }
}

/// A value type an image may hold.
pub trait Sample: Copy + PartialEq + Display {
    /// Its name as NumPy spells it (`uint8`, `float32`, ...).
    const NAME: &'static str;
    /// Floating point (must be 0 or 1 to be a mask) rather than bool or integer.
    const FLOAT: bool;
    /// The value as `f64`, for thresholds and labels (exact for integers below 2^53).
    fn to_f64(self) -> f64;
    /// True for 0 (or `false`).
    fn is_zero(self) -> bool;
}

impl Sample for bool {
    const NAME: &'static str = "bool";
    const FLOAT: bool = false;
    fn to_f64(self) -> f64 {
        f64::from(u8::from(self))
    }
    fn is_zero(self) -> bool {
        !self
    }
}

macro_rules! sample {
    ($float:expr, $($t:ty => $name:literal),*) => {$(
        impl Sample for $t {
            const NAME: &'static str = $name;
            const FLOAT: bool = $float;
            fn to_f64(self) -> f64 {
                self as f64
            }
            fn is_zero(self) -> bool {
                self == (0 as $t)
            }
        }
    )*};
}
sample!(false, u8 => "uint8", i8 => "int8", u16 => "uint16", i16 => "int16", u32 => "uint32",
    i32 => "int32", u64 => "uint64", i64 => "int64");
sample!(true, f32 => "float32", f64 => "float64");

/// [`MaskRule`] applied to a stream of values of type `T`, one chunk at a time: each
/// value becomes 1 (vessel) or 0, and [`Binariser::finish`] says whether the image
/// was a mask. Under [`MaskRule::Binary`] it remembers at most two distinct non-zero
/// integers and the first float other than 0 and 1, so it takes constant memory.
#[derive(Debug, Clone)]
pub struct Binariser<T: Sample> {
    rule: MaskRule,
    first: Option<T>,
    offending: Option<T>,
}

impl<T: Sample> Binariser<T> {
    /// A binariser of values of type `T` by `rule`.
    pub fn new(rule: MaskRule) -> Self {
        Binariser { rule, first: None, offending: None }
    }

    /// 1 if `x` is vessel, else 0.
    #[inline]
    pub fn vessel(&mut self, x: T) -> u8 {
        u8::from(match self.rule {
            MaskRule::Threshold(t) => x.to_f64() > t,
            MaskRule::Label(v) => x.to_f64() == v,
            MaskRule::Binary if x.is_zero() => false,
            MaskRule::Binary if T::FLOAT => {
                if x.to_f64() != 1.0 && self.offending.is_none() {
                    self.offending = Some(x);
                }
                x.to_f64() == 1.0
            }
            MaskRule::Binary => {
                match self.first {
                    None => self.first = Some(x),
                    Some(f) if f != x && self.offending.is_none() => self.offending = Some(x),
                    Some(_) => {}
                }
                true
            }
        })
    }

    /// Append the mask of `values` to `out`.
    pub fn extend(&mut self, values: impl IntoIterator<Item = T>, out: &mut Vec<u8>) {
        out.extend(values.into_iter().map(|x| self.vessel(x)));
    }

    /// Under [`MaskRule::Binary`], the one non-zero integer seen so far (`None` if
    /// none, or for floats).
    pub fn vessel_value(&self) -> Option<T> {
        self.first
    }

    /// True once the image is known not to be a mask (the caller may stop reading).
    pub fn refused(&self) -> bool {
        self.offending.is_some()
    }

    /// `Ok` if every value seen so far fits the rule, else why the image is not a
    /// mask: the values found, and [`MASK_ADVICE`].
    pub fn finish(&self) -> Result<(), String> {
        match (self.offending, self.first) {
            (None, _) => Ok(()),
            (Some(x), _) if T::FLOAT => Err(format!(
                "not a binary mask: {} values other than 0 and 1 (e.g. {x}): a probability or \
                 intensity image; {MASK_ADVICE}",
                T::NAME
            )),
            (Some(x), first) => Err(format!(
                "not a binary mask: {} values 0, {} and {x} (at least two non-zero values): a label \
                 or intensity image; {MASK_ADVICE}",
                T::NAME,
                first.map_or_else(String::new, |f| f.to_string())
            )),
        }
    }
}

/// The mask of all of `values` by `rule` (1 = vessel), or why it is not one.
///
/// ```
/// use vesselflow_io::{binarise, MaskRule};
///
/// assert_eq!(binarise([0.0f32, 1.0, 1.0], MaskRule::Binary).unwrap(), [0, 1, 1]);
/// assert!(binarise([0u8, 3, 6], MaskRule::Binary).unwrap_err().contains("label="));
/// assert_eq!(binarise([0u8, 3, 6], MaskRule::Label(3.0)).unwrap(), [0, 1, 0]);
/// assert_eq!(binarise([0.2, 0.7], MaskRule::Threshold(0.5)).unwrap(), [0, 1]);
/// ```
pub fn binarise<T: Sample>(values: impl IntoIterator<Item = T>, rule: MaskRule) -> Result<Vec<u8>, String> {
    let mut binariser = Binariser::new(rule);
    let mut out = Vec::new();
    binariser.extend(values, &mut out);
    binariser.finish().map(|()| out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn binary_images_are_masks() {
        assert_eq!(binarise([false, true], MaskRule::Binary).unwrap(), [0, 1]);
        assert_eq!(binarise([0i16, -4, -4], MaskRule::Binary).unwrap(), [0, 1, 1]);
        assert_eq!(binarise([7u64, 7], MaskRule::Binary).unwrap(), [1, 1]);
        assert_eq!(binarise([0.0f64, -0.0, 1.0], MaskRule::Binary).unwrap(), [0, 0, 1]);
    }

    #[test]
    fn other_images_are_refused_naming_the_values() {
        let label = binarise([0u8, 3, 3, 6, 5], MaskRule::Binary).unwrap_err();
        assert!(label.contains("uint8 values 0, 3 and 6"), "{label}");
        assert!(label.contains("threshold=") && label.contains("label="), "{label}");
        let map = binarise([0.0f32, 1.0, 0.25], MaskRule::Binary).unwrap_err();
        assert!(map.contains("float32 values other than 0 and 1 (e.g. 0.25)"), "{map}");
        let nan = binarise([0.0f64, f64::NAN], MaskRule::Binary).unwrap_err();
        assert!(nan.contains("NaN"), "{nan}");
    }

    #[test]
    fn threshold_and_label_binarise_anything() {
        assert_eq!(binarise([0u8, 3, 6], MaskRule::Label(6.0)).unwrap(), [0, 0, 1]);
        assert_eq!(binarise([0.2f32, 0.5, 0.9, f32::NAN], MaskRule::Threshold(0.5)).unwrap(), [0, 0, 1, 0]);
        assert_eq!(MaskRule::new(Some(0.5), None), Ok(MaskRule::Threshold(0.5)));
        assert!(MaskRule::new(Some(0.5), Some(1.0)).unwrap_err().contains("not both"));
        assert!(MaskRule::new(None, Some(f64::NAN)).unwrap_err().contains("label= must be a finite number, got NaN"));
    }
}
