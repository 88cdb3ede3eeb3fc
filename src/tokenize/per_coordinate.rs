//! The comparison baseline of the paper: one token per coordinate (9 per face), and the
//! sequence lengths of both representations.

use super::{FaceToken, TokenizeError};

/// Tokens per face in the per-coordinate baseline.
const COORDS_PER_FACE: usize = 9;

/// The baseline sequence: the faces' coordinates flattened, length 9N.
pub fn per_coordinate_tokens(faces: &[FaceToken]) -> Vec<u16> {
    faces.as_flattened().to_vec()
}

/// The inverse of [`per_coordinate_tokens`]; an error unless the length is a multiple of 9.
pub fn faces_from_per_coordinate(tokens: &[u16]) -> Result<Vec<FaceToken>, TokenizeError> {
    let (faces, rest) = tokens.as_chunks::<COORDS_PER_FACE>();
    if rest.is_empty() {
        Ok(faces.to_vec())
    } else {
        Err(TokenizeError::PerCoordinateLength { len: tokens.len() })
    }
}

/// Sequence lengths of one mesh under both representations.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SequenceStats {
    pub faces: usize,
    /// Positions the decoder's attention processes with one token per face. The start token
    /// is NOT counted (nor an end token in the baseline), so that the ratio is the 1/9 of
    /// DESIGN.md and the paper rather than (N + 1) / 9N.
    pub face_sequence_len: usize,
    /// Positions of the per-coordinate baseline: 9 per face.
    pub per_coordinate_len: usize,
    /// `face_sequence_len / per_coordinate_len`; 1/9 for an empty mesh too, since the ratio is
    /// one of the two encodings per face.
    pub compression_ratio: f64,
}

pub fn sequence_stats(faces: &[FaceToken]) -> SequenceStats {
    let face_sequence_len = faces.len();
    let per_coordinate_len = COORDS_PER_FACE * faces.len();
    let compression_ratio = if per_coordinate_len == 0 {
        1.0 / COORDS_PER_FACE as f64
    } else {
        face_sequence_len as f64 / per_coordinate_len as f64
    };
    SequenceStats { faces: faces.len(), face_sequence_len, per_coordinate_len, compression_ratio }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn lengths_not_a_multiple_of_nine_are_errors() {
        assert!(faces_from_per_coordinate(&[0; 10]).is_err());
        assert!(faces_from_per_coordinate(&[0; 8]).is_err());
        assert_eq!(faces_from_per_coordinate(&[]).unwrap(), Vec::<FaceToken>::new());
    }

    #[test]
    fn stats_of_a_small_sequence() {
        let s = sequence_stats(&[[0; 9], [1; 9], [2; 9]]);
        assert_eq!((s.faces, s.face_sequence_len, s.per_coordinate_len), (3, 3, 27));
        assert!((s.compression_ratio - 1.0 / 9.0).abs() < 1e-15);
        assert!((sequence_stats(&[]).compression_ratio - 1.0 / 9.0).abs() < 1e-15);
    }

    proptest! {
        #[test]
        fn per_coordinate_round_trip(faces in prop::collection::vec(prop::array::uniform9(0u16..1024), 0..40)) {
            let tokens = per_coordinate_tokens(&faces);
            prop_assert_eq!(tokens.len(), 9 * faces.len());
            prop_assert_eq!(&tokens[..], faces.as_flattened());
            prop_assert_eq!(faces_from_per_coordinate(&tokens).unwrap(), faces);
        }
    }
}
