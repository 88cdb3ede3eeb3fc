//! FACE tokenization: quantization, the canonical ZYX order, one split per flat polygon, one
//! token per face, and the one-token-per-coordinate baseline the paper compares against.
//!
//! A mesh in the normalized frame becomes a sorted sequence of [`FaceToken`]s (9 quantized
//! coordinates each); [`detokenize`] turns a sequence back into a welded mesh.

mod error;
mod order;
mod per_coordinate;
mod polygons;
mod quantize;
mod tokens;
mod weld;

pub use error::TokenizeError;
pub use order::{
    FaceToken, ZyxVertex, canonical_face, canonical_start, face_vertices, is_canonical_face,
};
pub use per_coordinate::{
    SequenceStats, faces_from_per_coordinate, per_coordinate_tokens, sequence_stats,
};
pub use polygons::{
    canonical_polygons, canonical_triangulation, canonical_triangulation_near_grid,
};
pub use quantize::{DEFAULT_LEVELS, MAX_LEVELS, MIN_LEVELS, Quantizer};
pub use tokens::{
    Tokenized, detokenize, face_positions, is_canonical_sequence, tokenize, tokenize_mesh,
};
pub use weld::weld_near_corners;
