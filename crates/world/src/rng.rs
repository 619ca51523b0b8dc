//! Seeding: every random stream is derived from the user's seed and a fixed tag path, so results
//! do not depend on thread scheduling or on the order in which streams are created.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// SplitMix64 finaliser: a bijective mix with good avalanche, used to combine seeds and tags.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Tags naming the independent random streams of a dataset.
pub(crate) mod tag {
    pub const OBJECT: u64 = 1;
    pub const TRACKED: u64 = 2;
    pub const MOTION: u64 = 4;
    pub const PLACEMENT: u64 = 5;
    pub const OBSERVATION: u64 = 6;
}

/// A ChaCha8 stream for `seed` and the tag path `tags`.
pub(crate) fn stream(seed: u64, tags: &[u64]) -> ChaCha8Rng {
    let mut s = mix(seed);
    for &t in tags {
        s = mix(s ^ mix(t.wrapping_add(0x51_7CC1_B727_220A)));
    }
    ChaCha8Rng::seed_from_u64(s)
}
