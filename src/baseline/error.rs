/// Everything that can go wrong building a baseline surface from points.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BaselineError {
    #[error("{method} needs at least {needed} distinct points, got {got}")]
    TooFewPoints { method: &'static str, needed: usize, got: usize },
    #[error("point {index} has a non-finite coordinate")]
    NonFinite { index: usize },
    /// The points span fewer than three dimensions: a closed surface around them has no volume.
    #[error("the points are {0}: there is no closed surface around them")]
    Flat(&'static str),
    #[error("{normals} normals for {points} points (Poisson needs one normal per point)")]
    NormalCount { normals: usize, points: usize },
    #[error("invalid mesh: {0}")]
    InvalidMesh(String),
    #[error("invalid option: {0}")]
    InvalidOption(String),
    #[error("the convex hull failed: {0}")]
    Hull(String),
    /// The Poisson crate asserts and unwraps internally; an input that trips one of those is
    /// reported here instead of taking the process down.
    #[error("the Poisson solver failed: {0}")]
    PoissonFailed(String),
    #[error("Poisson reconstruction produced no surface")]
    EmptySurface,
    #[error("simplification left no faces")]
    SimplifiedAway,
    #[error("simplification left {faces} faces, over the budget of {budget}")]
    OverBudget { faces: usize, budget: usize },
}
