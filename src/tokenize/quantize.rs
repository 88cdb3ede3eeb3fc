use super::{FaceToken, TokenizeError};

/// The fewest quantization levels the model supports (the paper's default).
pub const MIN_LEVELS: u16 = 128;
/// The most quantization levels the model supports (the paper's large model).
pub const MAX_LEVELS: u16 = 1024;
/// The quantization of DESIGN.md unless a model says otherwise.
pub const DEFAULT_LEVELS: u16 = 128;

/// Uniform quantization of the normalized frame [-1, 1] into `levels` cells per axis.
///
/// Serialized as the plain number of levels; deserializing checks the range like
/// [`Quantizer::new`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "u16", into = "u16")]
pub struct Quantizer {
    levels: u16,
}

impl Quantizer {
    /// A quantizer with `levels` cells per axis, `MIN_LEVELS..=MAX_LEVELS`.
    pub fn new(levels: u16) -> Result<Self, TokenizeError> {
        if (MIN_LEVELS..=MAX_LEVELS).contains(&levels) {
            Ok(Self { levels })
        } else {
            Err(TokenizeError::InvalidLevels { levels })
        }
    }

    pub fn levels(&self) -> u16 {
        self.levels
    }

    /// `q = clamp(round((x + 1) / 2 * (Q - 1)), 0, Q - 1)`.
    ///
    /// Callers validate finiteness (`Mesh::validate`); a NaN still must not panic here, and maps
    /// to 0 (the saturating float-to-int cast does that, and clamps infinities to the ends).
    pub fn quantize(&self, x: f32) -> u16 {
        let top = f64::from(self.levels - 1);
        // f64 so that the rounding boundary is exact for every f32 input.
        let q = ((f64::from(x) + 1.0) / 2.0 * top).round().clamp(0.0, top);
        q as u16
    }

    /// `x = q / (Q - 1) * 2 - 1`, the centre of cell `q`. A `q` past the last level (a token the
    /// caller did not check with [`Quantizer::fits`]) is clamped to the last level, so the
    /// result always lies in [-1, 1].
    pub fn dequantize(&self, q: u16) -> f32 {
        let top = f64::from(self.levels - 1);
        (f64::from(q.min(self.levels - 1)) / top * 2.0 - 1.0) as f32
    }

    /// Whether every coordinate of the face is a level of this quantizer.
    pub fn fits(&self, face: &FaceToken) -> bool {
        face.iter().all(|&c| c < self.levels)
    }
}

impl Default for Quantizer {
    fn default() -> Self {
        Self { levels: DEFAULT_LEVELS }
    }
}

impl TryFrom<u16> for Quantizer {
    type Error = TokenizeError;

    fn try_from(levels: u16) -> Result<Self, Self::Error> {
        Self::new(levels)
    }
}

impl From<Quantizer> for u16 {
    fn from(q: Quantizer) -> u16 {
        q.levels
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn levels_out_of_range_are_rejected() {
        assert!(Quantizer::new(127).is_err());
        assert!(Quantizer::new(1025).is_err());
        assert_eq!(Quantizer::new(128).unwrap().levels(), 128);
        assert_eq!(Quantizer::new(1024).unwrap().levels(), 1024);
        assert_eq!(Quantizer::default().levels(), DEFAULT_LEVELS);
    }

    #[test]
    fn hand_computed_values_at_128_levels() {
        let q = Quantizer::new(128).unwrap();
        // (x + 1) / 2 * 127: -1 -> 0, 1 -> 127, 0 -> 63.5 -> 64 (round half away from zero).
        assert_eq!(q.quantize(-1.0), 0);
        assert_eq!(q.quantize(1.0), 127);
        assert_eq!(q.quantize(0.0), 64);
        assert_eq!(q.quantize(0.5), 95); // 95.25
        assert_eq!(q.quantize(-2.0), 0);
        assert_eq!(q.quantize(7.0), 127);
        assert_eq!(q.dequantize(0), -1.0);
        assert_eq!(q.dequantize(127), 1.0);
        assert_eq!(q.dequantize(300), 1.0);
        assert!((q.dequantize(64) - (64.0 / 127.0 * 2.0 - 1.0)).abs() < 1e-7);
    }

    #[test]
    fn non_finite_inputs_do_not_panic() {
        let q = Quantizer::default();
        assert_eq!(q.quantize(f32::NAN), 0);
        assert_eq!(q.quantize(f32::INFINITY), 127);
        assert_eq!(q.quantize(f32::NEG_INFINITY), 0);
    }

    #[test]
    fn serde_is_the_number_of_levels_and_checks_it() {
        let q = Quantizer::new(256).unwrap();
        assert_eq!(serde_json::to_string(&q).unwrap(), "256");
        assert_eq!(serde_json::from_str::<Quantizer>("256").unwrap(), q);
        assert!(serde_json::from_str::<Quantizer>("64").is_err());
    }

    #[test]
    fn fits_checks_every_coordinate() {
        let q = Quantizer::default();
        assert!(q.fits(&[127; 9]));
        assert!(!q.fits(&[0, 0, 0, 0, 0, 0, 0, 0, 128]));
    }

    proptest! {
        #[test]
        fn dequantize_then_quantize_is_identity(levels in MIN_LEVELS..=MAX_LEVELS, q in 0u16..1024) {
            let quant = Quantizer::new(levels).unwrap();
            let q = q % levels;
            prop_assert_eq!(quant.quantize(quant.dequantize(q)), q);
        }

        #[test]
        fn quantization_error_is_at_most_half_a_cell(levels in MIN_LEVELS..=MAX_LEVELS, x in -1f32..=1.0) {
            let quant = Quantizer::new(levels).unwrap();
            let half_cell = 1.0 / f32::from(levels - 1);
            prop_assert!((quant.dequantize(quant.quantize(x)) - x).abs() <= half_cell * 1.0001);
        }
    }
}
