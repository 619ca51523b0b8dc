//! The crate's error type.

/// Everything that can go wrong when building or running the backbone.
///
/// Bad input is always reported with one of these variants; the crate never panics on user data.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SimError {
    /// Two inputs that must agree in length do not.
    #[error("{what}: expected length {expected}, got {got}")]
    LengthMismatch {
        /// Which input.
        what: &'static str,
        /// The length it must have.
        expected: usize,
        /// The length it has.
        got: usize,
    },
    /// An input holds a NaN or infinite value.
    #[error("{what}[{index}] is not finite")]
    NonFinite {
        /// Which input.
        what: &'static str,
        /// Index of the first bad entry.
        index: usize,
    },
    /// A scalar parameter is out of its valid range.
    #[error("invalid {name} = {value}: {reason}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// The value given.
        value: f64,
        /// What is required.
        reason: &'static str,
    },
    /// A `held` entry is below -1 or names a gripper the actions do not have.
    #[error("held[{index}] = {value} is invalid ({reason})")]
    InvalidHeld {
        /// Particle index.
        index: usize,
        /// The gripper index given.
        value: i64,
        /// What is required.
        reason: &'static str,
    },
    /// The scratch space was made by a backbone of another size.
    #[error(
        "scratch was made for {scratch_particles} particles / {scratch_springs} springs, backbone has {particles} / {springs}"
    )]
    ScratchMismatch {
        /// Particles the scratch was made for.
        scratch_particles: usize,
        /// Springs the scratch was made for.
        scratch_springs: usize,
        /// Particles of the backbone it is used with.
        particles: usize,
        /// Springs of the backbone it is used with.
        springs: usize,
    },
    /// A request would need more memory or work than the crate allows.
    #[error("{what} too large: {value} (limit {limit})")]
    TooLarge {
        /// What is too large.
        what: &'static str,
        /// The requested amount.
        value: u64,
        /// The limit.
        limit: u64,
    },
    /// The simulation became non-finite or absurd (|x| or |v| above [`crate::DIVERGENCE_LIMIT`]).
    #[error(
        "simulation diverged at step {step} (particle {particle}): position or velocity non-finite or beyond the limit"
    )]
    Diverged {
        /// Index of the model step that failed (counted from the start of the rollout or scratch).
        step: usize,
        /// First offending particle.
        particle: usize,
    },
    /// A [`crate::StepTape`] does not belong to the backbone it is used with, or its step did
    /// not complete.
    #[error("step tape: {reason}")]
    TapeMismatch {
        /// What does not match.
        reason: &'static str,
    },
    /// An [`crate::Effect`] rejected its setup.
    #[error("effect {name}: {message}")]
    Effect {
        /// The effect's name.
        name: String,
        /// Its message.
        message: String,
    },
}
