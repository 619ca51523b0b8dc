use crate::SceneError;

/// Which frames a rollout starts from and predicts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Window {
    /// Frame the rollout starts from (its state is given; earlier frames are history).
    pub start: usize,
    /// Number of model steps predicted: frames `start + 1 ..= start + steps`.
    pub steps: usize,
}

/// An evaluation protocol.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Protocol {
    /// The paper's: two history frames (0, 1), start at frame 2, predict 37 steps
    /// (frames 3..=39 of a 40-frame, 4 s episode at 10 fps).
    #[default]
    Paper,
    /// DEFORM's: start from frames 0 and 1 (velocity by finite difference) and predict every
    /// remaining frame (498 steps for a 500-frame file).
    Deform,
}

/// Steps the paper protocol predicts.
pub const PAPER_STEPS: usize = 37;

impl Protocol {
    /// The window of this protocol for an episode of `frames` frames.
    pub fn window(self, frames: usize) -> Result<Window, SceneError> {
        let (start, steps, needed, protocol) = match self {
            Protocol::Paper => (2, PAPER_STEPS, 2 + PAPER_STEPS + 1, "paper"),
            Protocol::Deform => (1, frames.saturating_sub(2), 3, "deform"),
        };
        if frames < needed {
            return Err(SceneError::TooShort {
                frames,
                needed,
                protocol,
            });
        }
        Ok(Window { start, steps })
    }

    /// Name used on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Protocol::Paper => "paper",
            Protocol::Deform => "deform",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows() {
        assert_eq!(
            Protocol::Paper.window(40).unwrap(),
            Window {
                start: 2,
                steps: 37
            }
        );
        assert!(Protocol::Paper.window(39).is_err());
        assert_eq!(
            Protocol::Deform.window(500).unwrap(),
            Window {
                start: 1,
                steps: 498
            }
        );
        assert!(Protocol::Deform.window(2).is_err());
    }
}
